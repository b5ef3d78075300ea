"""Training pairs: an *observed* map (what a depth sensor would give, turned
by a random in-plane angle) and the clean codebook map of a nearby
viewpoint, with the true in-plane angle between them."""

from __future__ import annotations

from dataclasses import dataclass

import edgepose
import numpy as np
from edgepose.maps import DEFAULT_MAP_POINTS, visible_mask
from edgepose.views import rotation_about_z

#: Observed views lie this close to their codebook view (2,100 views are ~4.4° apart).
MAX_VIEW_OFFSET_DEG = 3.0
#: Share of observed maps with something in front hiding part of the object,
#: and the largest hidden fraction (real shelves and bins hide up to ~70 %).
OCCLUSION_PROBABILITY = 0.7
MAX_HIDDEN = 0.7
#: Share of observed maps whose mask spilled onto a surface behind the
#: object, and the most spilled points (fraction of the object's).
SPILL_PROBABILITY = 0.2
MAX_SPILL = 0.15


@dataclass
class Batch:
    observed: np.ndarray  # (B, M, 3) float32
    codebook: np.ndarray  # (B, M, 3) float32 clean maps of the nearby views
    directions: np.ndarray  # (B, 3) codebook view directions (object frame)
    shape_ids: np.ndarray  # (B,)
    angles: np.ndarray  # (B,) in-plane turn codebook → observed, radians


def random_directions(rng: np.random.Generator, n: int) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def perturb(direction: np.ndarray, max_deg: float, rng: np.random.Generator) -> np.ndarray:
    """A direction within ``max_deg`` of ``direction`` (uniform over the cap's area)."""
    axis = np.cross(direction, random_directions(rng, 1)[0])
    axis /= np.linalg.norm(axis)
    angle = np.radians(max_deg) * np.sqrt(rng.random())
    # Rodrigues rotation of `direction` about `axis` (perpendicular to it).
    return direction * np.cos(angle) + np.cross(axis, direction) * np.sin(angle)


def observe(
    model: edgepose.StandardModel, rotation: np.ndarray, rng: np.random.Generator, m: int = DEFAULT_MAP_POINTS
) -> np.ndarray:
    """A sensor-like map of ``model`` seen with ``rotation`` (object → view):
    uneven density, dropout, a cut-away occlusion, depth noise and
    quantisation, a small scale error. Falls back to the clean view when too
    little is left."""
    seen = visible_mask(model, rotation)
    r32 = rotation.T.astype(np.float32)
    points = model.points[seen] @ r32
    normals = model.normals[seen] @ r32
    keep = np.ones(len(points), dtype=bool)
    if rng.random() < 0.5:  # sensors sample grazing surfaces sparsely
        keep &= rng.random(len(points)) < np.clip(-normals[:, 2] * 1.2, 0.1, 1.0)
    keep &= rng.random(len(points)) < rng.uniform(0.5, 1.0)
    if rng.random() < OCCLUSION_PROBABILITY:
        keep &= ~occluded(points, rng.uniform(0.0, MAX_HIDDEN), rng)
    if keep.sum() >= 64:
        points = points[keep]
    points = points.astype(np.float64)
    if rng.random() < SPILL_PROBABILITY:
        points = np.concatenate([points, spill(points, rng.uniform(0.0, MAX_SPILL), rng)])
    sigma = rng.uniform(0.0005, 0.003)  # metres, along the ray
    points[:, 2] += rng.normal(0.0, sigma, len(points))
    points[:, :2] += rng.normal(0.0, sigma / 3, (len(points), 2))
    if rng.random() < 0.5:
        points[:, 2] = np.round(points[:, 2] / 0.001) * 0.001
    scale = model.scale * (1.0 + rng.uniform(-0.03, 0.03))
    return edgepose.normalize_to_map(points.astype(np.float32), scale, m)[0]


def occluded(points: np.ndarray, hidden: float, rng: np.random.Generator) -> np.ndarray:
    """(N,) bool: the view-frame ``points`` hidden by an occluder in front,
    about ``hidden`` of them: the side beyond a straight edge (a box's) or a
    band across the object (a post's, a cylinder's), in a random direction."""
    a = rng.uniform(0, 2 * np.pi)
    side = points[:, 0] * np.cos(a) + points[:, 1] * np.sin(a)
    if rng.random() < 0.6:
        return side > np.quantile(side, 1.0 - hidden)
    start = rng.uniform(0.0, 1.0 - hidden)
    lo, hi = np.quantile(side, [start, start + hidden])
    return (side >= lo) & (side <= hi)


def spill(points: np.ndarray, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """About ``fraction`` × N points of a surface 2–6 cm behind the view-frame
    ``points``, just outside their silhouette: what a detector mask grown
    over the background adds."""
    count = int(fraction * len(points))
    centre = points[:, :2].mean(axis=0)
    picked = points[rng.integers(len(points), size=count)]
    ring = centre + (picked[:, :2] - centre) * rng.uniform(1.02, 1.12, size=(count, 1))
    depth = points[:, 2].max() + rng.uniform(0.02, 0.06)
    return np.column_stack([ring, np.full(count, depth)])


def sample_batch(
    models: list[edgepose.StandardModel], rng: np.random.Generator, shapes: int, views_per_shape: int
) -> Batch:
    observed, directions, rotations, shape_ids, angles = [], [], [], [], []
    for s in rng.choice(len(models), size=shapes, replace=False):
        model = models[s]
        for d in random_directions(rng, views_per_shape):
            r_book = edgepose.view_rotation(d)
            theta = rng.uniform(-np.pi, np.pi)
            r_obs = rotation_about_z(theta) @ edgepose.view_rotation(perturb(d, MAX_VIEW_OFFSET_DEG, rng))
            observed.append(observe(model, r_obs, rng))
            # The turn codebook → observed is the z-rotation part of R_obs R_bookᵀ.
            rel = r_obs @ r_book.T
            angles.append(np.arctan2(rel[1, 0], rel[0, 0]))
            directions.append(d)
            rotations.append(r_book)
            shape_ids.append(s)
    codebook = []
    for s in np.unique(shape_ids):
        idx = [i for i, sid in enumerate(shape_ids) if sid == s]
        views = edgepose.Viewpoints(np.array([directions[i] for i in idx]), np.array([rotations[i] for i in idx]))
        codebook.append((idx, edgepose.compute_maps(models[s], views).points))
    book = np.empty((len(observed), DEFAULT_MAP_POINTS, 3), dtype=np.float32)
    for idx, maps in codebook:
        book[idx] = maps
    return Batch(np.stack(observed), book, np.array(directions), np.array(shape_ids), np.array(angles))
