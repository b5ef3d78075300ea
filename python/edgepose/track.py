"""``Tracker``: an object's pose over a depth stream, at hundreds of frames a
second on a CPU, re-initialising itself when it loses the object.

The first frame (and any frame after a failed check) runs the full
:func:`edgepose.estimate`. Every later frame predicts the pose from the last
one (constant velocity, optional), refines it by the Rust point-to-plane ICP
on a subsampled cloud and checks it with the same scoring terms as
``estimate`` (the share of observed points it explains, free-space
violations, the centre staying on the cloud). A pose that fails the check is
replaced, in the same call, by a fresh ``estimate``. Each returned
:class:`edgepose.Pose` says how it was obtained (``Pose.mode``).

Frames are camera-frame clouds in metres, segmented to the object, as for
``estimate``; poses are ``T_cam_obj``. Given each frame's depth image too
(``update(cloud, depth=, K=)``, or ``update_depth``), every pose is also
checked against the scene around the mask, as ``estimate`` checks it: a
tracked pose that would hide background the camera saw fails the check;
and the cloud's points on the surface the object stands on (a table the
mask spilled onto) are dropped first, as ``estimate`` drops them
(``EstimateSettings.support_plane``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from edgepose import _core
from edgepose.cloud import (
    DEPTH_SCALE_MM,
    checked_depth,
    checked_frame,
    checked_mask,
    clean_cloud,
    clean_depth_cloud,
    cloud_from_depth,
    median_depth,
)
from edgepose.codebook import Codebook
from edgepose.confidence import FitEvidence, SearchEvidence, evidence_of
from edgepose.encoder import Encoder, default_encoder
from edgepose.pose import Pose, check_types, estimate
from edgepose.settings import DEFAULT_SETTINGS, EstimateSettings
from edgepose.stages import (
    SCENE_MARGIN,
    SceneDepth,
    free_space_tolerance,
    near_the_cloud,
    off_support_plane,
    subsample,
)


@dataclass(frozen=True)
class TrackSettings:
    """Tuning of :class:`Tracker` (distances × the object's diameter d)."""

    points: int = 256
    """Observed points (a seeded subsample) each tracked frame's ICP and fit use ..."""
    grid_points: int = 1024
    """... and the points whose rays the free-space check looks along."""
    icp_iterations: int = 10
    icp_max_distance: float = 0.15
    """× d. ICP ignores pairs farther apart (covers ~0.5 m/s at 30 fps for 10 cm objects after prediction)."""
    velocity: float = 0.7
    """Each frame's pose is predicted from the last one moved by this share of
    the last frame's motion (constant velocity, damped; 0: no prediction).
    At 1, noise in the poses feeds the prediction and builds up."""
    inlier_distance: float = 0.04
    """× d. An observed point this close to the model at the pose is explained."""
    min_inlier_fraction: float = 0.85
    """A tracked pose explaining fewer of the observed points than this fails the check ..."""
    max_free_space_violation: float = 0.1
    """... as does one contradicting free space on more of its rays than this ..."""
    max_scene_violation: float = 0.1
    """... or, given the frame's depth, putting more than this share of its
    camera-facing points off the mask in front of the measured scene
    (``estimate`` searches again above the same share)."""

    def with_(self, **changes: object) -> TrackSettings:
        return dataclasses.replace(self, **changes)  # type: ignore[arg-type]


DEFAULT_TRACK_SETTINGS = TrackSettings()


class Tracker:
    """Follows one object (``codebook``) through successive frames.

    ``update(cloud)`` returns the frame's pose; ``reset()`` forgets the
    object, so the next frame is estimated afresh. The only state is the last
    pose and the one before (for the velocity); a frame that raises (an
    empty or garbage cloud: the usual :class:`edgepose.InvalidCloudError`)
    leaves it untouched. One tracker may be shared between threads (calls
    are serialised); trackers are independent. Deterministic: the same
    frames give the same poses."""

    def __init__(
        self,
        codebook: Codebook,
        *,
        settings: EstimateSettings = DEFAULT_SETTINGS,
        track: TrackSettings = DEFAULT_TRACK_SETTINGS,
        encoder: Encoder | None = None,
    ) -> None:
        check_types(codebook=codebook, settings=settings)
        self.codebook = codebook
        self.settings = settings
        self.track = track
        self.encoder = encoder or default_encoder()
        self._lock = threading.Lock()
        self._last: Pose | None = None
        self._previous: Pose | None = None

    @property
    def last(self) -> Pose | None:
        """The last frame's pose (None before the first frame or after ``reset``)."""
        return self._last

    def reset(self) -> None:
        """Forget the object: the next frame runs ``estimate``."""
        with self._lock:
            self._last = self._previous = None

    def update(
        self,
        cloud: object,
        *,
        depth: np.ndarray | None = None,
        K: object = None,
        depth_scale: float = DEPTH_SCALE_MM,
    ) -> Pose:
        """The object's pose in this frame's ``cloud`` ((N, 3) metres, camera
        frame, segmented to the object). ``depth`` (H, W) and ``K`` (3×3): the
        whole depth image the cloud was cut from (``depth / depth_scale``
        metres), when known: poses are then checked against the scene
        around the object too, as by :func:`edgepose.estimate`."""
        frame = checked_frame(depth, K, depth_scale)
        d = self.codebook.model.diameter
        return self._update(frame, lambda: cloud, lambda count: clean_cloud(cloud, d, count))

    def update_depth(
        self, depth: np.ndarray, K: np.ndarray, mask: np.ndarray | None = None, depth_scale: float = DEPTH_SCALE_MM
    ) -> Pose:
        """:meth:`update` on the cloud of a depth image, checked against the
        rest of the image: ``depth / depth_scale`` is metres (1000: uint16
        millimetres), ``K`` the 3×3 intrinsics, ``mask`` the object's pixels
        (see :func:`edgepose.cloud_from_depth`). A tracked frame reads only
        the pixels it uses."""
        frame = (*checked_depth(depth, K, depth_scale), depth_scale)
        return self.update_frame(frame, None if mask is None else checked_mask(mask, frame[0].shape))

    def update_frame(self, frame: tuple[np.ndarray, np.ndarray, float], mask: np.ndarray | None) -> Pose:
        """:meth:`update_depth` on a frame already checked (``(depth, K,
        depth_scale)`` from :func:`edgepose.cloud.checked_frame`, ``mask``
        from :func:`edgepose.cloud.checked_mask`): what
        :func:`edgepose.track_many` calls for each object of one frame."""
        d = self.codebook.model.diameter
        return self._update(
            frame,
            lambda: cloud_from_depth(*frame[:2], mask, frame[2]),
            lambda count: clean_depth_cloud(*frame, mask, d, count),
        )

    def _update(
        self,
        frame: tuple[np.ndarray, np.ndarray, float] | None,
        cloud: Callable[[], object],
        cleaned: Callable[[int], np.ndarray],
    ) -> Pose:
        """The frame's pose: tracked from the last one on ``cleaned(count)``
        (at most ``count`` of the object's points, float32, as
        :func:`edgepose.cloud.clean_cloud` keeps them), or estimated afresh
        on ``cloud()`` when there is none or the tracked pose fails its check."""
        with self._lock:
            t0 = time.perf_counter()
            pose = None
            if self._last is not None:
                pose = self._tracked(cleaned, t0, frame)
            if pose is None:
                mode = "initialised" if self._last is None else "reinitialised"
                depth, K, depth_scale = frame if frame is not None else (None, None, DEPTH_SCALE_MM)
                found = estimate(
                    cloud(),
                    self.codebook,
                    encoder=self.encoder,
                    settings=self.settings,
                    depth=depth,
                    K=K,
                    depth_scale=depth_scale,
                )
                timings = {**found.timings, "total": time.perf_counter() - t0}
                pose = dataclasses.replace(found, mode=mode, timings=timings)
            # A velocity only between consecutive tracked frames of the same object.
            self._previous = self._last if pose.mode == "tracked" else None
            self._last = pose
            return pose

    def _predicted(self) -> tuple[np.ndarray, np.ndarray]:
        """This frame's pose (model frame → camera: R, t of the model's
        centre) predicted from the last: the last frame's motion, as a turn
        about the object's centre and a shift of that centre, repeated
        (damped: noise must not build up)."""
        last, prev, track = self._last, self._previous, self.track
        assert last is not None
        centre = self.codebook.model.centre
        R, t = last.R, last.t + last.R @ centre
        if track.velocity > 0 and prev is not None:
            R = _scaled_turn(R @ prev.R.T, track.velocity) @ R
            t = t + track.velocity * (t - (prev.t + prev.R @ centre))
        return R, t

    def _tracked(
        self, cleaned: Callable[[int], np.ndarray], t0: float, frame: tuple[np.ndarray, np.ndarray, float] | None
    ) -> Pose | None:
        """The last pose refined onto the frame's points (``cleaned``, see
        :meth:`_update`), or None when it fails the check (``frame``: the
        checked depth image, K and depth scale, or None). Raises
        InvalidCloudError for a cloud that cannot be the object."""
        last, codebook, track, settings = self._last, self.codebook, self.track, self.settings
        assert last is not None
        model = codebook.model
        d = model.diameter
        seen = off_support_plane(cleaned(track.grid_points), frame, d, settings)
        points = subsample(seen, track.points, settings.subsample_seed)
        R, t = self._predicted()
        tolerance = free_space_tolerance(median_depth(seen), d, settings)
        depth, K, depth_scale = frame if frame is not None else (None, None, 1.0)
        fit = codebook.index.track_frame(
            points,
            seen,
            R[None],
            t[None],
            tolerance,
            _frame_settings(track, settings, d),
            depth,
            K,
            depth_scale,
            None if frame is None else model.box_corners,
        )
        icp, scores, tight = fit.icp, fit.loose, fit.tight
        R, t = icp.rotations[0], icp.translations[0]
        if not (
            np.isfinite(icp.rmse[0])
            and icp.inliers[0] >= settings.refine.min_icp_inliers
            and scores.inlier_fraction[0] >= track.min_inlier_fraction
            and scores.free_space_violation[0] <= track.max_free_space_violation
            and (not fit.with_scene or scores.scene_violation[0] <= track.max_scene_violation)
            and near_the_cloud(seen.mean(axis=0, dtype=np.float64), codebook, t[None], settings)[0]
        ):
            return None
        # What tracking does not recompute (the retrieval's score, how far the
        # pose stood out from its rivals) is carried from the estimate that started the track.
        evidence = evidence_of(
            FitEvidence.of(tight, scores, settings.refine.hypothesis_inlier_distance * d, math.hypot(*fit.sides) / d),
            SearchEvidence.carried(last.evidence, last.score),
        )
        judge = self.encoder.judge(with_scene=fit.with_scene)
        confidence = judge.probability(evidence) if judge else float("nan")
        if last.unseen_turn is not None:  # tracking cannot tell the turn the view left open either
            evidence["unseen_turn_share"] = last.unseen_turn.share
            confidence *= last.unseen_turn.share
        elapsed = time.perf_counter() - t0
        return dataclasses.replace(
            last,
            R=R,
            t=t - R @ model.centre,
            fit=float(tight.fit[0]),
            timings={"track": elapsed, "total": elapsed},
            refined=True,
            inlier_fraction=float(tight.inlier_fraction[0]),
            free_space_violation=float(scores.free_space_violation[0]),
            kept_points=len(seen),
            searches=0,
            confidence=confidence,
            strict_threshold=judge.strict_threshold if judge else float("nan"),
            evidence=evidence,
            alternatives=(),
            mode="tracked",
        )


def _scaled_turn(R: np.ndarray, share: float) -> np.ndarray:
    """The rotation about the same axis as ``R`` by ``share`` of its angle,
    in the same direction. A frame's turn is well below 180°, so its axis,
    with its sign, comes from the skew part of ``R``. Scalar arithmetic:
    numpy's per-call cost is most of a 3×3's."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    x, y, z = r21 - r12, r02 - r20, r10 - r01
    length = math.sqrt(x * x + y * y + z * z)  # 2 sin(angle)
    if length < 1e-9:
        return np.eye(3)
    x, y, z = x / length, y / length, z / length
    angle = share * math.acos(min(max((r00 + r11 + r22 - 1.0) / 2.0, -1.0), 1.0))
    s, c = math.sin(angle), 1.0 - math.cos(angle)  # Rodrigues: I + s K + c K²
    return np.array(
        [
            [1.0 - c * (y * y + z * z), c * x * y - s * z, c * x * z + s * y],
            [c * x * y + s * z, 1.0 - c * (x * x + z * z), c * y * z - s * x],
            [c * x * z - s * y, c * y * z + s * x, 1.0 - c * (x * x + y * y)],
        ]
    )


@functools.lru_cache(maxsize=64)
def _frame_settings(track: TrackSettings, settings: EstimateSettings, diameter: float) -> _core.TrackFrameSettings:
    """What a tracked frame's core call needs of the settings, in metres for
    an object of ``diameter``."""
    return _core.TrackFrameSettings(
        icp_iterations=track.icp_iterations,
        icp_max_distance=track.icp_max_distance * diameter,
        inlier_distance=track.inlier_distance * diameter,
        tight_inlier_distance=settings.refine.hypothesis_inlier_distance * diameter,
        model_stride=settings.score.free_space_model_stride,
        diameter=diameter,
        scene_radius=SceneDepth.radius,
        scene_margin=SCENE_MARGIN,
    )
