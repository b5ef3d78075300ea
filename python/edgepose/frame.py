"""``estimate_many(depth, K, objects)``: the poses of several objects seen in
one depth frame, each given by its mask and its codebook; and
``track_many(depth, K, objects)``: one frame's update of several objects'
trackers, each given by its mask and its :class:`edgepose.Tracker`.

It does what :func:`edgepose.estimate` does per object given the frame
(``estimate(cloud, codebook, depth=depth, K=K)``: poses are checked against
the scene around each object too), but shares the frame's work: the depth
image is checked once, and the objects are estimated in parallel threads
(the Rust core and onnxruntime release the GIL), each thread taking the
next object when done with its last and keeping that object's work in the
core to itself. The poses equal
:func:`edgepose.estimate`'s on each object's masked cloud and the frame.

Units are metres; camera frames follow OpenCV; poses are ``T_cam_obj``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from edgepose.cloud import DEPTH_SCALE_MM, checked_depth, checked_mask, clean_depth_cloud
from edgepose.codebook import Codebook
from edgepose.encoder import Encoder, default_encoder
from edgepose.errors import EdgePoseError, InvalidArgumentError
from edgepose.pose import Pose, check_estimate_inputs, check_types, pose_from_query
from edgepose.search import Laps
from edgepose.settings import DEFAULT_SETTINGS, EstimateSettings, usable_cores
from edgepose.stages import query_of_cleaned
from edgepose.track import Tracker
from edgepose.workers import each


@dataclass(frozen=True, eq=False)
class FramePoses:
    """The poses of one frame's objects, in the order they were given."""

    poses: tuple[Pose | None, ...]
    """Each object's pose; None where its input was unusable (see ``errors``)."""
    errors: tuple[EdgePoseError | None, ...]
    """Why an object has no pose (e.g. ``InvalidCloudError``: its mask holds
    too few measured pixels); None for the objects that have one."""
    seconds: float
    """Wall-clock time from the depth image to the last pose, seconds: the
    per-image time the BOP benchmark records (the networks' first load,
    once per process, is not counted)."""
    timings: dict = field(default_factory=dict)
    """Seconds per stage summed over the objects (the stages of
    :attr:`edgepose.Pose.timings`; ``prepare_query`` includes cutting each
    cloud from the frame), and ``total``: :attr:`seconds`."""

    def __len__(self) -> int:
        return len(self.poses)


def estimate_many(
    depth: np.ndarray,
    K: object,
    objects: Sequence[tuple[np.ndarray, Codebook]],
    *,
    depth_scale: float = DEPTH_SCALE_MM,
    refine: bool = True,
    encoder: Encoder | None = None,
    settings: EstimateSettings = DEFAULT_SETTINGS,
    workers: int | None = None,
) -> FramePoses:
    """The pose ``T_cam_obj`` of each ``(mask, codebook)`` of ``objects`` in
    one frame: ``depth`` (H, W) with ``depth / depth_scale`` in metres (1000
    for uint16 millimetres, 1 for float metres; 0: no measurement), ``K`` the
    3×3 pinhole matrix, each ``mask`` (H, W) bool the object's pixels (a
    detector's mask that spills is fine, as for :func:`edgepose.estimate`).

    ``workers`` threads share the objects (default: one per core, at most one
    per object). A bad frame (depth, ``K``, a mask's shape, a codebook of
    another encoder) raises; an object whose mask gives no usable cloud gets
    ``None`` and its error in :attr:`FramePoses.errors`, and the others
    their poses."""
    encoder = encoder or default_encoder()
    t0 = time.perf_counter()
    workers = max(1, min(workers or usable_cores(), len(objects)))
    depth, K = checked_depth(depth, K, depth_scale)
    masks, codebooks = _checked_objects(objects, depth.shape, encoder, settings)
    frame = (depth, K, depth_scale)

    def estimated(i: int) -> tuple[Pose | None, EdgePoseError | None]:
        laps = Laps()
        try:
            cleaned = clean_depth_cloud(*frame, masks[i], codebooks[i].model.diameter, settings.max_cloud_points)
            query = query_of_cleaned(cleaned, codebooks[i], settings, frame)
        except EdgePoseError as e:
            return None, e
        laps("prepare_query")
        return pose_from_query(query, codebooks[i], encoder, refine, settings, laps), None

    results = each(estimated, len(objects), workers)
    poses, errors = zip(*results) if results else ((), ())
    seconds = time.perf_counter() - t0
    timings: dict[str, float] = {}
    for pose in (p for p in poses if p is not None):
        for stage, spent in pose.timings.items():
            if stage != "total":
                timings[stage] = timings.get(stage, 0.0) + spent
    timings["total"] = seconds
    return FramePoses(tuple(poses), tuple(errors), seconds, timings)


def track_many(
    depth: np.ndarray,
    K: object,
    objects: Sequence[tuple[np.ndarray, Tracker]],
    *,
    depth_scale: float = DEPTH_SCALE_MM,
    workers: int | None = None,
) -> FramePoses:
    """Each ``(mask, tracker)`` of ``objects`` updated with one frame, as
    ``tracker.update_depth(depth, K, mask, depth_scale)`` would (same
    arguments as :func:`estimate_many`), the objects in ``workers`` parallel
    threads (default: one per core, at most one per object; the Rust core
    releases the GIL) and the frame checked once. A bad frame (depth, ``K``,
    a mask's shape, something other than a :class:`edgepose.Tracker`)
    raises; an object whose mask gives no usable cloud gets ``None`` and its
    error in :attr:`FramePoses.errors` (its tracker keeps its last pose), and
    the others their poses. ``seconds`` is the frame's wall-clock time."""
    t0 = time.perf_counter()
    workers = max(1, min(workers or usable_cores(), len(objects)))
    frame = (*checked_depth(depth, K, depth_scale), depth_scale)
    for i, pair in enumerate(objects):
        if not (isinstance(pair, (tuple, list)) and len(pair) == 2 and isinstance(pair[1], Tracker)):
            raise InvalidArgumentError(f"objects[{i}] must be a (mask, Tracker) pair, got {pair!r:.80}")
    masks = [checked_mask(mask, frame[0].shape) for mask, _ in objects]

    def updated(i: int) -> tuple[Pose | None, EdgePoseError | None]:
        try:
            return objects[i][1].update_frame(frame, masks[i]), None
        except EdgePoseError as e:
            return None, e

    results = each(updated, len(objects), workers)
    poses, errors = zip(*results) if results else ((), ())
    seconds = time.perf_counter() - t0
    return FramePoses(tuple(poses), tuple(errors), seconds, {"total": seconds})


def _checked_objects(
    objects: Sequence[tuple[np.ndarray, Codebook]], shape: tuple[int, ...], encoder: Encoder, settings: EstimateSettings
) -> tuple[list[np.ndarray], list[Codebook]]:
    """The masks (bool, ``shape``) and codebooks of ``objects``, each pair
    checked as :func:`edgepose.estimate` checks its arguments; the errors name ``objects[i]``."""
    for i, pair in enumerate(objects):
        if not (isinstance(pair, (tuple, list)) and len(pair) == 2):
            raise InvalidArgumentError(f"objects[{i}] must be a (mask, codebook) pair, got {pair!r:.80}")
        try:
            check_types(codebook=pair[1])
        except InvalidArgumentError as e:
            raise InvalidArgumentError(f"objects[{i}]: {e}") from None
    masks = [checked_mask(mask, shape) for mask, _ in objects]
    codebooks = [codebook for _, codebook in objects]
    for codebook in codebooks:
        check_estimate_inputs(codebook, encoder, settings)
    return masks, codebooks
