"""Long fuzz run of every door untrusted input comes through, with the
strategies and checks of tests/test_fuzz.py (which runs a short,
derandomised slice of each in CI):

- ``load``: damaged codebook files (``Codebook.load``);
- ``estimate``: clouds of any dtype, shape, layout and damage (``estimate``);
- ``depth``: depth images, intrinsics, masks and depth scales (``cloud_from_depth``);
- ``frame``: the same frames given to ``estimate(depth=, K=)``, ``estimate_many``,
  ``Tracker.update_depth`` and ``track_many`` (a tracker already on the
  object: the tracked frame's path) beside a good cloud;
- ``bop``: a one-image BOP folder cut from the real frames, one file damaged
  (``BopDataset``: models, targets, cameras, annotations, depth, masks).

    .venv/bin/python benches/fuzz.py --cases 1000000 --workers 2

Every input must give a valid result (a whole codebook, finite points, a
finite rigid pose, a well-formed dataset) or an EdgePoseError; any other
exception stops the run with hypothesis' minimal failing example, and a hang
trips the faulthandler watchdog (stack dump, exit 1; armed per batch of
``--batch`` cases, each a few ms, so a batch past 120 s holds a hang). The
watchdog reads wall time: a run at ``nice 19`` beside other busy work can
starve past it without hanging (run at the same priority, or lower
``--batch``). Depth frames are cut to
a window around the object (the intrinsics shifted with it) so that a case
costs milliseconds. Prints the cases per target, their outcomes, the time,
and each worker's RSS after warm-up and at the end (hypothesis' own
bookkeeping included: ``benches/soak.py`` measures edgepose's memory).
"""

from __future__ import annotations

import argparse
import collections
import multiprocessing
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from types import SimpleNamespace

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import edgepose  # noqa: E402
import numpy as np  # noqa: E402
import test_fuzz  # noqa: E402
from edgepose.eval import render_view  # noqa: E402
from edgepose.model import read_mesh  # noqa: E402
from hypothesis import given, settings  # noqa: E402
from soak import rss_mb  # noqa: E402

#: Share of the cases each target gets: the cheap doors most, the ones that run a whole estimate less.
SHARES = {"depth": 0.5, "bop": 0.2, "load": 0.15, "estimate": 0.1, "frame": 0.05}
REAL = ROOT.parent / "shared" / "data" / "ycbv_real"


def windowed(view, margin: int = 16) -> SimpleNamespace:
    """``view`` cut to its mask's bounding box plus ``margin`` pixels, with
    the principal point moved to match: the same points, a smaller frame."""
    rows, cols = np.nonzero(view.mask)
    r0, c0 = max(rows.min() - margin, 0), max(cols.min() - margin, 0)
    r1, c1 = rows.max() + margin + 1, cols.max() + margin + 1
    K = view.camera.K.copy()
    K[0, 2] -= c0
    K[1, 2] -= r0
    return SimpleNamespace(
        depth=np.ascontiguousarray(view.depth[r0:r1, c0:c1]),
        mask=np.ascontiguousarray(view.mask[r0:r1, c0:c1]),
        camera=SimpleNamespace(K=K),
        cloud=view.cloud,
    )


def run_worker(
    worker: int, cases: dict[str, int], batch: int, mesh_path: Path, seconds: dict[str, float] | None = None
) -> dict:
    """Fuzz each target for its number of cases (or, with ``seconds``, until
    its time is up, whichever comes first); returns the outcome tally."""
    mesh = read_mesh(mesh_path)
    codebook = edgepose.build_codebook(mesh)
    view = windowed(render_view(mesh, seed=2 + worker))
    work = Path(tempfile.mkdtemp(prefix=f"edgepose-fuzz-{worker}-"))
    # The loader's checks do not depend on the view count: a small codebook is a quick case.
    small = edgepose.build_codebook(mesh, views=64)
    small.save(work / "good.codebook")
    blob = (work / "good.codebook").read_bytes()
    bop_files = test_fuzz.small_bop_folder(REAL, work / "bop_good") if REAL.is_dir() else None
    tally: dict[str, collections.Counter] = {name: collections.Counter() for name in cases}
    doors = iter(np.random.default_rng(worker).integers(0, len(test_fuzz.FRAME_DOORS), size=10**8))
    fuzz = settings(max_examples=batch, derandomize=False, **test_fuzz.FUZZ_SETTINGS)

    @fuzz
    @given(damaged=test_fuzz.damaged_codebooks(blob))
    def load(damaged):
        tally["load"][test_fuzz.check_load(damaged, work / "damaged.codebook", small)] += 1

    @fuzz
    @given(value=test_fuzz.estimate_inputs(view.cloud))
    def estimate(value):
        tally["estimate"][test_fuzz.check_estimate(value, codebook)] += 1

    @fuzz
    @given(value=test_fuzz.frame_inputs(view))
    def depth(value):
        tally["depth"][test_fuzz.check_cloud_from_depth(value)] += 1

    @fuzz
    @given(value=test_fuzz.frame_inputs(view))
    def frame(value):
        door = test_fuzz.FRAME_DOORS[next(doors)]
        tally["frame"][f"{door}: {test_fuzz.check_frame(value, door, view.cloud, codebook)}"] += 1

    @fuzz
    @given(damaged=test_fuzz.damaged_bop_files(bop_files or {}))
    def bop(damaged):
        test_fuzz.write_bop_folder(work / "bop", damaged)
        tally["bop"][test_fuzz.check_bop(work / "bop")] += 1

    runs = {"load": load, "estimate": estimate, "depth": depth, "frame": frame, "bop": bop}
    if bop_files is None:
        cases = {name: n for name, n in cases.items() if name != "bop"}
    rss_start = None
    spent: dict[str, float] = {}
    heartbeat = time.perf_counter()
    for name, wanted in cases.items():
        t0 = time.perf_counter()
        deadline = t0 + (seconds[name] if seconds else float("inf"))
        while sum(tally[name].values()) < wanted and time.perf_counter() < deadline:
            if time.perf_counter() - heartbeat > 300:
                heartbeat = time.perf_counter()
                print(f"worker {worker}: {name} {sum(tally[name].values())} of {wanted} cases", flush=True)
            with test_fuzz.watchdog():  # per batch: a case that hangs keeps its batch past WATCHDOG_S
                runs[name]()
            if rss_start is None:
                rss_start = rss_mb()  # after the first batch: allocator pools, onnxruntime arenas
        spent[name] = time.perf_counter() - t0
        done = sum(tally[name].values())
        print(f"worker {worker}: {name} {done} cases in {spent[name]:.0f} s", flush=True)
    return {"tally": tally, "seconds": spent, "rss": (rss_start, rss_mb())}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", type=int, default=1_000_000, help="total cases, split by SHARES and workers")
    parser.add_argument("--workers", type=int, default=2, help="processes, each with its own seed and view")
    parser.add_argument("--minutes", type=float, default=None, help="time budget, split by SHARES (default: none)")
    parser.add_argument("--only", default=None, help="comma-separated targets (default: all)")
    parser.add_argument("--batch", type=int, default=500, help="examples per hypothesis run")
    parser.add_argument("--mesh", type=Path, default=ROOT / "codebooks" / "power_drill.ply")
    args = parser.parse_args()
    names = args.only.split(",") if args.only else list(SHARES)
    share = sum(SHARES[n] for n in names)
    per_worker = {n: max(1, round(args.cases * SHARES[n] / share / args.workers)) for n in names}
    budget = {n: 60 * args.minutes * SHARES[n] / share for n in names} if args.minutes else None
    t0 = time.perf_counter()
    spawn = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(args.workers, mp_context=spawn) as pool:
        futures = [pool.submit(run_worker, w, per_worker, args.batch, args.mesh, budget) for w in range(args.workers)]
        try:
            results = [f.result() for f in futures]
        except BrokenProcessPool:
            print("a worker died (a crash: its stack is above): FAILED", file=sys.stderr)
            return 1
    elapsed = time.perf_counter() - t0
    total: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    busy: dict[str, float] = collections.defaultdict(float)
    for result in results:
        for name, counts in result["tally"].items():
            total[name].update(counts)
        for name, s in result["seconds"].items():
            busy[name] += s
    print(
        f"\n{sum(sum(c.values()) for c in total.values())} cases in {elapsed / 60:.1f} min "
        f"({args.workers} workers), zero failures, zero hangs"
    )
    for name, counts in total.items():
        n = sum(counts.values())
        rate = 1e3 * busy[name] / max(n, 1)
        print(f"  {name}: {n} cases, {rate:.2f} ms each; " + ", ".join(f"{k} {v}" for k, v in counts.most_common()))
    for w, result in enumerate(results):
        start, end = result["rss"]
        print(f"  worker {w}: RSS after the first batch {start:.0f} MB, at end {end:.0f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
