"""Map construction on the shared YCB meshes: standard model, 2,100 view maps,
and a numpy implementation of the same per-view step as an in-process peer.

    .venv/bin/python benches/bench_maps.py [--repeats 5] [--views 2100]

Prints medians; the machine is noisy, so compare ratios.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import edgepose
import numpy as np
from edgepose.model import read_mesh

YCB = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ycb"


def median_seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def numpy_view_map(model: edgepose.StandardModel, rotation: np.ndarray, m: int) -> np.ndarray:
    """The same map step in numpy (visibility from the core, FPS in numpy)."""
    seen = edgepose.visible_mask(model, rotation)
    pts = (model.points[seen] @ rotation.T.astype(np.float32)).astype(np.float32)
    pts -= pts.mean(axis=0)
    current = int(np.argmax((pts**2).sum(axis=1)))
    min_sq = np.full(len(pts), np.inf, dtype=np.float32)
    chosen = [current]
    for _ in range(1, m):
        min_sq = np.minimum(min_sq, ((pts - pts[current]) ** 2).sum(axis=1))
        current = int(np.argmax(min_sq))
        chosen.append(current)
    return pts[chosen] * np.float32(model.scale)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--views", type=int, default=2100)
    parser.add_argument("--map-points", type=int, default=512)
    args = parser.parse_args()

    views = edgepose.fibonacci_viewpoints(args.views)
    print(f"{args.views} views, {args.map_points} points per map, 4096-point models, median of {args.repeats}")
    print(
        f"{'object':<16} {'read mesh':>10} {'model':>8} {'maps':>8} {'per view':>9} {'numpy/view':>11} {'speed-up':>9}"
    )
    map_times = []
    for path in sorted(YCB.glob("*.ply")):
        read = median_seconds(lambda path=path: read_mesh(path), args.repeats)
        mesh = read_mesh(path)
        build = median_seconds(lambda mesh=mesh: edgepose.load_model(mesh), args.repeats)
        model = edgepose.load_model(mesh)
        maps = median_seconds(lambda model=model: edgepose.compute_maps(model, views, args.map_points), args.repeats)
        sample = range(0, args.views, max(1, args.views // 8))
        numpy_per_view = median_seconds(
            lambda model=model, sample=sample: [
                numpy_view_map(model, views.rotations[v], args.map_points) for v in sample
            ],
            1,
        ) / len(sample)
        per_view = maps / args.views
        map_times.append(maps)
        print(
            f"{path.stem:<16} {read * 1e3:>8.0f}ms {build * 1e3:>6.0f}ms {maps * 1e3:>6.0f}ms "
            f"{per_view * 1e6:>7.0f}µs {numpy_per_view * 1e3:>9.1f}ms {numpy_per_view / per_view:>8.0f}×"
        )
    print(f"median maps time over objects: {statistics.median(map_times) * 1e3:.0f} ms (budget 1000 ms, aim 300 ms)")


if __name__ == "__main__":
    main()
