"""The ``edgepose`` command line.

Examples::

    edgepose demo                                   # codebook + pose of the example object
    edgepose demo --seed 3                          # another random pose
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
EXAMPLE_MESH = Path("..") / "shared" / "data" / "ycb" / "power_drill.ply"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="edgepose",
        description="6D pose of unseen objects from depth point clouds, on a CPU.",
        epilog=__doc__.split("Examples::", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="store_true", help="print versions (proves the compiled core loads)")
    commands = parser.add_subparsers(dest="command")
    demo = commands.add_parser("demo", help="build a codebook, render the object at a random pose, estimate it")
    demo.add_argument("--mesh", type=Path, default=EXAMPLE_MESH, help=f"mesh file (default: {EXAMPLE_MESH})")
    demo.add_argument("--scale", type=float, default=None, help="file units → metres (default: detect)")
    demo.add_argument("--views", type=int, default=2100, help="number of viewpoints (default: 2100)")
    demo.add_argument("--seed", type=int, default=0, help="seed of the rendered view (default: 0)")
    args = parser.parse_args(argv)

    if args.version:
        import edgepose

        print(f"edgepose {edgepose.__version__} (compiled core loaded)")
        return 0
    if args.command == "demo":
        return _demo(args.mesh, args.scale, args.views, args.seed)
    parser.print_help()
    return 2


def _demo(mesh_path: Path, scale: float | None, views: int, seed: int) -> int:
    import numpy as np

    import edgepose
    from edgepose.eval import pose_errors, render_view
    from edgepose.model import _read_mesh, detect_scale

    try:
        mesh = _read_mesh(mesh_path)
        mesh.apply_scale(scale or detect_scale(float(np.ptp(mesh.vertices, axis=0).max())))
        codebook = edgepose.build_codebook(mesh, views=views, scale=1.0)
    except edgepose.EdgePoseError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    t = codebook.timings
    print(f"object      {mesh_path} ({codebook.model.diameter * 1000:.0f} mm across)")
    print(f"codebook    {len(codebook)} views in {t['total']:.2f} s "
          f"(model {t['model']:.2f} s, maps {t['maps']:.2f} s, encoding {t['encode']:.2f} s)")

    view = render_view(mesh, seed=seed)
    print(f"rendered    {len(view.cloud)} points at {np.linalg.norm(view.T_cam_obj[:3, 3]):.2f} m "
          f"(1 mm depth noise, seed {seed})")
    edgepose.estimate(view.cloud, codebook)  # first call loads onnxruntime's kernels
    pose = edgepose.estimate(view.cloud, codebook)
    errors = pose_errors(codebook.model.points + codebook.model.centre, pose.matrix, view.T_cam_obj,
                         codebook.model.diameter, symmetric=False)
    np.set_printoptions(precision=4, suppress=True)
    print("estimated   T_cam_obj =\n" + _indent(pose.matrix))
    print("true        T_cam_obj =\n" + _indent(view.T_cam_obj))
    verdict = "correct" if errors.correct_add_or_s else "WRONG"
    print(f"errors      rotation {errors.rotation_deg:.2f}°, translation {errors.translation_mm:.1f} mm, "
          f"ADD {errors.add * 1000:.1f} mm ({verdict} at 0.1 × diameter = {errors.diameter * 100:.1f} mm)")
    stages = "  ".join(f"{k} {v * 1000:.2f}" for k, v in pose.timings.items())
    print(f"timings ms  {stages}")
    return 0


def _indent(matrix) -> str:
    return "\n".join("            " + line for line in str(matrix).splitlines())


if __name__ == "__main__":
    sys.exit(main())
