"""The BOP challenge's pose errors (VSD, MSSD, MSPD) and their thresholds,
as the BOP toolkit (thodan/bop_toolkit, ``eval_bop19_pose.py``) computes them.

Units are metres unless a name says otherwise (MSPD: pixels). Poses are
rotations ``R`` (3, 3) and translations ``t`` (3,) taking object-frame model
points to the camera frame (OpenCV).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from edgepose.eval.metrics import _matrix, _points
from edgepose.eval.render import Camera, rasterize_depth

if TYPE_CHECKING:
    from edgepose.symmetry import Symmetry

#: ``max_sym_disc_step`` of the BOP19 evaluation (``eval_bop19_pose.py``).
BOP_MAX_SYM_DISC_STEP = 0.01


def _frozen(array: np.ndarray) -> np.ndarray:
    array.setflags(write=False)
    return array


#: VSD misalignment tolerances τ, fractions of the diameter: the toolkit's
#: ``np.arange(0.05, 0.51, 0.05)`` (0.05 … 0.5, ten values, same rounding).
BOP_VSD_TAUS = _frozen(np.arange(0.05, 0.51, 0.05))
#: VSD correctness thresholds θ (unitless, the error is a fraction of pixels):
#: each of the 10 × 10 (τ, θ) pairs gives one recall; a pose is correct when
#: ``error < θ`` (strictly, ``pose_matching.match_poses``).
BOP_VSD_THRESHOLDS = _frozen(np.arange(0.05, 0.51, 0.05))
#: MSSD correctness thresholds, fractions of the diameter: correct when
#: ``mssd / diameter < θ`` (``eval_calc_scores.py`` divides by the diameter).
BOP_MSSD_THRESHOLDS = _frozen(np.arange(0.05, 0.51, 0.05))
#: MSPD correctness thresholds, pixels at an image 640 pixels wide (5 … 50
#: step 5). ``eval_calc_scores.py`` multiplies every MSPD error by
#: ``640 / w`` (w: the scene's image width, pixels) before the strict test
#: ``error · 640 / w < θ``; i.e. the thresholds scale to ``θ · w / 640``
#: pixels (:func:`bop_mspd_thresholds`).
BOP_MSPD_THRESHOLDS = _frozen(np.arange(5, 51, 5).astype(np.float64))
#: VSD visibility tolerance δ (metres) for most datasets.
BOP_VSD_DELTA = 0.015
#: VSD δ by BOP dataset name (metres): ``vsd_deltas`` of
#: ``scripts/eval_bop19_pose.py`` (15 mm, itodd 5 mm), converted from mm.
BOP_VSD_DELTAS: dict[str, float] = {
    "hb": 0.015,
    "icbin": 0.015,
    "icmi": 0.015,
    "itodd": 0.005,
    "lm": 0.015,
    "lmo": 0.015,
    "ruapc": 0.015,
    "tless": 0.015,
    "tudl": 0.015,
    "tyol": 0.015,
    "ycbv": 0.015,
    "hope": 0.015,
}

#: Model points × symmetry transforms compared at once in MSSD / MSPD.
_SYM_CHUNK_POINTS = 1_000_000


def bop_mspd_thresholds(image_width: int) -> np.ndarray:
    """MSPD thresholds (pixels) for images ``image_width`` pixels wide:
    ``BOP_MSPD_THRESHOLDS · image_width / 640`` (a pose is correct when its
    MSPD is strictly below)."""
    return BOP_MSPD_THRESHOLDS * (float(image_width) / 640.0)


def bop_symmetry_transforms(symmetry: Symmetry, max_sym_disc_step: float = BOP_MAX_SYM_DISC_STEP) -> np.ndarray:
    """(G, 4, 4) the toolkit's symmetry set (``misc.get_symmetry_transformations``),
    object frame, metres; identity first.

    Discrete turns are the identity followed by ``symmetry.discrete``. Each
    continuous symmetry (axis, point on it = BOP's ``offset``) is sampled at
    ``n = ceil(π / max_sym_disc_step)`` angles ``i · 2π / n`` for
    ``i = 0 … n − 1`` (315 for 0.01): the loop includes the identity (i = 0)
    and ends one step short of 2π; the turn is ``R`` with
    ``t = point − R · point``. The samples of all continuous symmetries are
    concatenated (not composed: each repeats the identity). With any
    continuous symmetry the set is every ``C @ D`` — discrete ``D`` outer,
    continuous ``C`` inner (index ``d · len(C) + c``) — so it has
    ``(1 + M) · A · n`` members; without, it is the ``1 + M`` discrete turns.
    """
    if not max_sym_disc_step > 0:
        raise ValueError(f"max_sym_disc_step must be positive, got {max_sym_disc_step}")
    discrete = np.concatenate([np.eye(4)[None], np.asarray(symmetry.discrete, dtype=np.float64).reshape(-1, 4, 4)])
    continuous = np.asarray(symmetry.continuous, dtype=np.float64).reshape(-1, 6)
    if not len(continuous):
        return discrete
    steps = int(np.ceil(np.pi / max_sym_disc_step))
    angles = np.arange(steps) * (2.0 * np.pi / steps)
    turns = np.concatenate([_turns_about(row[:3], row[3:], angles) for row in continuous])
    return np.einsum("cij,djk->dcik", turns, discrete).reshape(-1, 4, 4)


def _turns_about(axis: np.ndarray, point: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(len(angles), 4, 4) turns by ``angles`` (radians) about the line through
    ``point`` along ``axis`` (Rodrigues, as the toolkit's ``rotation_matrix``)."""
    d = axis / np.linalg.norm(axis)
    cross = np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
    cos, sin = np.cos(angles)[:, None, None], np.sin(angles)[:, None, None]
    R = cos * np.eye(3) + (1.0 - cos) * np.outer(d, d) + sin * cross
    T = np.tile(np.eye(4), (len(angles), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = point - R @ point
    return T


def mssd(
    R_est: np.ndarray,
    t_est: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    points: np.ndarray,
    transforms: np.ndarray,
) -> float:
    """Maximum Symmetry-aware Surface Distance (metres): over the symmetry
    ``transforms`` S ((G, 4, 4), object frame, from
    :func:`bop_symmetry_transforms`), the least of the largest distance
    between a model point under the estimate and under ``T_gt · S``.
    ``points`` (N, 3) model vertices, object frame, metres; poses map the
    object frame to the camera frame (translations in metres, any shape of 3)."""
    R_est, t_est, R_gt, t_gt = _rt(R_est, t_est, "est") + _rt(R_gt, t_gt, "gt")
    points, transforms = _points(points), _transforms(transforms)
    est = _apply(R_est[None], t_est[None], points)[0]
    best = np.inf
    for S in _chunks(transforms, len(points)):
        gt = _apply(R_gt @ S[:, :3, :3], S[:, :3, 3] @ R_gt.T + t_gt, points)
        best = min(best, float(np.linalg.norm(est - gt, axis=2).max(axis=1).min()))
    return best


def mspd(
    R_est: np.ndarray,
    t_est: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    points: np.ndarray,
    transforms: np.ndarray,
    K: np.ndarray,
) -> float:
    """Maximum Symmetry-aware Projection Distance (pixels): as :func:`mssd`
    but between the points' projections by the intrinsics ``K`` (3, 3)
    (``K · p_cam`` divided by its third coordinate, as the toolkit's
    ``project_pts``; no check that points lie in front of the camera)."""
    R_est, t_est, R_gt, t_gt = _rt(R_est, t_est, "est") + _rt(R_gt, t_gt, "gt")
    points, transforms = _points(points), _transforms(transforms)
    K = _matrix(K, (3, 3), "K")
    est = _project(_apply(R_est[None], t_est[None], points)[0], K)
    best = np.inf
    for S in _chunks(transforms, len(points)):
        gt = _project(_apply(R_gt @ S[:, :3, :3], S[:, :3, 3] @ R_gt.T + t_gt, points), K)
        best = min(best, float(np.linalg.norm(est - gt, axis=-1).max(axis=1).min()))
    return best


def vsd(
    R_est: np.ndarray,
    t_est: np.ndarray,
    R_gt: np.ndarray,
    t_gt: np.ndarray,
    depth_test: np.ndarray,
    K: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    delta: float,
    taus: np.ndarray,
    diameter: float,
) -> np.ndarray:
    """Visible Surface Discrepancy, BOP19 form: (len(taus),) errors in [0, 1].

    The mesh (``vertices`` (V, 3) object frame, metres; ``faces`` (F, 3)) is
    rendered at both poses with :func:`edgepose.eval.render.rasterize_depth`
    (intrinsics ``fx, fy, cx, cy`` of ``K``, the size of ``depth_test``;
    pixel centres at integer coordinates, as OpenCV and BOP's K have them:
    the toolkit's OpenGL renderer samples half a pixel off, so silhouette
    edges, and VSD near its thresholds, can differ slightly);
    every depth image (metres, 0 = nothing) becomes a distance image,
    ``√((x̂·z)² + (ŷ·z)² + z²)`` with ``x̂ = (u − cx)/fx``, ``ŷ = (v − cy)/fy``
    (``depth_im_to_dist_im_fast``). Visibility, mode "bop19": a rendered
    pixel is visible when ``float32(d_model) − float32(d_test) ≤ delta``
    (metres) or the test has no measurement there (``d_test == 0``); the
    estimate is also visible wherever the ground truth is visible and the
    estimate is rendered. Over the union U and intersection I of the two
    visible masks, the "step" cost gives, for each τ (a fraction of
    ``diameter``), ``(#{p ∈ I : |d_gt − d_est| / diameter ≥ τ} + |U| − |I|) / |U|``,
    and 1 for every τ when U is empty.

    Only pixels rendered at either pose can be visible, so the work is
    restricted to their bounding box (identical to the full image)."""
    R_est, t_est, R_gt, t_gt = _rt(R_est, t_est, "est") + _rt(R_gt, t_gt, "gt")
    K = _matrix(K, (3, 3), "K")
    depth_test = np.asarray(depth_test)
    if depth_test.ndim != 2:
        raise ValueError(f"depth_test must have shape (H, W), got {depth_test.shape}")
    taus = np.asarray(taus, dtype=np.float64).ravel()
    vertices, faces = _points(vertices), np.asarray(faces, dtype=np.int64)
    height, width = depth_test.shape
    camera = Camera(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), width, height)
    depth_est = _render_depth(vertices @ R_est.T + t_est, faces, camera)
    depth_gt = _render_depth(vertices @ R_gt.T + t_gt, faces, camera)

    rows, cols = np.nonzero((depth_est > 0) | (depth_gt > 0))
    if not len(rows):
        return np.ones(len(taus))
    box = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
    x_hat = (np.arange(width)[box[1]] - K[0, 2]) / np.float64(K[0, 0])
    y_hat = (np.arange(height)[box[0]] - K[1, 2]) / np.float64(K[1, 1])
    dist_test, dist_est, dist_gt = (_distance(d[box], x_hat, y_hat) for d in (depth_test, depth_est, depth_gt))

    visible_gt = _visible_bop19(dist_test, dist_gt, delta)
    visible_est = _visible_bop19(dist_test, dist_est, delta) | (visible_gt & (dist_est > 0))
    inter = visible_gt & visible_est
    union_count = int(np.count_nonzero(visible_gt | visible_est))
    if union_count == 0:
        return np.ones(len(taus))
    complement = union_count - int(np.count_nonzero(inter))
    dists = np.abs(dist_gt[inter] - dist_est[inter]) / diameter
    costs = np.count_nonzero(dists[None, :] >= taus[:, None], axis=1)
    return (costs + complement) / float(union_count)


def _render_depth(vertices_cam: np.ndarray, faces: np.ndarray, camera: Camera) -> np.ndarray:
    """Rendered depth (metres), 0 where no surface (like the toolkit's renderers)."""
    depth = rasterize_depth(vertices_cam, faces, camera)
    depth[~np.isfinite(depth)] = 0.0
    return depth


def _distance(depth: np.ndarray, x_hat: np.ndarray, y_hat: np.ndarray) -> np.ndarray:
    """Camera-centre distance of each pixel's point (metres, 0 where depth is 0),
    in the toolkit's order of operations."""
    return np.sqrt((x_hat[None, :] * depth) ** 2 + (y_hat[:, None] * depth) ** 2 + depth.astype(np.float64) ** 2)


def _visible_bop19(dist_test: np.ndarray, dist_model: np.ndarray, delta: float) -> np.ndarray:
    """``visibility._estimate_visib_mask`` in mode "bop19": rendered pixels not
    behind the test surface by more than ``delta`` metres, or with no test
    measurement (float32 differences, as the toolkit)."""
    diff = dist_model.astype(np.float32) - dist_test.astype(np.float32)
    return ((diff <= float(delta)) | (dist_test == 0)) & (dist_model > 0)


def _apply(R: np.ndarray, t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(G, N, 3) ``points`` (N, 3) moved by each of G poses (R (G, 3, 3), t (G, 3)),
    by one code path for estimate and ground truth alike (equal poses give
    equal points, so identical poses score exactly 0, as in the toolkit)."""
    return np.einsum("gij,nj->gni", R, points) + t[:, None, :]


def _project(points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(..., 2) pixel coordinates of camera-frame points (..., 3)."""
    homogeneous = points_cam @ K.T
    return homogeneous[..., :2] / homogeneous[..., 2:]


def _rt(R: np.ndarray, t: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    R = _matrix(R, (3, 3), f"R_{name}")
    t = np.asarray(t, dtype=np.float64)
    if t.size != 3:
        raise ValueError(f"t_{name} must have 3 elements, got shape {t.shape}")
    return R, t.reshape(3)


def _transforms(transforms: np.ndarray) -> np.ndarray:
    transforms = np.asarray(transforms, dtype=np.float64)
    if transforms.ndim != 3 or transforms.shape[1:] != (4, 4) or len(transforms) == 0:
        raise ValueError(f"transforms must have shape (G, 4, 4) with G > 0, got {transforms.shape}")
    return transforms


def _chunks(transforms: np.ndarray, n_points: int) -> list[np.ndarray]:
    step = max(1, _SYM_CHUNK_POINTS // n_points)
    return [transforms[i : i + step] for i in range(0, len(transforms), step)]
