"""Maps: what a camera sees of the model, in its view frame, centred on the
visible points, scaled into the unit sphere and resampled to a fixed number
of points by farthest-point sampling. An observed cloud is normalised the
same way at query time (:func:`normalize_to_map`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from edgepose import _core
from edgepose.model import StandardModel
from edgepose.views import Viewpoints

DEFAULT_MAP_POINTS = 512


@dataclass(frozen=True)
class Maps:
    """Maps of every viewpoint of one model."""

    points: np.ndarray
    """(V, M, 3) float32 map points, view frame, unit-sphere scale."""
    centroids: np.ndarray
    """(V, 3) float64 centroid of each view's visible points, model frame, metres."""
    visible: np.ndarray
    """(V,) uint32 number of model points each view sees."""


def compute_maps(
    model: StandardModel,
    viewpoints: Viewpoints,
    points_per_map: int = DEFAULT_MAP_POINTS,
) -> Maps:
    """Maps of all viewpoints, computed in parallel in Rust (GIL released)."""
    if points_per_map < 1:
        raise ValueError(f"points_per_map must be positive, got {points_per_map}")
    points, centroids, visible = _core.compute_maps(
        model.core, np.ascontiguousarray(viewpoints.rotations, dtype=np.float64), points_per_map
    )
    return Maps(points, centroids, visible)


def visible_mask(model: StandardModel, rotation: np.ndarray) -> np.ndarray:
    """(N,) bool: which model points a camera with rotation object → view
    ``rotation`` sees (back-face culling plus a splatted z-buffer)."""
    r = np.asarray(rotation, dtype=np.float64)
    points = np.ascontiguousarray(model.points @ r.T.astype(np.float32))
    normals = np.ascontiguousarray(model.normals @ r.T.astype(np.float32))
    return _core.visible_mask(points, normals, model.spacing)


def farthest_point_sample(points: np.ndarray, m: int) -> np.ndarray:
    """(m,) indices of ``m`` evenly spread points of an (N, 3) cloud. Starts at
    the point farthest from the centroid; pads by cycling when N < m."""
    points = np.ascontiguousarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    return _core.farthest_point_sample(points, m).astype(np.intp)


def normalize_to_map(points: np.ndarray, scale: float, m: int = DEFAULT_MAP_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Centre an (N, 3) cloud on its centroid, multiply by ``scale`` and
    resample to ``m`` points. Returns ``(map (m, 3), centroid (3,))``, the
    centroid in the input's frame and units."""
    points = np.ascontiguousarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"points must have shape (N, 3) with N > 0, got {points.shape}")
    return _core.normalize_to_map(points, float(scale), m)
