"""Real sensor frames in the BOP layout (e.g. YCB-Video's): every target
estimated from its annotated visible mask, optionally grown by a few pixels
as a detector's mask spills, by :func:`edgepose.estimate` from the cloud
alone and given the depth frame; and each scene's consecutive frames
followed by a :class:`edgepose.Tracker` per object.

Units are metres; poses are ``T_cam_obj`` in the OpenCV camera frame.
Correctness is *depth-fair* ADD(-S) < 0.1 × diameter: ADD-S for an object
whose model edgepose finds shape-symmetric (a can, a box), since depth
alone cannot tell its turns apart, ADD otherwise. *View-fair* correctness
adds the views that cannot tell a pose: a target whose view hides what
breaks its object's near symmetry (a mug's handle, read from the ground
truth by :mod:`edgepose.eval.view_ambiguity`) counts when its pose is
flagged (confidence below the strict threshold, the truth among its
alternatives; for a tracked frame, among the turns its ``unseen_turn``
leaves open).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from edgepose.cloud import cloud_from_depth, dilate
from edgepose.codebook import Codebook
from edgepose.eval.bop import BopDataset, BopGt, BopImage, BopRow, BopTarget
from edgepose.eval.metrics import PoseErrors, pose_errors
from edgepose.eval.view_ambiguity import feature_points, view_hides_feature
from edgepose.frame import estimate_many, track_many
from edgepose.pose import Pose, estimate
from edgepose.settings import DEFAULT_SETTINGS, EstimateSettings
from edgepose.symmetry import transform_from
from edgepose.track import Tracker
from edgepose.unseen_turn import NearAxis, near_axis, turned_about


@dataclass(frozen=True, eq=False)
class RealObject:
    """What the metrics need of one dataset object, metres, mesh frame."""

    obj_id: int
    points: np.ndarray
    """(N, 3) model points (the codebook's mesh samples)."""
    diameter: float
    symmetric: bool
    """Shape-symmetric as edgepose detects it: judged by ADD-S (depth-fair)."""
    features: np.ndarray | None = None
    """(N,) bool: the ``points`` that break a near symmetry (a mug's handle),
    for an asymmetric object with a near-symmetry axis; None otherwise."""

    def hidden_by(self, T_cam_obj: np.ndarray, depth: np.ndarray, K: np.ndarray, mask: np.ndarray) -> bool:
        """Whether a view (depth frame, metres; the object's visible
        ``mask``) at the true pose hides the features."""
        if self.features is None:
            return False
        return view_hides_feature(self.points, self.features, T_cam_obj, depth, K, mask)


def real_objects(codebooks: dict[int, Codebook]) -> dict[int, RealObject]:
    """The metric model of each object, from its codebook."""
    return {obj_id: _real_object(obj_id, cb) for obj_id, cb in codebooks.items()}


def _real_object(obj_id: int, cb: Codebook) -> RealObject:
    points, diameter, symmetric = cb.model.mesh_points, cb.model.diameter, cb.symmetry.symmetric
    axis = None if symmetric else near_axis(cb.symmetry)
    features = None if axis is None else feature_points(points, axis, diameter)
    return RealObject(obj_id, points, diameter, symmetric, features)


@dataclass
class TargetResult:
    """One target's estimate at one mask level, by one method."""

    method: str
    """``estimate`` (cloud alone) or ``estimate+frame`` (given the depth frame)."""
    grow_px: int
    """Pixels the annotated visible mask was grown by (0: as annotated)."""
    scene_id: int
    im_id: int
    obj_id: int
    visib_fract: float
    points: int
    """Points in the masked cloud."""
    seconds: float
    """Wall time of the estimate call."""
    errors: PoseErrors
    pose: Pose | None
    """None when the estimate raised (``error``)."""
    error: str = ""
    alternative_correct: bool = False
    """Whether one of the pose's alternatives is right (depth-fair)."""
    view_hides_feature: bool = False
    """Whether the view hides what breaks the object's near symmetry (from
    the ground truth): no depth method can tell the turn it leaves open."""

    @property
    def correct(self) -> bool:
        return bool(self.errors.correct_add_or_s)

    @property
    def flagged(self) -> bool:
        """The pose says it cannot tell: confidence below its strict
        threshold and the truth among its alternatives."""
        return self.pose is not None and self.pose.confidence < self.pose.strict_threshold and self.alternative_correct

    @property
    def view_fair_correct(self) -> bool:
        """Right, or the view hides the feature and the pose is flagged."""
        return self.correct or (self.view_hides_feature and self.flagged)


def target_instances(dataset: BopDataset, targets: Iterable[BopTarget]) -> list[tuple[BopImage, int, int]]:
    """(image, gt_id, obj_id) of each instance to find: per target, its
    ``inst_count`` most visible annotated instances."""
    out = []
    for t in targets:
        image = dataset.image(t.scene_id, t.im_id)
        gts = sorted((g for g in image.gts if g.obj_id == t.obj_id), key=lambda g: -g.visib_fract)
        out += [(image, g.gt_id, t.obj_id) for g in gts[: t.inst_count]]
    return out


def estimate_targets(
    dataset: BopDataset,
    targets: Iterable[BopTarget],
    codebooks: dict[int, Codebook],
    grow_px: int,
    *,
    with_frame: bool,
    settings: EstimateSettings = DEFAULT_SETTINGS,
    progress: Callable[[TargetResult], None] | None = None,
) -> list[TargetResult]:
    """Estimate each target instance from its visible mask grown by
    ``grow_px`` pixels (from the cloud alone, or ``with_frame``: given the
    depth frame too). One untimed warm-up estimate precedes the timed ones."""
    objects = real_objects(codebooks)
    method = "estimate+frame" if with_frame else "estimate"
    results = []
    warmed = False
    depths: dict[tuple[int, int], np.ndarray] = {}
    for image, gt_id, obj_id in target_instances(dataset, targets):
        key = (image.scene_id, image.im_id)
        if key not in depths:
            depths.clear()  # one image at a time: instances come grouped by image
            depths[key] = image.depth()
        depth = depths[key]
        mask = image.mask(gt_id)
        if grow_px:
            mask = dilate(mask, grow_px)
        cloud = cloud_from_depth(depth, image.K, mask, depth_scale=1.0)
        frame = {"depth": depth, "K": image.K, "depth_scale": 1.0} if with_frame else {}
        if not warmed:
            estimate(cloud, codebooks[obj_id], settings=settings, **frame)  # type: ignore[arg-type]
            warmed = True
        gt = next(g for g in image.gts if g.gt_id == gt_id)
        obj = objects[obj_id]
        t0 = time.perf_counter()
        try:
            pose: Pose | None = estimate(cloud, codebooks[obj_id], settings=settings, **frame)  # type: ignore[arg-type]
            error = ""
        except Exception as e:  # a failed estimate is a result
            pose, error = None, f"{type(e).__name__}: {e}"
        seconds = time.perf_counter() - t0
        T_est = pose.matrix if pose is not None else np.full((4, 4), np.nan)
        errors = pose_errors(obj.points, T_est, gt.matrix, obj.diameter, obj.symmetric)
        alternative_correct = pose is not None and any(
            pose_errors(obj.points, a.matrix, gt.matrix, obj.diameter, obj.symmetric).correct_add_or_s
            for a in pose.alternatives
        )
        result = TargetResult(
            method,
            grow_px,
            image.scene_id,
            image.im_id,
            obj_id,
            gt.visib_fract,
            len(cloud),
            seconds,
            errors,
            pose,
            error,
            alternative_correct,
            obj.hidden_by(gt.matrix, depth, image.K, image.mask(gt_id)),
        )
        results.append(result)
        if progress:
            progress(result)
    return results


def bop_rows(results: list[TargetResult]) -> list[BopRow]:
    """The estimates as BOP rows; each row's time is its image's total."""
    per_image: dict[tuple[int, int], float] = {}
    for r in results:
        per_image[(r.scene_id, r.im_id)] = per_image.get((r.scene_id, r.im_id), 0.0) + r.seconds
    return [
        BopRow(r.scene_id, r.im_id, r.obj_id, r.pose.confidence, r.pose.R, r.pose.t, per_image[(r.scene_id, r.im_id)])
        for r in results
        if r.pose is not None
    ]


@dataclass
class TrackedFrame:
    """One object in one frame of a clip, followed by a tracker."""

    scene_id: int
    im_id: int
    obj_id: int
    mode: str
    """``initialised``, ``tracked``, ``reinitialised``, or ``lost`` (the frame raised)."""
    seconds: float
    correct: bool
    confidence: float
    view_fair: bool = False
    """Right, or the view hides the object's feature (from the ground truth)
    and the pose is flagged: confidence below its strict threshold and the
    truth among the turns its ``unseen_turn`` leaves open."""


@dataclass
class ClipRun:
    """Every object of every clip followed through its frames, and the same
    frames estimated afresh by :func:`edgepose.estimate_many`."""

    frames: list[TrackedFrame] = field(default_factory=list)
    tracker_image_seconds: list[float] = field(default_factory=list)
    """Per image: the tracker updates of all its objects, one after another, added up."""
    track_many_image_seconds: list[float] = field(default_factory=list)
    """Per image: one :func:`edgepose.track_many` call on all its objects
    (their own trackers, in parallel threads)."""
    track_many_same: list[bool] = field(default_factory=list)
    """Per object and image: whether ``track_many``'s pose equals the lone tracker's."""
    many_image_seconds: list[float] = field(default_factory=list)
    """Per image: one ``estimate_many`` call on all its objects."""
    many_correct: list[bool] = field(default_factory=list)
    """Per object and image: whether ``estimate_many``'s pose is right."""


def track_clips(
    dataset: BopDataset,
    codebooks: dict[int, Codebook],
    grow_px: int = 0,
    *,
    scenes: Iterable[int] | None = None,
    images: int | None = None,
    settings: EstimateSettings = DEFAULT_SETTINGS,
) -> ClipRun:
    """Each scene's images in order, as a clip: one :class:`edgepose.Tracker`
    per object of the scene fed ``update_depth`` with its visible mask
    (grown by ``grow_px``), and, on the same frames, a second set of
    trackers fed all at once by :func:`edgepose.track_many`, and
    ``estimate_many`` over all the objects (``images``: only each scene's
    first so many). Objects with a codebook only; an object less than 10 %
    visible in a frame is skipped there (its trackers keep their last pose)."""
    objects = real_objects(codebooks)
    run = ClipRun()
    for scene_id in scenes if scenes is not None else dataset.scene_ids():
        trackers: dict[int, Tracker] = {}
        together: dict[int, Tracker] = {}
        for im_id in dataset.image_ids(scene_id)[:images]:
            image = dataset.image(scene_id, im_id)
            depth = image.depth()
            gts = [g for g in image.gts if g.obj_id in codebooks and g.visib_fract >= 0.1]
            masks = [dilate(image.mask(g.gt_id), grow_px) if grow_px else image.mask(g.gt_id) for g in gts]

            def tracker_of(group: dict[int, Tracker], gt: BopGt) -> Tracker:
                return group.setdefault(gt.gt_id, Tracker(codebooks[gt.obj_id], settings=settings))

            image_seconds = 0.0
            alone: list[Pose | None] = []
            for gt, mask in zip(gts, masks):
                t0 = time.perf_counter()
                try:
                    pose: Pose | None = tracker_of(trackers, gt).update_depth(depth, image.K, mask, depth_scale=1.0)
                except Exception:  # a lost frame is a result
                    pose = None
                seconds = time.perf_counter() - t0
                image_seconds += seconds
                alone.append(pose)
                mode, confidence = (pose.mode, pose.confidence) if pose is not None else ("lost", 0.0)
                obj = objects[gt.obj_id]
                right = _right(obj, pose, gt)
                fair = right or (
                    _turn_flagged(obj, pose, gt) and obj.hidden_by(gt.matrix, depth, image.K, image.mask(gt.gt_id))
                )
                run.frames.append(TrackedFrame(scene_id, im_id, gt.obj_id, mode, seconds, right, confidence, fair))
            run.tracker_image_seconds.append(image_seconds)
            tracked = track_many(
                depth, image.K, [(m, tracker_of(together, g)) for g, m in zip(gts, masks)], depth_scale=1.0
            )
            run.track_many_image_seconds.append(tracked.seconds)
            run.track_many_same += [_same_pose(a, b) for a, b in zip(alone, tracked.poses)]
            many = estimate_many(
                depth,
                image.K,
                [(m, codebooks[g.obj_id]) for g, m in zip(gts, masks)],
                depth_scale=1.0,
                settings=settings,
            )
            run.many_image_seconds.append(many.seconds)
            run.many_correct += [_right(objects[g.obj_id], p, g) for g, p in zip(gts, many.poses)]
    return run


def _right(obj: RealObject, pose: Pose | None, gt: BopGt) -> bool:
    """Whether ``pose`` is depth-fair right for the annotated instance ``gt``."""
    if pose is None:
        return False
    return bool(pose_errors(obj.points, pose.matrix, gt.matrix, obj.diameter, obj.symmetric).correct_add_or_s)


def _turn_flagged(obj: RealObject, pose: Pose | None, gt: BopGt) -> bool:
    """Whether ``pose`` says it cannot tell the turn: confidence below its
    strict threshold and the truth among the pose turned by each angle of
    its ``unseen_turn`` (the alternatives a tracked pose carries)."""
    if pose is None or pose.unseen_turn is None or not pose.confidence < pose.strict_threshold:
        return False
    turn = pose.unseen_turn
    rotations, translations = turned_about(
        pose.R, pose.t, NearAxis(turn.axis, turn.point), np.zeros(3), turn.angles_deg
    )
    return any(
        pose_errors(obj.points, transform_from(R, t), gt.matrix, obj.diameter, obj.symmetric).correct_add_or_s
        for R, t in zip(rotations, translations)
    )


def _same_pose(a: Pose | None, b: Pose | None) -> bool:
    """Whether two trackers gave the same pose (or both none)."""
    if a is None or b is None:
        return a is b
    return bool(np.array_equal(a.matrix, b.matrix)) and a.mode == b.mode
