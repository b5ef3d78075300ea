"""Pose error metrics: ADD, ADD-S, ADD(-S), rotation and translation errors,
the YCB-Video area under the accuracy curve, and how well a confidence
ranks and calibrates (AUROC, calibration error, acceptance). The BOP
challenge's errors are in :mod:`edgepose.eval.bop_metrics`.

Units are metres unless a name says otherwise. Poses are ``T_cam_obj``
(4, 4): ``p_cam = R @ p_obj + t``; model points are in the object frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    pass

#: The shared YCB objects that are geometrically symmetric, by hand: a
#: cross-check of :func:`edgepose.symmetry.detect_symmetry` in the tests (the
#: evaluation uses the detected symmetries). The mustard bottle's mesh is the
#: same turned 180° about its long axis to within 2 mm (only its label tells
#: front from back); banana and power_drill are asymmetric.
YCB_SYMMETRIC = frozenset({"master_chef_can", "cracker_box", "mustard_bottle"})

#: A pose is correct when its metric is below this fraction of the diameter.
CORRECT_FRACTION = 0.1

#: Rows of model points compared at once in ADD-S: bounds memory to
#: ``_CHUNK × N`` float64 distances (20 MB for N = 5,000).
_CHUNK = 512


def add(model_points: np.ndarray, T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """ADD: mean distance (metres) between each model point under ``T_est``
    and the same point under ``T_gt``."""
    points = _points(model_points)
    est, gt = _transform(T_est, points), _transform(T_gt, points)
    return float(np.linalg.norm(est - gt, axis=1).mean())


def add_s(model_points: np.ndarray, T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """ADD-S: mean over the model points under ``T_gt`` of the distance
    (metres) to the closest model point under ``T_est``.

    Brute-force nearest neighbours in chunks of rows; distances are taken in
    the ground-truth object frame, where coordinates are small, and the
    chosen neighbour's distance is recomputed exactly."""
    points = _points(model_points)
    # Estimated points in the gt object frame: same distances, less cancellation.
    relative = np.linalg.inv(_pose(T_gt)) @ _pose(T_est)
    distances = nearest_distances(points, _transform(relative, points))
    total = 0.0
    for start in range(0, len(points), _CHUNK):
        total += float(distances[start : start + _CHUNK].sum())
    return total / len(points)


def nearest_distances(query: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N,) distance (metres) from each ``query`` point to its nearest of
    ``points`` ((M, 3), same frame): brute force in chunks of rows, the
    chosen neighbour's distance recomputed exactly."""
    points_sq = np.einsum("ij,ij->i", points, points)
    out = np.empty(len(query))
    for start in range(0, len(query), _CHUNK):
        rows = query[start : start + _CHUNK]
        sq = points_sq[None, :] - 2.0 * rows @ points.T  # ‖row‖² is the same for every column
        nearest = points[np.argmin(sq, axis=1)]
        out[start : start + _CHUNK] = np.linalg.norm(rows - nearest, axis=1)
    return out


def add_or_s(model_points: np.ndarray, T_est: np.ndarray, T_gt: np.ndarray, symmetric: bool) -> float:
    """ADD(-S): ADD-S for a symmetric object, ADD otherwise (metres)."""
    metric = add_s if symmetric else add
    return metric(model_points, T_est, T_gt)


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Geodesic angle (degrees, 0–180) of the rotation taking ``R_gt`` to ``R_est``."""
    R_est, R_gt = _matrix(R_est, (3, 3), "R_est"), _matrix(R_gt, (3, 3), "R_gt")
    cos = (np.trace(R_est.T @ R_gt) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def translation_error_mm(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """Distance between two translations given in metres, in millimetres."""
    t_est, t_gt = _matrix(t_est, (3,), "t_est"), _matrix(t_gt, (3,), "t_gt")
    return float(1000.0 * np.linalg.norm(t_est - t_gt))


def auc(errors_m: np.ndarray, max_threshold: float = 0.10) -> float:
    """Area under the accuracy–threshold curve for thresholds 0 to
    ``max_threshold`` (metres), normalised to [0, 1].

    YCB-Video convention, exactly as PoseCNN's ``plot_accuracy_keyframe.m``
    (the figure papers report as "AUC of ADD-S / ADD(-S)", × 100): errors above
    ``max_threshold`` (and non-finite ones) are failures; the finite errors
    are sorted into d₁ ≤ … ≤ dₘ with accuracies k/n (n counts every error),
    and the VOC-style sum Σ (d_k − d_{k−1}) · k/n + (max − dₘ) · m/n is
    divided by ``max_threshold``. Each gap is credited with the accuracy at
    its right end, so the result exceeds the exact area under the step curve
    by dₘ / (n · max) at most (negligible for thousands of poses); within a
    run of tied errors the first one's accuracy counts, as in the original.
    """
    errors = np.asarray(errors_m, dtype=np.float64).ravel()
    if errors.size == 0:
        raise ValueError("auc needs at least one error")
    if not max_threshold > 0:
        raise ValueError(f"max_threshold must be positive, got {max_threshold}")
    if np.any(errors < 0):
        raise ValueError("errors must be non-negative distances")
    d = np.sort(np.where(errors <= max_threshold, errors, np.inf))  # NaN counts as a failure
    accuracy = np.arange(1, d.size + 1) / d.size
    finite = np.isfinite(d)
    if not finite.any():
        return 0.0
    rec, prec = d[finite], accuracy[finite]
    mrec = np.concatenate([[0.0], rec, [max_threshold]])
    mpre = np.maximum.accumulate(np.concatenate([[0.0], prec, [prec[-1]]]))
    steps = np.nonzero(mrec[1:] != mrec[:-1])[0] + 1
    return float(np.sum((mrec[steps] - mrec[steps - 1]) * mpre[steps]) / max_threshold)


@dataclass(frozen=True)
class PoseErrors:
    """Every error of one estimated pose against the ground truth."""

    add: float
    """ADD, metres."""
    add_s: float
    """ADD-S, metres."""
    add_or_s: float
    """ADD(-S): ADD-S for symmetric objects, ADD otherwise, metres."""
    rotation_deg: float
    """Geodesic rotation error, degrees."""
    translation_mm: float
    """Translation error, millimetres."""
    diameter: float
    """Object diameter, metres: the scale of the correctness threshold."""

    @property
    def correct_add_s(self) -> bool:
        """ADD-S below 0.1 × diameter."""
        return self.add_s < CORRECT_FRACTION * self.diameter

    @property
    def correct_add_or_s(self) -> bool:
        """ADD(-S) below 0.1 × diameter."""
        return self.add_or_s < CORRECT_FRACTION * self.diameter


def pose_errors(
    model_points: np.ndarray,
    T_est: np.ndarray,
    T_gt: np.ndarray,
    diameter: float,
    symmetric: bool,
) -> PoseErrors:
    """All errors of ``T_est`` against ``T_gt`` for an object of ``diameter``
    metres, sampled by ``model_points`` ((N, 3), object frame, metres)."""
    T_est, T_gt = _pose(T_est), _pose(T_gt)
    add_m = add(model_points, T_est, T_gt)
    add_s_m = add_s(model_points, T_est, T_gt)
    return PoseErrors(
        add=add_m,
        add_s=add_s_m,
        add_or_s=add_s_m if symmetric else add_m,
        rotation_deg=rotation_error_deg(T_est[:3, :3], T_gt[:3, :3]),
        translation_mm=translation_error_mm(T_est[:3, 3], T_gt[:3, 3]),
        diameter=float(diameter),
    )


def _transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    T = _pose(T)
    return points @ T[:3, :3].T + T[:3, 3]


def _points(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"model_points must have shape (N, 3) with N > 0, got {points.shape}")
    return points


def _pose(T: np.ndarray) -> np.ndarray:
    return _matrix(T, (4, 4), "pose")


def _matrix(array: np.ndarray, shape: tuple[int, ...], name: str) -> np.ndarray:
    array = np.asarray(array, dtype=np.float64)
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    return array


# ------------------------------------------------------------ confidence quality


def auroc(confidence: np.ndarray, correct: np.ndarray) -> float:
    """Area under the ROC curve of ``confidence`` for telling correct poses
    from wrong ones: the chance that a random correct pose scores above a
    random wrong one (ties count half). NaN when either class is empty."""
    p, y = _scored(confidence, correct)
    pos, neg = p[y], p[~y]
    if not len(pos) or not len(neg):
        return float("nan")
    order = np.argsort(p, kind="stable")
    ranks = np.empty(len(p))
    sorted_p = p[order]
    # Average ranks (1-based) over ties.
    starts = np.flatnonzero(np.r_[True, sorted_p[1:] != sorted_p[:-1]])
    ends = np.r_[starts[1:], len(p)]
    for s, e in zip(starts, ends):
        ranks[order[s:e]] = (s + e + 1) / 2
    return float((ranks[y].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


@dataclass(frozen=True)
class Calibration:
    """How well confidences match how often poses are right, in equal-width bins of confidence."""

    edges: np.ndarray
    """(B + 1,) bin edges, 0 to 1."""
    count: np.ndarray
    """(B,) poses per bin."""
    mean_confidence: np.ndarray
    """(B,) mean confidence per bin (NaN when empty)."""
    accuracy: np.ndarray
    """(B,) share of correct poses per bin (NaN when empty)."""
    ece: float
    """Expected calibration error: Σ (count / n) · |accuracy − mean confidence|."""


def calibration(confidence: np.ndarray, correct: np.ndarray, bins: int = 10) -> Calibration:
    """Reliability-diagram bins and the expected calibration error."""
    p, y = _scored(confidence, correct)
    edges = np.linspace(0.0, 1.0, bins + 1)
    which = np.clip(np.searchsorted(edges, p, side="right") - 1, 0, bins - 1)
    count = np.bincount(which, minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_conf = np.bincount(which, weights=p, minlength=bins) / count
        accuracy = np.bincount(which, weights=y.astype(float), minlength=bins) / count
    filled = count > 0
    ece = float(np.sum(count[filled] * np.abs(accuracy[filled] - mean_conf[filled])) / max(len(p), 1))
    return Calibration(edges, count, mean_conf, accuracy, ece)


@dataclass(frozen=True)
class Acceptance:
    """What a confidence threshold lets through."""

    threshold: float | np.ndarray
    """One threshold for every pose, or (N,) one per pose (each pose's own rule)."""
    wrong_accepted: float
    """Share (0–1) of wrong poses with confidence ≥ threshold (NaN: no wrong poses)."""
    correct_kept: float
    """Share (0–1) of correct poses with confidence ≥ threshold (NaN: no correct poses)."""


def acceptance(confidence: np.ndarray, correct: np.ndarray, threshold: float | np.ndarray = 0.5) -> Acceptance:
    """The shares of wrong and correct poses at confidence ≥ ``threshold``
    (a number, or (N,) one per pose)."""
    p, y = _scored(confidence, correct)
    accepted = p >= threshold

    def share(mask: np.ndarray) -> float:
        return float(accepted[mask].mean()) if mask.any() else float("nan")

    return Acceptance(threshold, share(~y), share(y))


def _scored(confidence: np.ndarray, correct: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(confidence, dtype=np.float64).ravel()
    y = np.asarray(correct, dtype=bool).ravel()
    if p.shape != y.shape:
        raise ValueError(f"one correctness per confidence: {p.shape} vs {y.shape}")
    if not np.isfinite(p).all():
        raise ValueError("confidences must be finite")
    return p, y


# ------------------------------------------------------------ BOP challenge errors
#
# VSD, MSSD and MSPD as the BOP toolkit computes them (thodan/bop_toolkit:
# bop_toolkit_lib/pose_error.py, misc.py, visibility.py), in metres where the
# toolkit uses millimetres. Only the error functions are mirrored: the
# toolkit's scripts/eval_calc_errors.py also short-cuts MSSD to ``inf`` when
# ‖t_est − t_gt‖ ≥ diameter and VSD to 1 when the (approximated) projections
# of the two bounding spheres do not overlap; such poses fail every BOP19
# threshold anyway, but callers wanting the scripts' numbers must apply that.
