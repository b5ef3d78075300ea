"""The ``edgepose`` command line.

Examples::

    edgepose demo                                   # example object, map statistics
    edgepose demo --mesh my_part.stl --scale 0.001  # your own mesh (mm → m)
    edgepose --version
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

#: The example object the demo uses when no mesh is given: a YCB mesh from the
#: shared benchmark data (CC BY 4.0), found beside the project checkout.
EXAMPLE_MESH = Path("..") / "shared" / "data" / "ycb" / "mustard_bottle.ply"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="edgepose",
        description="6D pose of unseen objects from depth point clouds, on a CPU.",
        epilog=__doc__.split("Examples::", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="store_true", help="print versions (proves the compiled core loads)")
    commands = parser.add_subparsers(dest="command")
    demo = commands.add_parser("demo", help="build the standard model and all view maps of an object")
    demo.add_argument("--mesh", type=Path, default=EXAMPLE_MESH, help=f"mesh file (default: {EXAMPLE_MESH})")
    demo.add_argument("--scale", type=float, default=None, help="file units → metres (default: detect)")
    demo.add_argument("--views", type=int, default=2100, help="number of viewpoints (default: 2100)")
    demo.add_argument("--map-points", type=int, default=512, help="points per map (default: 512)")
    args = parser.parse_args(argv)

    if args.version:
        import edgepose

        print(f"edgepose {edgepose.__version__} (compiled core loaded)")
        return 0
    if args.command == "demo":
        return _demo(args.mesh, args.scale, args.views, args.map_points)
    parser.print_help()
    return 2


def _demo(mesh: Path, scale: float | None, views: int, map_points: int) -> int:
    import numpy as np

    import edgepose

    try:
        t0 = time.perf_counter()
        model = edgepose.load_model(mesh, scale=scale)
        t1 = time.perf_counter()
    except edgepose.EdgePoseError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    viewpoints = edgepose.fibonacci_viewpoints(views)
    t2 = time.perf_counter()
    maps = edgepose.compute_maps(model, viewpoints, map_points)
    t3 = time.perf_counter()

    cos = np.clip(viewpoints.directions @ viewpoints.directions.T, -1, 1)
    np.fill_diagonal(cos, -1)
    spacing_deg = np.degrees(np.arccos(cos.max(axis=1)))
    seen = maps.visible / len(model.points)
    print(f"object        {mesh}")
    print(f"model         {len(model.points)} points, diameter {model.diameter * 1000:.1f} mm, "
          f"point spacing {model.spacing * 1000:.2f} mm, scale {model.scale:.2f} /m   ({(t1 - t0) * 1000:.0f} ms)")
    print(f"viewpoints    {len(viewpoints)} on a Fibonacci sphere, nearest-neighbour spacing "
          f"{spacing_deg.mean():.2f}° mean ({spacing_deg.min():.2f}–{spacing_deg.max():.2f}°)   ({(t2 - t1) * 1000:.1f} ms)")
    print(f"maps          {maps.points.shape[0]} × {maps.points.shape[1]} points, visible share of the model "
          f"{seen.min():.0%} min / {np.median(seen):.0%} median / {seen.max():.0%} max, "
          f"{np.mean(maps.visible < map_points):.1%} of views padded   ({(t3 - t2) * 1000:.0f} ms)")
    radius = np.linalg.norm(maps.points, axis=2).max(axis=1)
    print(f"map extent    max ‖p‖ per map {radius.min():.2f}–{radius.max():.2f} (unit-sphere scale)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
