"""Catalogue build throughput: objects per minute, locally (one object after
another, each with every core) against Ray on this machine (one task per
object, ``--cpus-per-task`` cores each), and the rerun that finds every
codebook up to date.

    .venv/bin/python benches/bench_catalog.py            # 12 meshes, 2,100 views
    .venv/bin/python benches/bench_catalog.py --views 500

The catalogue: the five YCB meshes plus seven of the shared training CAD
models (codebooks of test objects are fine; the networks never train on
them). Wall-clock times; the Ray figures are given with and without starting
the Ray instance. Every Ray codebook is checked byte-for-byte against the
local one.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

from edgepose.catalog import BuildSettings, LocalExecutor, RayExecutor, build_catalog, find_meshes

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
CAD = ("box.STL", "cylinder.stl", "fandisk.obj", "bunny.ply", "teapot.stl", "torus.STL", "suzanne.ply")


def catalogue(folder: Path) -> list[Path]:
    folder.mkdir()
    for mesh in [*sorted((DATA / "ycb").glob("*.ply")), *(DATA / "train_shapes" / "cad" / name for name in CAD)]:
        shutil.copy(mesh, folder / mesh.name)
    return find_meshes([folder])


def timed_build(meshes: list[Path], out: Path, settings: BuildSettings, executor) -> tuple[float, list]:
    t0 = time.perf_counter()
    results = build_catalog(meshes, out, settings, executor=executor)
    seconds = time.perf_counter() - t0
    failed = [r for r in results if r.failed]
    if failed:
        raise SystemExit(f"failed: {[r.error for r in failed]}")
    return seconds, results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=2100)
    parser.add_argument("--cpus-per-task", type=int, nargs="+", default=[1, 2], help="Ray runs to time")
    args = parser.parse_args()
    import ray

    settings = BuildSettings(views=args.views)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        meshes = catalogue(root / "meshes")
        n = len(meshes)
        cores = os.cpu_count()
        print(f"{n} objects, {args.views} views each, {cores} cores")
        rows = []

        seconds, _ = timed_build(meshes, root / "local", settings, LocalExecutor())
        rows.append(("local, one object at a time, all cores", seconds, seconds))
        local_bytes = {p.name: p.read_bytes() for p in (root / "local").glob("*.codebook")}
        seconds, results = timed_build(meshes, root / "local", settings, LocalExecutor())
        assert all(r.status == "skipped" for r in results)
        resume_local = seconds

        for cpus in args.cpus_per_task:
            out = root / f"ray{cpus}"
            t0 = time.perf_counter()
            ray.init(num_cpus=cores, include_dashboard=False, log_to_driver=False, logging_level="warning")
            started = time.perf_counter() - t0
            seconds, _ = timed_build(meshes, out, settings, RayExecutor(cpus_per_task=cpus))
            tasks = cores // cpus
            rows.append(
                (f"Ray, {tasks} task{'s' * (tasks > 1)} × {cpus} core{'s' * (cpus > 1)}", seconds + started, seconds)
            )
            assert {p.name: p.read_bytes() for p in out.glob("*.codebook")} == local_bytes, "Ray bytes differ"
            seconds, results = timed_build(meshes, out, settings, RayExecutor(cpus_per_task=cpus))
            assert all(r.status == "skipped" for r in results)
            resume_ray = seconds
            ray.shutdown()

    local = rows[0][2]
    print("\n| run | wall s (with Ray start) | objects/min (with Ray start) | build s | objects/min | vs local |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for name, with_start, build in rows:
        print(
            f"| {name} | {with_start:.1f} | {60 * n / with_start:.1f} | {build:.1f} | {60 * n / build:.1f} "
            f"| {local / build:.2f}× |"
        )
    print(
        f"\nrerun, all {n} up to date: local {resume_local:.2f} s, Ray {resume_ray:.2f} s "
        f"({resume_local / n * 1000:.0f} ms per object checked locally)"
    )
    print("Ray codebooks byte-identical to the local ones: yes")


if __name__ == "__main__":
    main()
