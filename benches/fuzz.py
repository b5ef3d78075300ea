"""Long fuzz run of the codebook loader and estimate()'s input path, with the
strategies and checks of tests/test_fuzz.py (which runs a short, derandomised
version in CI).

    .venv/bin/python benches/fuzz.py --seconds 600

Every input must give a valid codebook / finite pose or an EdgePoseError; any
other exception stops the run with hypothesis' minimal failing example, and a
hang trips the faulthandler watchdog (stack dump, exit). Prints how many
inputs were tried, the outcomes, and the RSS before and after.

That RSS grows with hypothesis' own bookkeeping: the same strategies with
no edgepose call grew it by as much (+65 % against +61 % in 300 s,
2026-11-26). So the leak check is a replay: some of the generated inputs
are kept, then fed again in a plain loop (``--replay`` passes), and the
RSS growth over those passes is edgepose's.
"""

from __future__ import annotations

import argparse
import collections
import copy
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import edgepose  # noqa: E402
import test_fuzz  # noqa: E402
from edgepose.eval import render_view  # noqa: E402
from edgepose.model import read_mesh  # noqa: E402
from hypothesis import given, settings  # noqa: E402


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=600.0, help="total budget, split between the two targets")
    parser.add_argument("--mesh", type=Path, default=ROOT.parent / "shared" / "data" / "ycb" / "power_drill.ply")
    parser.add_argument("--batch", type=int, default=200, help="examples per hypothesis run")
    parser.add_argument("--keep", type=int, default=200, help="inputs of each target kept for the replay")
    parser.add_argument("--replay", type=int, default=5, help="passes over the kept inputs (0: no replay)")
    args = parser.parse_args()

    mesh = read_mesh(args.mesh)
    codebook = edgepose.build_codebook(mesh)
    cloud = render_view(mesh, seed=2).cloud
    workdir = Path(tempfile.mkdtemp(prefix="edgepose-fuzz-"))
    codebook.save(workdir / "good.codebook")
    blob = (workdir / "good.codebook").read_bytes()
    damaged_path = workdir / "damaged.codebook"

    tally: dict[str, collections.Counter] = {"load": collections.Counter(), "estimate": collections.Counter()}
    kept: dict[str, list] = {"load": [], "estimate": []}

    def keep(target: str, value: object) -> None:
        """Keeps the first ``--keep`` inputs (with ``--keep`` <= ``--batch``,
        all drawn in the warm-up, before the RSS is read)."""
        if len(kept[target]) < args.keep:
            kept[target].append(copy.deepcopy(value))

    fuzz = settings(max_examples=args.batch, derandomize=False, **test_fuzz.FUZZ_SETTINGS)

    @fuzz
    @given(damaged=test_fuzz.damaged_codebooks(blob))
    def fuzz_load(damaged):
        keep("load", damaged)
        tally["load"][test_fuzz.check_load(damaged, damaged_path, codebook)] += 1

    @fuzz
    @given(value=test_fuzz.estimate_inputs(cloud))
    def fuzz_estimate(value):
        keep("estimate", value)
        tally["estimate"][test_fuzz.check_estimate(value, codebook)] += 1

    fuzz_load()  # warm-up: allocator pools, onnxruntime arenas
    fuzz_estimate()
    rss_start, t0 = rss_mb(), time.perf_counter()
    half = t0 + args.seconds / 2
    while time.perf_counter() < half:
        fuzz_load()
    while time.perf_counter() < t0 + args.seconds:
        fuzz_estimate()
    elapsed, rss_end = time.perf_counter() - t0, rss_mb()

    for target, counts in tally.items():
        total = sum(counts.values())
        print(f"{target}: {total} inputs, " + ", ".join(f"{k} {v}" for k, v in counts.most_common()))
    print(
        f"{elapsed:.0f} s, zero failures; RSS after warm-up {rss_start:.1f} MB, at end {rss_end:.1f} MB "
        f"({100 * (rss_end - rss_start) / rss_start:+.1f} %; hypothesis' bookkeeping included)"
    )
    if args.replay > 0:
        replay(kept, damaged_path, codebook, args.replay)


def replay(kept: dict[str, list], damaged_path: Path, codebook: edgepose.Codebook, passes: int) -> None:
    """Feeds the kept inputs again, ``passes`` times, in a plain loop; the
    first pass warms up, the RSS growth over the others is edgepose's."""

    def one_pass() -> None:
        for damaged in kept["load"]:
            test_fuzz.check_load(damaged, damaged_path, codebook)
        for value in kept["estimate"]:
            test_fuzz.check_estimate(value, codebook)

    one_pass()
    rss_start = rss_mb()
    for _ in range(passes - 1):
        one_pass()
    rss_end = rss_mb()
    calls = (passes - 1) * (len(kept["load"]) + len(kept["estimate"]))
    print(
        f"replay: {len(kept['load'])} codebooks and {len(kept['estimate'])} estimate inputs, "
        f"{passes} passes in a plain loop; RSS over the last {passes - 1} ({calls} calls): "
        f"{rss_start:.1f} -> {rss_end:.1f} MB ({rss_end - rss_start:+.1f} MB)"
    )


if __name__ == "__main__":
    main()
