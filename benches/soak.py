"""Soak test of the real pipeline: ``estimate`` (from the cloud, and given the
frame), ``estimate_many`` and the ``Tracker``, on real frames
(``../shared/data/ycbv_real``) and synthetic views, called over and over
from the main thread, from a pool of threads and from forked processes,
for ``--minutes``.

    .venv/bin/python benches/soak.py --minutes 30

Every result is compared bit for bit with the serial one (poses, and the
trackers' poses frame by frame). The process's resident memory (RSS), open
files and threads are sampled after each round; after the warm-up rounds
they must stay flat (RSS within ``--rss-tolerance`` %, files and threads
equal), else the script exits 1. The RSS is read after ``gc.collect()``
and glibc's ``malloc_trim(0)``: memory still held, not the free lists that
the allocator's per-thread arenas keep (those swing by a few % from round
to round with the threads). Prints one line per sample and a summary.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import multiprocessing
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import edgepose
import numpy as np
from edgepose.eval import render_view
from edgepose.eval.bop import BopDataset
from edgepose.eval.bop_run import bop_codebooks
from edgepose.eval.real import target_instances
from edgepose.model import read_mesh

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "ycbv_real"


def rss_mb() -> float:
    """Resident set size now (Linux /proc), MB."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def held_mb() -> float:
    """:func:`rss_mb` after freeing what can be freed: Python's cycles and
    glibc's cached free memory."""
    gc.collect()
    ctypes.CDLL("libc.so.6").malloc_trim(0)
    return rss_mb()


def open_files() -> int:
    return len(os.listdir("/proc/self/fd"))


def threads() -> int:
    with open("/proc/self/status") as f:
        return int(next(line for line in f if line.startswith("Threads:")).split()[1])


class Work:
    """The soak's inputs: a list of jobs, each a function of nothing that
    returns arrays (poses), run the same way serially, threaded or forked."""

    def __init__(self, real_images: int, views: int) -> None:
        mesh = read_mesh(ROOT / "codebooks" / "power_drill.ply")
        drill = edgepose.Codebook.load(ROOT / "codebooks" / "power_drill.codebook")
        self.jobs: list[tuple[str, object]] = []
        for seed in range(views):
            view = render_view(mesh, seed=seed)
            self.jobs.append(("synthetic estimate", (view.cloud, drill, None)))
        if REAL.is_dir():
            dataset = BopDataset(REAL)
            targets = dataset.targets()
            codebooks = bop_codebooks(
                dataset, sorted({t.obj_id for t in targets}), ROOT / "benches" / ".cache" / f"{dataset.name}_codebooks"
            )
            images: dict[tuple[int, int], list] = {}
            for image, gt_id, obj_id in target_instances(dataset, targets):
                images.setdefault((image.scene_id, image.im_id), [image, []])[1].append((gt_id, obj_id))
            for image, instances in list(images.values())[:real_images]:
                depth = image.depth()
                masks = [(image.mask(gt_id), codebooks[obj_id]) for gt_id, obj_id in instances]
                for mask, codebook in masks:
                    cloud = edgepose.cloud_from_depth(depth, image.K, mask, depth_scale=1.0)
                    self.jobs.append(("real estimate", (cloud, codebook, None)))
                    self.jobs.append(("real estimate+frame", (cloud, codebook, (depth, image.K))))
                self.jobs.append(("real estimate_many", (depth, image.K, masks)))
                # A short clip: the same object over this image and the next ones of its scene.
                frames = []
                for im_id in dataset.image_ids(image.scene_id):
                    if im_id >= image.im_id and len(frames) < 5:
                        other = dataset.image(image.scene_id, im_id)
                        gt = next((g for g in other.gts if g.obj_id == instances[0][1]), None)
                        if gt is not None:
                            frames.append((other.depth(), other.K, other.mask(gt.gt_id)))
                self.jobs.append(("real tracker", (codebooks[instances[0][1]], frames)))

    def run(self, i: int) -> list[np.ndarray]:
        kind, job = self.jobs[i]
        if kind.endswith("estimate_many"):
            depth, K, masks = job
            frame = edgepose.estimate_many(depth, K, masks, depth_scale=1.0, workers=1)
            return [p.matrix if p is not None else np.full((4, 4), np.nan) for p in frame.poses]
        if kind.endswith("tracker"):
            codebook, frames = job
            tracker = edgepose.Tracker(codebook)
            return [tracker.update_depth(d, K, m, depth_scale=1.0).matrix for d, K, m in frames]
        cloud, codebook, frame = job
        extra = {} if frame is None else {"depth": frame[0], "K": frame[1], "depth_scale": 1.0}
        return [edgepose.estimate(cloud, codebook, **extra).matrix]


WORK: Work | None = None  # set before forking: the children inherit it


def _forked(indices: list[int]) -> list[list[np.ndarray]]:
    assert WORK is not None
    return [WORK.run(i) for i in indices]


def same(a: list[np.ndarray], b: list[np.ndarray]) -> bool:
    return len(a) == len(b) and all(np.array_equal(x, y, equal_nan=True) for x, y in zip(a, b))


def main() -> int:
    global WORK
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--warmup-minutes", type=float, default=3.0, help="minutes before the memory baseline")
    parser.add_argument("--threads", type=int, default=4)
    parser.add_argument("--processes", type=int, default=2, help="forked processes per round")
    parser.add_argument("--real-images", type=int, default=12, help="real images used (their objects, clips)")
    parser.add_argument("--views", type=int, default=12, help="synthetic views of the shipped drill")
    parser.add_argument("--rss-tolerance", type=float, default=1.0, help="allowed RSS growth after warm-up, %%")
    args = parser.parse_args()

    WORK = Work(args.real_images, args.views)
    jobs = range(len(WORK.jobs))
    kinds = sorted({kind for kind, _ in WORK.jobs})
    print(f"{len(WORK.jobs)} jobs: " + ", ".join(f"{k} {sum(j[0] == k for j in WORK.jobs)}" for k in kinds), flush=True)
    serial = [WORK.run(i) for i in jobs]
    fork = multiprocessing.get_context("fork")
    started = time.perf_counter()
    rounds = calls = mismatches = 0
    samples: list[tuple[float, float, int, int]] = []
    while True:
        # One round: every job serially, then by a pool of threads, then in forked processes.
        mismatches += sum(not same(WORK.run(i), serial[i]) for i in jobs)
        with ThreadPoolExecutor(max_workers=args.threads) as pool:
            threaded = list(pool.map(WORK.run, jobs))
        mismatches += sum(not same(threaded[i], serial[i]) for i in jobs)
        with fork.Pool(args.processes) as pool:
            chunks = [list(jobs)[p :: args.processes] for p in range(args.processes)]
            for chunk, results in zip(chunks, pool.map(_forked, chunks)):
                mismatches += sum(not same(r, serial[i]) for i, r in zip(chunk, results))
        rounds += 1
        calls += 3 * len(WORK.jobs)
        minutes = (time.perf_counter() - started) / 60
        samples.append((minutes, held_mb(), open_files(), threads()))
        print(
            f"round {rounds:4d} {minutes:6.1f} min: RSS {samples[-1][1]:8.1f} MB, open files {samples[-1][2]}, "
            f"threads {samples[-1][3]}, mismatches {mismatches}",
            flush=True,
        )
        settled = [s for s in samples if s[0] >= args.warmup_minutes]
        if minutes >= args.minutes and len(settled) >= 2:
            break
    first = next(i for i, s in enumerate(samples) if s[0] >= args.warmup_minutes)
    base, end = samples[first], samples[-1]
    growth = 100 * (end[1] - base[1]) / base[1]
    peak = 100 * (max(s[1] for s in samples[first:]) - base[1]) / base[1]
    flat = abs(growth) <= args.rss_tolerance and end[2] == base[2] and end[3] == base[3]
    print(
        f"\n{rounds} rounds, {calls} calls in {samples[-1][0]:.1f} min ({args.threads} threads, "
        f"{args.processes} forked processes per round); results differing from serial: {mismatches}\n"
        f"after warm-up (round {first + 1}, {base[0]:.1f} min) → end: "
        f"RSS {base[1]:.1f} → {end[1]:.1f} MB ({growth:+.2f} %, "
        f"peak {peak:+.2f} %), open files {base[2]} → {end[2]}, threads {base[3]} → {end[3]}: "
        f"{'flat' if flat else 'NOT FLAT'}"
    )
    return 0 if flat and mismatches == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
