"""``edgepose track``: one object's pose through a sequence of frames.

Units are metres; poses are ``T_cam_obj``, camera frame as OpenCV.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from edgepose.cli.app import (
    CodebookOption,
    DepthScaleOption,
    Failure,
    IntrinsicsOption,
    RerunOption,
    RrdOption,
    handle_errors,
    stdout_console,
)
from edgepose.cloud import DEPTH_SCALE_MM

if TYPE_CHECKING:
    from edgepose.pose import Pose

FRAME_SUFFIXES = (".png", ".npy", ".ply", ".pcd")


def track(
    frames: Annotated[
        list[Path],
        typer.Argument(
            help="Frames in order: 16-bit depth .png (with --K and --masks) or .npy/.ply/.pcd clouds (metres), "
            "or folders of them (sorted by name)."
        ),
    ],
    codebook: CodebookOption,
    K: IntrinsicsOption = None,
    masks: Annotated[
        Path | None,
        typer.Option(
            help="The object's masks for depth frames: a folder of PNGs named as the frames, or one PNG for all."
        ),
    ] = None,
    depth_scale: DepthScaleOption = DEPTH_SCALE_MM,
    out: Annotated[Path, typer.Option("-o", "--out", help="Poses CSV to write.")] = Path("poses.csv"),
    rerun: RerunOption = False,
    rrd: RrdOption = None,
) -> None:
    """Track an object through frames; write one pose per frame to a CSV.

    The first frame is estimated, later ones are tracked from the last pose (a few ms) and estimated again when the
    tracked pose fails its check. Depth frames are given whole to the tracker: poses are checked against the scene
    around the mask, and the table or wall the object stands on is left out of its cloud. CSV columns: frame, the
    4×4 T_cam_obj row-major (m00 … m33, metres), mode (initialised, tracked, reinitialised, or error with the
    reason), confidence, ms. Ends with a summary line.
    """
    import edgepose
    from edgepose import io
    from edgepose.viz import Frame, NullRecorder, recorder

    with handle_errors():
        book = edgepose.Codebook.load(codebook)
        paths = _frame_paths(frames)
        depth_frames = [p for p in paths if p.suffix.lower() == ".png"]
        camera = None
        if depth_frames:
            if K is None or masks is None:
                raise Failure("depth frames (.png) need --K (intrinsics) and --masks (the object's pixels)")
            camera = io.parse_intrinsics(K)
        elif K is not None or masks is not None:
            raise Failure("--K and --masks apply to depth frames (.png) only")
        tracker = edgepose.Tracker(book)
        log = recorder(spawn=rerun, save=rrd)
        model_points = book.model.mesh_points
        rows, times, modes = [], [], []
        for i, path in enumerate(paths):
            depth = mask = cloud = None
            try:  # a depth frame also checks the pose against the scene and drops the table (Tracker.update)
                if path.suffix.lower() == ".png":
                    assert camera is not None and masks is not None  # checked above
                    depth, mask = io.read_depth_png(path), io.read_mask_png(_mask_for(path, masks))
                    pose = tracker.update_depth(depth, camera, mask, depth_scale=depth_scale)
                else:
                    cloud = io.read_cloud(path)
                    pose = tracker.update(cloud)
            except edgepose.EdgePoseError as e:  # an empty or bad frame: reported, the track goes on
                rows.append([i, path.name, *([""] * 16), f"error: {e}", "", ""])
                modes.append("error")
                continue
            ms = pose.timings["total"] * 1e3
            times.append(ms)
            modes.append(pose.mode)
            rows.append(_pose_row(i, path, pose, ms))
            if not isinstance(log, NullRecorder):  # the whole cloud is made for the picture only
                if cloud is None:
                    assert depth is not None and camera is not None
                    cloud = edgepose.cloud_from_depth(depth, camera, mask, depth_scale=depth_scale)
                log.log(codebook.stem, Frame(cloud, model_points, pose.matrix, K=camera, depth=depth))
        _write_poses(out, rows)
    _print_summary(len(paths), modes, times, out)


def _print_summary(frames: int, modes: list[str], times: list[float], out: Path) -> None:
    """One line: how many frames were tracked, initialised, re-initialised
    or left without a pose, and the median milliseconds per frame."""
    import numpy as np

    counts = {m: modes.count(m) for m in ("initialised", "tracked", "reinitialised", "error")}
    tracked = [t for t, m in zip(times, [m for m in modes if m != "error"]) if m == "tracked"]
    stdout_console().print(
        f"{frames} frames: {counts['tracked']} tracked, {counts['initialised']} initialised, "
        f"{counts['reinitialised']} re-initialised, {counts['error']} without a pose; "
        f"median {np.median(times) if times else float('nan'):.2f} ms per frame"
        f"{f', tracked {np.median(tracked):.2f} ms' if tracked else ''}; poses in {out}"
    )


def _pose_row(i: int, path: Path, pose: Pose, ms: float) -> list:
    """Frame ``i``'s CSV row: its file, ``T_cam_obj`` row-major, mode, confidence, ms."""
    return [i, path.name, *(f"{v:.8f}" for v in pose.matrix.ravel()), pose.mode, f"{pose.confidence:.4f}", f"{ms:.3f}"]


def _write_poses(out: Path, rows: list[list]) -> None:
    """The track's CSV: a header, then one row a frame (see :func:`track`)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    with out.open("w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(
            ["frame", "file", *(f"m{r}{c}" for r in range(4) for c in range(4)), "mode", "confidence", "ms"]
        )
        writer.writerows(rows)


def _frame_paths(frames: list[Path]) -> list[Path]:
    """The frame files, folders expanded (their frame files sorted by name)."""
    paths: list[Path] = []
    for f in frames:
        if f.is_dir():
            paths += sorted(p for p in f.iterdir() if p.suffix.lower() in FRAME_SUFFIXES)
        elif f.is_file():
            paths.append(f)
        else:
            raise Failure(f"{f}: no such file or folder")
    if not paths:
        raise Failure("no frames (.png, .npy, .ply, .pcd) found")
    return paths


def _mask_for(frame: Path, masks: Path) -> Path:
    """The mask of a depth frame: the same name in a masks folder, or the one mask file."""
    if masks.is_dir():
        mask = masks / frame.name
        if not mask.is_file():
            raise Failure(f"{frame.name}: no mask {mask}")
        return mask
    return masks
