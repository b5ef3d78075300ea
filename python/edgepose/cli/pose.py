"""``edgepose demo`` and ``edgepose estimate``: the pose of one object.

Units are metres; poses are ``T_cam_obj``, camera frame as OpenCV.
"""

from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from edgepose.cli.app import (
    DEMO_OBJECT,
    SHIPPED_DIR,
    CodebookOption,
    DepthScaleOption,
    Failure,
    IntrinsicsOption,
    RerunOption,
    RrdOption,
    ScaleOption,
    handle_errors,
    stdout_console,
)
from edgepose.cloud import DEPTH_SCALE_MM
from edgepose.settings import DEFAULT_SETTINGS
from edgepose.views import DEFAULT_VIEWS


def demo(
    mesh: Annotated[
        Path | None,
        typer.Option(help="A mesh file to use instead of the shipped power drill (a codebook is built first)."),
    ] = None,
    scale: ScaleOption = None,
    views: Annotated[int, typer.Option(help="Viewpoints of a codebook built for --mesh.")] = DEFAULT_VIEWS,
    seed: Annotated[
        int | None, typer.Option(help="Seed of the rendered pose (default: a random one, printed).")
    ] = None,
    show: Annotated[Path, typer.Option(help="Where to write the picture of the result.")] = Path("edgepose_demo.png"),
    rerun: RerunOption = False,
    rrd: RrdOption = None,
) -> None:
    """Estimate the pose of the shipped example object rendered at a random pose.

    Renders a depth view of the power drill (or --mesh), estimates its pose, prints the estimate, the truth, the
    errors and the timings, and writes a picture (--show). Needs nothing but the installed package: the drill's
    codebook and mesh ship with it.
    """
    import secrets

    import edgepose
    from edgepose.eval import pose_errors, render_view
    from edgepose.model import read_mesh
    from edgepose.report import demo_text
    from edgepose.viz import Frame, recorder, save_result_png

    out = stdout_console()
    with handle_errors():
        if mesh is None:
            name, mesh_path = DEMO_OBJECT, SHIPPED_DIR / f"{DEMO_OBJECT}.ply"
            codebook_path = SHIPPED_DIR / f"{DEMO_OBJECT}.codebook"
            triangles = read_mesh(mesh_path)
            try:
                codebook = edgepose.Codebook.load(codebook_path)
            except edgepose.CodebookError as e:
                raise Failure(f"{e} (the shipped ones: `make codebooks`)") from None
            origin = f"shipped codebook {codebook_path.name}, {len(codebook)} views"
        else:
            name, mesh_path = mesh.stem, mesh
            triangles = read_mesh(mesh_path, scale=scale)
            codebook = edgepose.build_codebook(triangles, views=views, scale=1.0)
            t = codebook.timings
            origin = (
                f"codebook {len(codebook)} views built in {t['total']:.2f} s "
                f"(maps {t['maps']:.2f} s, encoding {t['encode']:.2f} s)"
            )
        seed = secrets.randbelow(1_000_000) if seed is None else seed
        view = render_view(triangles, seed=seed)
        edgepose.estimate(view.cloud, codebook)  # the first call loads onnxruntime's kernels
        pose = edgepose.estimate(view.cloud, codebook)
    model_points = codebook.model.mesh_points
    symmetric = codebook.symmetry.symmetric
    errors = pose_errors(model_points, pose.matrix, view.T_cam_obj, codebook.model.diameter, symmetric)
    text, caption = demo_text(name, origin, view, seed, pose, errors, symmetric)
    out.print(text)

    frame = Frame(view.cloud, model_points, pose.matrix, K=view.camera.K, depth=view.depth)
    with handle_errors():
        picture = save_result_png(show, frame, caption)
    recorder(spawn=rerun, save=rrd).log(name, frame)
    out.print(f"[bold]picture[/bold]     {picture}")


def _observed(
    cloud: Path, K: str | None, mask: Path | None, depth_scale: float
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The object's points (camera frame, metres) from a cloud file, or
    from a depth PNG with its intrinsics and mask; with the camera matrix
    and the depth image when it was one (None otherwise)."""
    import edgepose
    from edgepose import io

    if cloud.suffix.lower() == ".png":
        if K is None or mask is None:
            raise Failure(f"{cloud}: a depth image needs --K (intrinsics) and --mask (the object's pixels)")
        camera = io.parse_intrinsics(K)
        depth = io.read_depth_png(cloud)
        points = edgepose.cloud_from_depth(depth, camera, io.read_mask_png(mask), depth_scale=depth_scale)
        return points, camera, depth
    if K is not None or mask is not None:
        raise Failure("--K and --mask apply to depth images (.png) only")
    return io.read_cloud(cloud), None, None


def estimate(
    cloud: Annotated[
        Path,
        typer.Argument(
            help="The object's points: .ply/.pcd/.npy (metres, camera frame), "
            "or a 16-bit depth .png with --K and --mask."
        ),
    ],
    codebook: CodebookOption,
    K: IntrinsicsOption = None,
    mask: Annotated[
        Path | None,
        typer.Option(help="Segmentation mask PNG of the object (non-zero = object), same size as the depth image."),
    ] = None,
    depth_scale: DepthScaleOption = DEPTH_SCALE_MM,
    refine: Annotated[bool, typer.Option(help="Refine with point-to-plane ICP.")] = True,
    k: Annotated[int, typer.Option(help="Candidate viewpoints verified.")] = DEFAULT_SETTINGS.retrieve.k,
    truth: Annotated[
        Path | None, typer.Option(help="True T_cam_obj (JSON 4×4 / BOP gt entry, or .npy) to report the errors.")
    ] = None,
    show: Annotated[Path | None, typer.Option(help="Write a picture of the estimate (PNG).")] = None,
    bop_csv: Annotated[
        Path | None, typer.Option(help="Append the pose to a BOP results CSV (created with its header).")
    ] = None,
    scene_id: Annotated[int, typer.Option(help="BOP scene id.")] = 0,
    im_id: Annotated[int, typer.Option(help="BOP image id.")] = 0,
    obj_id: Annotated[int, typer.Option(help="BOP object id.")] = 1,
    rerun: RerunOption = False,
    rrd: RrdOption = None,
) -> None:
    """Estimate an object's pose in a cloud or a depth image; print it as JSON.

    JSON fields: matrix (4×4 T_cam_obj, metres), score (code cosine), fit (metres), view, refined, points, timings
    (seconds per stage of a warm call), and errors with --truth.
    """
    import edgepose
    from edgepose import io
    from edgepose.eval import BopRow, append_bop_csv
    from edgepose.report import errors_json, estimate_caption, json_text, pose_json
    from edgepose.viz import Frame, recorder, save_result_png

    with handle_errors():
        book = edgepose.Codebook.load(codebook)
        points, camera, depth = _observed(cloud, K, mask, depth_scale)
        T_true = io.read_pose(truth) if truth is not None else None
        # One untimed call first, so the timings are those of a long-running
        # process. A depth image's whole frame checks the pose against the
        # scene around the mask (depth and camera are None for a cloud).
        for _ in range(2):
            pose = edgepose.estimate(points, book, depth=depth, K=camera, depth_scale=depth_scale, refine=refine, k=k)

    result = pose_json(pose, len(points))
    model_points = book.model.mesh_points
    errors = None
    if T_true is not None:
        from edgepose.eval import pose_errors

        errors = pose_errors(model_points, pose.matrix, T_true, book.model.diameter, book.symmetry.symmetric)
        result["errors"] = errors_json(errors)
    print(json_text(result))

    frame = Frame(points, model_points, pose.matrix, K=camera, depth=depth)
    with handle_errors():
        if show is not None:
            save_result_png(show, frame, estimate_caption(cloud.name, len(points), pose, errors))
        if bop_csv is not None:
            try:
                row = BopRow(scene_id, im_id, obj_id, pose.score, pose.R, pose.t, pose.timings["total"])
                append_bop_csv(bop_csv, row)
            except ValueError as e:  # a malformed existing file
                raise Failure(str(e)) from None
    recorder(spawn=rerun, save=rrd).log(codebook.stem, frame)
