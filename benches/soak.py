"""Soak test: many consecutive estimates on one codebook, with the process's
resident memory (RSS) after warm-up and at the end, and the latency.

    .venv/bin/python benches/soak.py                  # 10,000 estimates
    .venv/bin/python benches/soak.py --estimates 2000 --threads 8

Memory must stay flat (growth ≤ 5 % after warm-up; the script exits 1
otherwise). With ``--threads`` the same clouds are also estimated from that
many threads at once and the poses compared bit for bit with the serial ones.
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import edgepose
import numpy as np
from edgepose.eval import render_view
from edgepose.model import read_mesh

ROOT = Path(__file__).resolve().parents[1]


def rss_mb() -> float:
    """Resident set size now (Linux /proc), MB."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--estimates", type=int, default=10_000)
    parser.add_argument("--warmup", type=int, default=500)
    parser.add_argument("--views", type=int, default=50, help="distinct rendered clouds, used in turn")
    parser.add_argument("--threads", type=int, default=0, help="also compare a threaded run with this many threads")
    parser.add_argument("--mesh", type=Path, default=ROOT.parent / "shared" / "data" / "ycb" / "power_drill.ply")
    args = parser.parse_args()

    mesh = read_mesh(args.mesh)
    codebook = edgepose.build_codebook(mesh)
    clouds = [render_view(mesh, seed=s).cloud for s in range(args.views)]

    for i in range(args.warmup):
        edgepose.estimate(clouds[i % len(clouds)], codebook)
    gc.collect()
    rss_warm = rss_mb()
    print(f"after {args.warmup} warm-up estimates: RSS {rss_warm:.1f} MB")

    latencies = np.empty(args.estimates)
    checkpoint = max(1, args.estimates // 5)
    for i in range(args.estimates):
        t = time.perf_counter()
        edgepose.estimate(clouds[i % len(clouds)], codebook)
        latencies[i] = time.perf_counter() - t
        if (i + 1) % checkpoint == 0:
            print(f"  {i + 1:>6} estimates: RSS {rss_mb():.1f} MB")
    gc.collect()
    rss_end = rss_mb()
    growth = 100 * (rss_end - rss_warm) / rss_warm
    print(
        f"{args.estimates} estimates: RSS {rss_warm:.1f} → {rss_end:.1f} MB ({growth:+.2f} %); "
        f"latency median {1e3 * np.median(latencies):.2f} ms, p99 {1e3 * np.percentile(latencies, 99):.2f} ms"
    )

    ok = growth <= 5.0
    if args.threads:
        serial = [edgepose.estimate(c, codebook).matrix for c in clouds]
        t = time.perf_counter()
        with ThreadPoolExecutor(max_workers=args.threads) as pool:
            threaded = list(pool.map(lambda c: edgepose.estimate(c, codebook).matrix, clouds * 4))
        elapsed = time.perf_counter() - t
        same = all(np.array_equal(a, serial[i % len(clouds)]) for i, a in enumerate(threaded))
        print(
            f"{args.threads} threads: {len(threaded)} estimates in {elapsed:.2f} s "
            f"({1e3 * elapsed / len(threaded):.2f} ms each), poses identical to serial: {same}"
        )
        ok &= same
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
