"""The ground truth of view-dependent ambiguity: whether a real view shows
what breaks an object's near symmetry (a mug's handle seen or hidden).

A mug whose handle the camera cannot see is, from that view, a cylinder:
no depth method can tell its turn about the body's axis, so the benchmark
must not count the turn it picks against it, only whether it says so
(:attr:`edgepose.Pose.unseen_turn`: a low confidence and the truth among
the alternatives). Which views hide the handle is read from the ground
truth: the model's *feature points* (those that some turn about the near
axis carries off the surface) placed at the true pose, projected into the
depth frame, and counted where the sensor saw them (inside the visible
mask, at their depth).

Units are metres; model points and axes in the object (mesh) frame; poses
``T_cam_obj`` in the OpenCV camera frame.
"""

from __future__ import annotations

import numpy as np

from edgepose.eval.metrics import nearest_distances
from edgepose.unseen_turn import NearAxis
from edgepose.views import rotation_about

#: Turns about the axis that a feature point is tried at (degrees): beyond
#: the ±20° a 0.1 × diameter ADD leaves a mug-sized body.
TURNS_DEG = np.arange(30.0, 331.0, 30.0)
#: A point is a feature point when some turn carries it farther than this
#: fraction of the diameter from every model point.
OFF_SURFACE = 0.1
#: A projected point is seen when the depth at its pixel is within this of
#: its own depth (metres): sensor noise, not the handle-to-body gap.
SEEN_WITHIN = 0.01
#: The view shows the feature when at least this share of the feature
#: points is seen.
MIN_SEEN_SHARE = 0.05


def feature_points(points: np.ndarray, axis: NearAxis, diameter: float) -> np.ndarray:
    """(N,) bool: the model points (N, 3, object frame, metres) that break
    the near symmetry about ``axis``: some turn in :data:`TURNS_DEG` carries
    them more than ``OFF_SURFACE × diameter`` from every model point."""
    points = np.asarray(points, dtype=np.float64)
    feature = np.zeros(len(points), dtype=bool)
    for angle in TURNS_DEG:
        R = rotation_about(axis.axis, np.radians(angle))
        turned = (points - axis.point) @ R.T + axis.point
        feature |= nearest_distances(turned, points) > OFF_SURFACE * diameter
    return feature


def seen_share(points: np.ndarray, T_cam_obj: np.ndarray, depth: np.ndarray, K: np.ndarray, mask: np.ndarray) -> float:
    """Share of ``points`` (M, 3, object frame, metres) that a depth frame
    (H, W, metres; 0 where the sensor has none) shows at pose ``T_cam_obj``:
    projected with ``K`` inside ``mask`` (the object's visible pixels) where
    the frame's depth is within :data:`SEEN_WITHIN` of the point's. 0 for no
    points."""
    if not len(points):
        return 0.0
    cam = points @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    z = cam[:, 2]
    front = z > 1e-6
    u = np.round(K[0, 0] * cam[:, 0] / np.where(front, z, 1.0) + K[0, 2]).astype(np.int64)
    v = np.round(K[1, 1] * cam[:, 1] / np.where(front, z, 1.0) + K[1, 2]).astype(np.int64)
    h, w = depth.shape
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    seen = np.zeros(len(points), dtype=bool)
    ui, vi = u[inside], v[inside]
    seen[inside] = mask[vi, ui] & (depth[vi, ui] > 0) & (np.abs(depth[vi, ui] - z[inside]) < SEEN_WITHIN)
    return float(seen.mean())


def view_hides_feature(
    points: np.ndarray,
    features: np.ndarray,
    T_cam_obj: np.ndarray,
    depth: np.ndarray,
    K: np.ndarray,
    mask: np.ndarray,
) -> bool:
    """Whether the view shows less than :data:`MIN_SEEN_SHARE` of the
    feature points (``features``: :func:`feature_points` of ``points``) at
    the true pose: the turn about the near axis is the view's to leave open."""
    return bool(features.any()) and seen_share(points[features], T_cam_obj, depth, K, mask) < MIN_SEEN_SHARE
