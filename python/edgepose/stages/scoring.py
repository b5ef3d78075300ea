"""Stage 4 of :func:`edgepose.estimate`: how well poses explain the view —
the truncated fit, the inlier fraction, the free-space and scene violations
(``rust/src/scoring.rs``) — and the checks built on them.

Poses are model frame → camera; metres.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from edgepose import _core
from edgepose.codebook import Codebook
from edgepose.settings import DEFAULT_SETTINGS, EstimateSettings
from edgepose.stages.query import Query


class PoseScores(NamedTuple):
    """Stage 4's terms per pose (see ``rust/src/scoring.rs``); lower ``cost`` is better."""

    fit: np.ndarray
    inlier_fraction: np.ndarray
    free_space_violation: np.ndarray
    cost: np.ndarray
    """fit / inlier distance + free_space_weight × (free-space + scene violations)."""
    off_silhouette: np.ndarray
    """Share of the camera-facing model points landing where nothing was observed, 0–1."""
    translation_constraint: np.ndarray
    """How firmly the explained points pin the translation: the smallest
    eigenvalue of the mean n nᵀ of their model normals, 0 (the pose could
    slide along the seen surface) to 1/3."""
    scene_violation: np.ndarray
    """Share of the camera-facing model points off the observed silhouette
    that stand in front of the scene's depth there, 0–1 (0 without a scene)."""

    @property
    def violation(self) -> np.ndarray:
        """Free-space plus scene violations: how much the pose contradicts the view."""
        return self.free_space_violation + self.scene_violation

    @property
    def net(self) -> np.ndarray:
        """Inlier fraction minus :attr:`violation`: how hypotheses compete."""
        return self.inlier_fraction - self.violation


def free_space_tolerance(median_depth: float, diameter: float, settings: EstimateSettings = DEFAULT_SETTINGS) -> float:
    """How far (metres) a camera-facing model point must stand in front of
    the observed depth to contradict the view: ``settings.score.free_space_tolerance``
    × ``diameter``, or ``settings.score.free_space_noise_sigmas`` standard
    deviations of the sensor's depth noise (``settings.score.depth_noise``) at the
    observed points' ``median_depth`` (metres), whichever is larger."""
    a, b, c = settings.score.depth_noise
    noise = a + b * (median_depth - c) ** 2
    return max(settings.score.free_space_tolerance * diameter, settings.score.free_space_noise_sigmas * noise)


def score_poses(
    query: Query,
    codebook: Codebook,
    observed: np.ndarray,
    rotations: np.ndarray,
    translations: np.ndarray,
    inlier_distance: float,
    free_space_weight: float,
    settings: EstimateSettings = DEFAULT_SETTINGS,
    free_space: _core.DepthGrid | None = None,
    *,
    fit_only: bool = False,
    two_cores: bool = False,
) -> PoseScores:
    """Stage 4: the terms of each pose against the ``observed`` points (camera
    frame) and the free space of the whole query (``free_space``: another
    grid of it than :attr:`Query.free_space`). ``inlier_distance`` is in
    metres. ``fit_only``: the fit terms alone (fit, inlier fraction,
    translation constraint), the free-space terms left at 0. ``two_cores``:
    the poses shared with one of the Rust core's threads (the same scores;
    ``settings.retrieve.candidates_on_two_cores``)."""
    d = codebook.model.diameter
    scored = codebook.index.score(
        observed,
        query.free_space if free_space is None else free_space,
        np.ascontiguousarray(rotations),
        np.ascontiguousarray(translations),
        inlier_distance,
        free_space_tolerance(query.median_depth, d, settings),
        0 if fit_only else max(settings.score.free_space_model_stride, 1),
        two_cores=two_cores,
    )
    return pose_scores(scored, inlier_distance, free_space_weight)


def pose_scores(scored: _core.ScoreResults, inlier_distance: float, free_space_weight: float) -> PoseScores:
    """The core's scores of poses (at ``inlier_distance`` metres) as
    :class:`PoseScores`, ranked with ``free_space_weight`` (:attr:`PoseScores.cost`)."""
    return PoseScores(*scored.terms(inlier_distance, free_space_weight))


def rim_tolerant_violation(
    query: Query, codebook: Codebook, R: np.ndarray, t: np.ndarray, settings: EstimateSettings = DEFAULT_SETTINGS
) -> float:
    """The free-space violation (0–1) of one pose (model frame → camera)
    with one grid cell of slack at the silhouette's edge
    (:attr:`Query.rim_tolerant_free_space`). A real sensor's silhouette is a
    pixel or two off the object (depth and mask registered apart, mixed
    depth at the edge), so a right pose's rim stands just in front of the
    edge cells: that alone must not make it doubtful."""
    # The violation reads model points only: one observed point is enough.
    scores = score_poses(
        query,
        codebook,
        query.points[:1],
        np.asarray(R[None], dtype=np.float64),
        np.asarray(t[None], dtype=np.float64),
        settings.refine.hypothesis_inlier_distance * codebook.model.diameter,
        0.0,
        settings,
        query.rim_tolerant_free_space,
    )
    return float(scores.free_space_violation[0])


def near_the_cloud(
    centroid: np.ndarray, codebook: Codebook, translations: np.ndarray, settings: EstimateSettings = DEFAULT_SETTINGS
) -> np.ndarray:
    """(H,) bool: whether each pose (model frame → camera, ``translations``
    (H, 3) metres: where the model's centre lands) keeps the model's centre
    within ``settings.refine.max_centre_offset`` model radii of the observed
    ``centroid`` ((3,) camera frame, metres: :attr:`Query.centroid`)."""
    return np.linalg.norm(translations - centroid, axis=1) <= centre_allowance(codebook, settings)


def centre_allowance(codebook: Codebook, settings: EstimateSettings = DEFAULT_SETTINGS) -> float:
    """How far (metres) a pose may put the model's centre from the observed
    centroid: ``settings.refine.max_centre_offset`` model radii (each
    observed point lies within one radius of the centre)."""
    radius = 1.0 / codebook.model.scale
    return float(settings.refine.max_centre_offset * radius)
