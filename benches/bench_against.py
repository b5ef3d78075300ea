"""The median estimate time of this checkout against an earlier commit's, on
the pose benchmark's views, interleaved view by view on the same machine:
how the speed issue's "half of the day's median" is measured.

    .venv/bin/python benches/bench_against.py REV [--rounds 8] [--repeats 2] [--turn 10]
                                              [--level clean] [--frame] [--views 20]

``REV`` (a commit, tag or branch) is built once into
``benches/.cache/against/<sha>/`` (its ``python/`` tree and its Rust core,
compiled with maturin: a few minutes; its target directory is kept there
for the next run). This checkout's core is compiled the same way (a
release wheel, default features: not the editable build it imports) into
``benches/.cache/against/worktree-<hash>/`` once per state of its Rust
sources, and its ``python/`` tree copied beside it for the run. Views:
``bench_pose.py``'s, rendered once (the five YCB meshes, ``--views`` per
mesh at ``--level``, the same seeds). Each round
starts one process per side (``REV``'s tree, this checkout's), which builds
(or reads back) its codebooks and estimates each view once to warm up
(``REV``'s codebooks are kept beside its build, this checkout's for the run
only), from the cloud alone (``--frame``: given the depth frame too). Then
the two take turns of ``--turn`` views, each estimating each view
``--repeats`` times in a row while the other waits (the side that goes
first alternates): the machine's pace drifts by tens of per cent between
minutes, and a turn lasts a fraction of a second. A turn of one view puts
each side's first estimate after the other's, its caches cold. Printed:
each round's two medians and their ratio, then the median of each side
over all rounds, the ratio of those medians, the median of the per-view
ratios (each view's median time here over ``REV``'s) and the range of the
rounds' ratios; then each side's stage laps (``Pose.timings``, as each
side names its stages), ms per estimate.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import pickle
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CACHE = REPO / "benches" / ".cache" / "against"


def git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=REPO, check=True, capture_output=True, text=True).stdout.strip()


def built(rev: str) -> Path:
    """The ``python/`` tree of ``rev`` with its compiled core, built once."""
    sha = git("rev-parse", "--verify", f"{rev}^{{commit}}")
    home = CACHE / sha
    package = home / "python"
    if (package / "edgepose" / "_core.abi3.so").is_file():
        return package
    source = home / "source"
    source.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "archive", sha], cwd=REPO, check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(source)], input=archive, check=True)
    print(f"building {rev} ({sha[:10]}) in {source} ...", flush=True)
    core = compiled(source, home / "target", home / "dist")
    shutil.rmtree(package, ignore_errors=True)
    (source / "python").rename(package)
    (package / "edgepose" / "_core.abi3.so").write_bytes(core)
    return package


def built_here(into: Path) -> Path:
    """This working tree's ``python/`` tree, copied into ``into``, with its
    Rust core compiled as ``REV``'s is (a release wheel, default features;
    not the editable build a checkout imports, whose features and layout
    differ): built once per state of the Rust sources and build files."""
    listed = git("ls-files", "--cached", "--others", "--exclude-standard").splitlines()
    files = sorted(f for f in listed if (REPO / f).is_file())
    inputs = [f for f in files if f.startswith("rust/") or f in ("Cargo.toml", "Cargo.lock", "pyproject.toml")]
    digest = hashlib.sha256()
    for name in inputs:
        digest.update(name.encode() + b"\0" + (REPO / name).read_bytes() + b"\0")
    home = CACHE / f"worktree-{digest.hexdigest()[:16]}"
    core = home / "_core.abi3.so"
    if not core.is_file():
        source = home / "source"
        shutil.rmtree(source, ignore_errors=True)
        # The build reads the top level's files too (the README, the licence).
        for name in sorted({*inputs, *(f for f in files if f.startswith("python/") or "/" not in f)}):
            (source / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, source / name)
        print(f"building the working tree's core in {source} ...", flush=True)
        # One target directory for every state of the tree: builds after a small change are incremental.
        core.write_bytes(compiled(source, CACHE / "worktree-target", home / "dist"))
    package = into / "python"
    shutil.copytree(REPO / "python", package, ignore=shutil.ignore_patterns("_core.abi3.so", "__pycache__"))
    shutil.copy2(core, package / "edgepose" / "_core.abi3.so")
    return package


def compiled(source: Path, target: Path, dist: Path) -> bytes:
    """The compiled core (``_core.abi3.so``) of the tree at ``source``: a
    release wheel built by maturin into ``dist``, Cargo's output in ``target``."""
    maturin = Path(sys.executable).with_name("maturin")
    env = dict(os.environ, CARGO_TARGET_DIR=str(target))
    subprocess.run([str(maturin), "build", "--release", "--quiet", "-o", str(dist)], cwd=source, env=env, check=True)
    wheel = max(dist.glob("*.whl"), key=lambda p: p.stat().st_mtime)
    with zipfile.ZipFile(wheel) as z:
        return z.read("edgepose/_core.abi3.so")


def rendered(level: str, views: int) -> Path:
    """The benchmark's views at ``level`` (clouds, depth frames), pickled once."""
    from bench_pose import load_sources
    from edgepose.eval.benchmark import load_object

    path = CACHE / f"views_{level}_{views}.pkl"
    if not path.is_file():
        ycb = argparse.Namespace(tune=False, meshes=None, objects=None, seed=0)
        objects = []
        for source in load_sources(ycb, argparse.ArgumentParser()):
            seeds = [source.seed_base + i for i in range(views)]
            obj = load_object(source.mesh, seeds, name=source.name, stress=level)
            objects.append((source.name, source.mesh, obj.clouds, obj.frames))
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(objects))
    return path


def child(views: Path, codebooks: Path, repeats: int, frame: bool) -> None:
    """Runs in the side's own process (only ``edgepose``'s public API, which
    ``REV`` has too): warms up, prints ``ready``, then for each view index
    read from stdin (several to a line: a turn) estimates that view
    ``repeats`` times and prints the turn's times in seconds; at the end of
    input prints the timed estimates' stage laps (``Pose.timings``: each
    stage's seconds summed over them, and their count) as JSON."""
    import edgepose

    codebooks.mkdir(parents=True, exist_ok=True)
    work = []
    for name, mesh, clouds, frames in pickle.loads(views.read_bytes()):
        path = codebooks / f"{name}.npz"
        if not path.is_file():
            edgepose.build_codebook(mesh).save(path)
        codebook = edgepose.Codebook.load(path)
        for cloud, (depth, K) in zip(clouds, frames):
            scene = {"depth": depth, "K": K, "depth_scale": 1.0} if frame else {}
            work.append((cloud, codebook, scene))
    for cloud, codebook, scene in work:
        edgepose.estimate(cloud, codebook, **scene)
    print(f"ready {len(work)}", flush=True)
    laps: dict[str, float] = {}
    timed = 0
    for line in sys.stdin:
        times = []
        for view in map(int, line.split()):
            cloud, codebook, scene = work[view]
            for _ in range(repeats):
                start = time.perf_counter()
                pose = edgepose.estimate(cloud, codebook, **scene)
                times.append(time.perf_counter() - start)
                timed += 1
                for stage, seconds in pose.timings.items():
                    laps[stage] = laps.get(stage, 0.0) + seconds
        print(" ".join(f"{t:.9f}" for t in times), flush=True)
    print(json.dumps({"laps": laps, "estimates": timed}), flush=True)


class Side:
    """One side's live process, importing edgepose from ``package``."""

    def __init__(self, package: Path, args: argparse.Namespace, views: Path, codebooks: Path) -> None:
        env = dict(os.environ, PYTHONPATH=str(package))
        command = [sys.executable, __file__, "--child", str(views), str(codebooks), str(args.repeats)]
        self.process = subprocess.Popen(
            command + (["--frame"] if args.frame else []),
            env=env,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        ready = self._line()
        self.views = int(ready.split()[1])

    def _line(self) -> str:
        assert self.process.stdout is not None
        line = self.process.stdout.readline()
        if not line:
            raise RuntimeError(f"a side's process ended (exit status {self.process.wait()})")
        return line

    def estimate(self, views: range) -> list[float]:
        """The views' estimate times in turn, seconds (``repeats`` a view)."""
        assert self.process.stdin is not None
        self.process.stdin.write(" ".join(map(str, views)) + "\n")
        self.process.stdin.flush()
        return [float(t) for t in self._line().split()]

    def close(self) -> dict:
        """Ends the process; its stage laps (see :func:`child`)."""
        assert self.process.stdin is not None
        self.process.stdin.close()
        laps = json.loads(self._line())
        self.process.wait()
        return laps


def main() -> None:
    if sys.argv[1:2] == ["--child"]:
        child(Path(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4]), "--frame" in sys.argv)
        return
    from bench_pose import RENDERED_VIEWS

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("rev", help="the earlier commit, tag or branch")
    parser.add_argument("--rounds", type=int, default=8, help="pairs of fresh processes")
    parser.add_argument("--repeats", type=int, default=2, help="timed estimates of each view per turn")
    parser.add_argument("--level", default="clean", help="stress level (edgepose.eval.stress.STRESS_LEVELS)")
    parser.add_argument("--views", type=int, default=RENDERED_VIEWS, help="views per mesh")
    parser.add_argument("--frame", action="store_true", help="estimate given the depth frame too")
    parser.add_argument("--turn", type=int, default=10, help="views a side estimates before the other's turn")
    args = parser.parse_args()
    package = built(args.rev)
    views = rendered(args.level, args.views)
    head = git("rev-parse", "--short", "HEAD") + (
        "+changes" if git("status", "--porcelain", "--untracked-files=no") else ""
    )
    print(f"{args.rev} against {head}: {args.level}, {args.views} views per mesh × {args.repeats}", flush=True)
    then: dict[int, list[float]] = {}
    now: dict[int, list[float]] = {}
    rounds = []
    stages: dict[str, dict[str, float]] = {"then": {}, "now": {}}
    estimates = {"then": 0, "now": 0}
    here = tempfile.TemporaryDirectory()  # this checkout's tree and codebooks: its code may change them
    tree = built_here(Path(here.name))
    for r in range(args.rounds):
        old = Side(package, args, views, package.parent / "codebooks")
        new = Side(tree, args, views, Path(here.name) / "codebooks")
        old_times, new_times = [], []
        for first in range(0, old.views, args.turn):
            turn = range(first, min(first + args.turn, old.views))
            pair = (old, new) if (first // args.turn + r) % 2 == 0 else (new, old)
            for side in pair:
                times = side.estimate(turn)
                (old_times if side is old else new_times).extend(times)
                for i, view in enumerate(turn):
                    (then if side is old else now).setdefault(view, []).extend(
                        times[i * args.repeats : (i + 1) * args.repeats]
                    )
        for key, side in (("then", old), ("now", new)):
            laps = side.close()
            estimates[key] += laps["estimates"]
            for stage, seconds in laps["laps"].items():
                stages[key][stage] = stages[key].get(stage, 0.0) + seconds
        a, b = 1e3 * statistics.median(old_times), 1e3 * statistics.median(new_times)
        rounds.append(b / a)
        print(f"round {r}: {args.rev} {a:.3f} ms, here {b:.3f} ms, ratio {b / a:.3f}", flush=True)
    a = 1e3 * statistics.median(t for ts in then.values() for t in ts)
    b = 1e3 * statistics.median(t for ts in now.values() for t in ts)
    per_view = [statistics.median(now[v]) / statistics.median(then[v]) for v in then]
    print(
        f"medians: {args.rev} {a:.3f} ms, here {b:.3f} ms; ratio of medians {b / a:.3f}, "
        f"median per-view ratio {statistics.median(per_view):.3f} (rounds {min(rounds):.3f}–{max(rounds):.3f})"
    )
    print("stage laps, ms per estimate (mean; a stage that ran in some estimates only counts 0 in the others):")
    print(f"  {'stage':<20}{args.rev:>10}{'here':>10}{'ratio':>8}")
    for stage in dict.fromkeys([*stages["then"], *stages["now"]]):
        a, b = (1e3 * stages[k].get(stage, 0.0) / max(estimates[k], 1) for k in ("then", "now"))
        print(f"  {stage:<20}{a:>10.3f}{b:>10.3f}" + (f"{b / a:>8.2f}" if a > 0 else f"{'':>8}"))


if __name__ == "__main__":
    main()
