"""The median estimate time of this checkout against an earlier commit's, on
the pose benchmark's views, in alternating rounds on the same machine: how
the speed issue's "half of the day's median" is measured.

    .venv/bin/python benches/bench_against.py REV [--rounds 10] [--repeats 2]
                                              [--level clean] [--frame] [--views 20]

``REV`` (a commit, tag or branch) is built once into
``benches/.cache/against/<sha>/`` (its ``python/`` tree and its Rust core,
compiled with maturin: a few minutes; its target directory is kept there
for the next run). Views: ``bench_pose.py``'s, rendered once (the five YCB
meshes, ``--views`` per mesh at ``--level``, the same seeds). Each round
runs ``REV``, then this checkout, each in a fresh process that builds (or
reads back) its codebooks, estimates each view once to warm up and then
``--repeats`` times (``REV``'s codebooks are kept beside its build, this
checkout's for the run only), from the cloud alone (``--frame``: given the depth
frame too). Printed: each round's two medians and their ratio, then the
median of each side over rounds, the ratio of those medians and the
median of the rounds' ratios. The machine's pace drifts by tens of per
cent between minutes: compare the sides within a round, not runs.
"""

from __future__ import annotations

import argparse
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

import numpy as np

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
    maturin = Path(sys.executable).with_name("maturin")
    env = dict(os.environ, CARGO_TARGET_DIR=str(home / "target"))
    subprocess.run(
        [str(maturin), "build", "--release", "--quiet", "-o", str(home / "dist")], cwd=source, env=env, check=True
    )
    wheel = max((home / "dist").glob("*.whl"), key=lambda p: p.stat().st_mtime)
    shutil.rmtree(package, ignore_errors=True)
    (source / "python").rename(package)
    with zipfile.ZipFile(wheel) as z:
        (package / "edgepose" / "_core.abi3.so").write_bytes(z.read("edgepose/_core.abi3.so"))
    return package


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
    ``REV`` has too): prints the median estimate in ms."""
    import edgepose

    codebooks.mkdir(parents=True, exist_ok=True)
    times = []
    for name, mesh, clouds, frames in pickle.loads(views.read_bytes()):
        path = codebooks / f"{name}.npz"
        if not path.is_file():
            edgepose.build_codebook(mesh).save(path)
        codebook = edgepose.Codebook.load(path)
        for cloud, (depth, K) in zip(clouds, frames):
            scene = {"depth": depth, "K": K, "depth_scale": 1.0} if frame else {}
            edgepose.estimate(cloud, codebook, **scene)
            for _ in range(repeats):
                start = time.perf_counter()
                edgepose.estimate(cloud, codebook, **scene)
                times.append(time.perf_counter() - start)
    print(f"median_ms {1e3 * float(np.median(times)):.4f}")


def side(package: Path | None, args: argparse.Namespace, views: Path, codebooks: Path) -> float:
    """One side's median (ms), in a fresh process (``package``: REV's tree)."""
    env = dict(os.environ)
    if package is not None:
        env["PYTHONPATH"] = str(package)
    command = [sys.executable, __file__, "--child", str(views), str(codebooks), str(args.repeats)]
    out = subprocess.run(
        command + (["--frame"] if args.frame else []), env=env, check=True, capture_output=True, text=True
    )
    return float(out.stdout.split("median_ms")[-1])


def main() -> None:
    if sys.argv[1:2] == ["--child"]:
        child(Path(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4]), "--frame" in sys.argv)
        return
    from bench_pose import RENDERED_VIEWS

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("rev", help="the earlier commit, tag or branch")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=2, help="timed estimates of each view per round")
    parser.add_argument("--level", default="clean", help="stress level (edgepose.eval.stress.STRESS_LEVELS)")
    parser.add_argument("--views", type=int, default=RENDERED_VIEWS, help="views per mesh")
    parser.add_argument("--frame", action="store_true", help="estimate given the depth frame too")
    args = parser.parse_args()
    package = built(args.rev)
    views = rendered(args.level, args.views)
    head = git("rev-parse", "--short", "HEAD") + (
        "+changes" if git("status", "--porcelain", "--untracked-files=no") else ""
    )
    print(f"{args.rev} against {head}: {args.level}, {args.views} views per mesh × {args.repeats}", flush=True)
    then, now = [], []
    here = tempfile.TemporaryDirectory()  # this checkout's codebooks: its code may change them
    for r in range(args.rounds):
        then.append(side(package, args, views, package.parent / "codebooks"))
        now.append(side(None, args, views, Path(here.name)))
        print(
            f"round {r}: {args.rev} {then[-1]:.3f} ms, here {now[-1]:.3f} ms, ratio {now[-1] / then[-1]:.3f}",
            flush=True,
        )
    a, b = statistics.median(then), statistics.median(now)
    ratios = [n / t for n, t in zip(now, then)]
    print(
        f"medians: {args.rev} {a:.3f} ms, here {b:.3f} ms; ratio of medians {b / a:.3f}, "
        f"median ratio {statistics.median(ratios):.3f} (rounds {min(ratios):.2f}–{max(ratios):.2f})"
    )


if __name__ == "__main__":
    main()
