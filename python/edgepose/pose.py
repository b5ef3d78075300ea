"""``estimate(cloud, codebook)``: the 6D pose of an object from its segmented
depth cloud (../shared/DESIGN.md, step 7), as five named stages:

1. :func:`prepare_query` — keep the points that are the object (outliers,
   flying pixels and background a spilled mask picked up are dropped), turn
   the cloud so its centroid ray is the optical axis, centre, scale and
   resample it to a map;
2. :func:`retrieve` — encode the map, cosine top-K over the codebook's
   codes (Rust), the in-plane angle of each candidate (IRR head);
3. :func:`candidate_poses` — each candidate view and angle as a pose;
4. :func:`score_poses` — how well each pose explains the view: truncated
   keypoint distances to the model and free-space violations (Rust);
5. :func:`refine_hypotheses` — point-to-plane ICP (Rust) from the best few
   distinct candidates, scored again; the best one is polished.

Every tuning value lives in :class:`edgepose.settings.EstimateSettings`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from edgepose import _core
from edgepose.cloud import MIN_POINTS, clean_cloud
from edgepose.codebook import Codebook, CodebookError
from edgepose.encoder import Encoder, default_encoder
from edgepose.maps import normalize_to_map
from edgepose.settings import DEFAULT_SETTINGS, MAX_ICP_ITERATIONS, EstimateSettings
from edgepose.views import ray_alignment, rotation_about_z


@dataclass(frozen=True, eq=False)
class Pose:
    """An object's pose in the camera frame and how it was found."""

    R: np.ndarray
    """(3, 3) float64 rotation object → camera."""
    t: np.ndarray
    """(3,) float64 translation, metres: ``p_cam = R @ p_obj + t``."""
    score: float
    """Cosine similarity of the chosen view's code to the observed one (1 is best)."""
    fit: float
    """Mean distance (metres) from the observed points to the model at this
    pose, each truncated at the inlier distance (``settings.hypothesis_inlier_distance``
    × diameter when refined, else the candidates' looser one)."""
    view: int
    """Index of the chosen codebook viewpoint."""
    candidates: np.ndarray
    """(K,) viewpoint indices of the cosine top-K, best code first."""
    candidate_fit: np.ndarray
    """(K,) truncated keypoint distance of each candidate pose, metres."""
    timings: dict = field(default_factory=dict)
    """Seconds per stage, named as the stage functions: prepare_query, retrieve,
    candidate_poses, score_poses, refine_hypotheses, and the total."""
    refined: bool = False
    """Whether ICP refined the pose (``refine=True`` and ICP found enough
    points near the model)."""
    inlier_fraction: float = 0.0
    """Share of the observed points within the inlier distance of the model at this pose, 0–1."""
    free_space_violation: float = 0.0
    """Share of the model's camera-facing points on observed rays that lie in
    front of what the camera saw there (by more than the tolerance), 0–1:
    high means the pose contradicts the view."""
    kept_points: int = 0
    """Observed points that :func:`prepare_query` kept as the object (of at
    most ``settings.max_cloud_points``)."""

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) float64 ``T_cam_obj``."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R, self.t
        return T


@dataclass(frozen=True, eq=False)
class Query:
    """An observed cloud made ready for the codebook (stage 1)."""

    points: np.ndarray
    """(N, 3) float32 camera-frame points kept as the object, metres."""
    spacing: float
    """Median distance between neighbouring points, metres (sizes the free-space grid)."""
    centroid: np.ndarray
    """(3,) float64 centroid of ``points``."""
    r_corr: np.ndarray
    """(3, 3) viewpoint correction: camera frame → frame whose +z is the centroid ray."""
    map: np.ndarray
    """(M, 3) float32 the corrected, centred, scaled and resampled map."""
    keypoints: np.ndarray
    """(KP, 3) float32 the map's first farthest-point samples, back in the camera frame."""


class PoseScores(NamedTuple):
    """Stage 4's terms per pose (see ``rust/src/scoring.rs``); lower ``cost`` is better."""

    fit: np.ndarray
    inlier_fraction: np.ndarray
    free_space_violation: np.ndarray
    cost: np.ndarray
    """fit / inlier distance + free_space_weight × free_space_violation."""


def prepare_query(cloud: object, codebook: Codebook, settings: EstimateSettings = DEFAULT_SETTINGS) -> Query:
    """Stage 1: the object's points of ``cloud`` (camera frame, metres) and its map."""
    model = codebook.model
    points = clean_cloud(cloud, model.diameter, settings.max_cloud_points).astype(np.float32)
    spacing = 0.0
    if settings.segment:
        keep, spacing = _core.segment_object(
            points,
            model.diameter,
            settings.shadow_spacings,
            settings.max_shadowed_fraction,
            settings.min_component_fraction,
            settings.max_component_offset,
        )
        if keep.sum() >= MIN_POINTS:
            points = np.ascontiguousarray(points[keep])
    centroid = points.mean(axis=0, dtype=np.float64)
    r_corr = ray_alignment(centroid)
    corrected = ((points - centroid) @ r_corr.T).astype(np.float32)
    query_map, _ = normalize_to_map(corrected, model.scale, codebook.map_points)
    keypoints = (query_map[: settings.keypoints] / model.scale) @ r_corr.astype(np.float32) + centroid.astype(
        np.float32
    )
    return Query(points, float(spacing), centroid, r_corr, query_map, np.ascontiguousarray(keypoints, dtype=np.float32))


def retrieve(query: Query, codebook: Codebook, encoder: Encoder, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stage 2: the map's code and its ``k`` most similar codebook views, with
    the in-plane angle to each: ``(candidates (k,), similarities (k,), angles
    (k,) radians)``."""
    code, spectrum = encoder.encode(query.map[None])
    candidates, similarity = _core.top_k(codebook.codes, code[0], k)
    candidates = candidates.astype(np.intp)
    angles = encoder.in_plane_angles(spectrum[0], codebook.spectra[candidates]).astype(np.float64)
    return candidates, similarity, angles


def candidate_poses(
    query: Query,
    codebook: Codebook,
    candidates: np.ndarray,
    angles: np.ndarray,
    settings: EstimateSettings = DEFAULT_SETTINGS,
) -> tuple[np.ndarray, np.ndarray]:
    """Stage 3: model frame → camera poses ``(R (k, 3, 3), t (k, 3))``:
    ``R = R_corrᵀ · Rz(θ) · R_view``; the translation from the centroids,
    then moved so the keypoints land on the model."""
    rotations = query.r_corr.T @ rotation_about_z(angles) @ codebook.viewpoints.rotations[candidates]
    translations = query.centroid - np.einsum("kij,kj->ki", rotations, codebook.centroids[candidates])
    if settings.align_iterations > 0:
        translations = codebook.index.align_translations(
            query.keypoints,
            rotations,
            translations,
            settings.align_iterations,
            settings.candidate_inlier_distance * codebook.model.diameter,
        )
    return rotations, translations


def score_poses(
    query: Query,
    codebook: Codebook,
    observed: np.ndarray,
    rotations: np.ndarray,
    translations: np.ndarray,
    inlier_distance: float,
    free_space_weight: float,
    settings: EstimateSettings = DEFAULT_SETTINGS,
) -> PoseScores:
    """Stage 4: the terms of each pose against the ``observed`` points (camera
    frame) and the free space of the whole query. ``inlier_distance`` is in metres."""
    d = codebook.model.diameter
    fit, inliers, violation = codebook.index.score(
        observed,
        query.points,
        query.spacing,
        np.ascontiguousarray(rotations),
        np.ascontiguousarray(translations),
        inlier_distance,
        settings.free_space_tolerance * d,
        settings.free_space_model_stride,
    )
    cost = fit / inlier_distance + free_space_weight * violation
    return PoseScores(fit, inliers, violation, cost)


class Refined(NamedTuple):
    """Stage 5's outcome: the chosen pose (model frame → camera) and its terms."""

    candidate: int
    """Which candidate it started from."""
    R: np.ndarray
    t: np.ndarray
    scores: PoseScores
    """The chosen pose's terms (arrays of one)."""
    refined: bool


def refine_hypotheses(
    query: Query,
    codebook: Codebook,
    rotations: np.ndarray,
    translations: np.ndarray,
    candidate_cost: np.ndarray,
    settings: EstimateSettings = DEFAULT_SETTINGS,
) -> Refined | None:
    """Stage 5: coarse ICP from the ``settings.hypotheses`` best distinct
    candidates, each scored again. Hypotheses that explain nearly as many
    points as the best and violate free space little more than the least
    violating compete; the lowest ICP RMSE wins and is polished by a longer
    ICP. None when no ICP found enough points."""
    d = codebook.model.diameter
    coarse = _subsample(query.points, settings.hypothesis_points, settings.subsample_seed)
    starts = distinct_hypotheses(
        rotations, np.argsort(candidate_cost, kind="stable"), settings.hypotheses, settings.distinct_deg
    )
    max_distance = settings.icp_max_distance * d
    icp = codebook.index.refine(
        coarse, rotations[starts], translations[starts], settings.hypothesis_iterations, max_distance
    )
    hyp_R, hyp_t, inliers, rmse = icp.rotations, icp.translations, icp.inliers, icp.rmse
    usable = (
        np.isfinite(rmse) & (inliers >= settings.min_icp_inliers) & near_the_cloud(query, codebook, hyp_t, settings)
    )
    if not usable.any():
        return None
    inlier_distance = settings.hypothesis_inlier_distance * d
    scores = score_poses(query, codebook, coarse, hyp_R, hyp_t, inlier_distance, 0.0, settings)
    explains = scores.inlier_fraction >= settings.hypothesis_inlier_ratio * scores.inlier_fraction[usable].max()
    free = (
        scores.free_space_violation <= scores.free_space_violation[usable].min() + settings.hypothesis_free_space_margin
    )
    competing = usable & explains & free
    pick = int(np.argmin(np.where(competing, rmse, np.inf)))
    best = Refined(int(starts[pick]), hyp_R[pick], hyp_t[pick], PoseScores(*(s[pick : pick + 1] for s in scores)), True)
    if settings.icp_iterations > 0:
        fine_icp = codebook.index.refine(
            _subsample(query.points, settings.icp_points, settings.subsample_seed + 1),
            hyp_R[pick : pick + 1],
            hyp_t[pick : pick + 1],
            settings.icp_iterations,
            max_distance,
        )
        fine_R, fine_t = fine_icp.rotations, fine_icp.translations
        if (
            fine_icp.inliers[0] >= settings.min_icp_inliers
            and np.isfinite(fine_icp.rmse[0])
            and near_the_cloud(query, codebook, fine_t, settings)[0]
        ):
            fine = score_poses(query, codebook, coarse, fine_R, fine_t, inlier_distance, 0.0, settings)
            best = Refined(best.candidate, fine_R[0], fine_t[0], fine, True)
    return best


def near_the_cloud(
    query: Query, codebook: Codebook, translations: np.ndarray, settings: EstimateSettings = DEFAULT_SETTINGS
) -> np.ndarray:
    """(H,) bool: whether each pose (model frame → camera, ``translations``
    (H, 3) metres: where the model's centre lands) keeps the model's centre
    within ``settings.max_centre_offset`` model radii of the observed centroid."""
    radius = 1.0 / codebook.model.scale
    return np.linalg.norm(translations - query.centroid, axis=1) <= settings.max_centre_offset * radius


def estimate(
    cloud: object,
    codebook: Codebook,
    *,
    refine: bool = True,
    k: int | None = None,
    encoder: Encoder | None = None,
    icp_iterations: int | None = None,
    settings: EstimateSettings = DEFAULT_SETTINGS,
) -> Pose:
    """The pose ``T_cam_obj`` of ``codebook``'s object in ``cloud``: an (N, 3)
    array of camera-frame points in metres (float32/64, or anything with
    ``.points``), segmented to that object (a detector's mask that spills onto
    the background is fine: such points are dropped). Deterministic: the same
    input gives the same pose.

    ``settings`` holds every tuning value; ``k`` (codebook views verified) and
    ``icp_iterations`` (final ICP polish; 0: the hypotheses' coarse ICP only)
    are shortcuts for its fields; ``refine=False`` skips ICP."""
    settings = settings.with_(
        **{name: value for name, value in (("k", k), ("icp_iterations", icp_iterations)) if value is not None}
    )
    encoder = encoder or default_encoder()
    if encoder.fingerprint != codebook.fingerprint:
        raise CodebookError(
            f"the codebook was built by encoder {codebook.fingerprint[:12]}…, a different encoder than the "
            f"one given ({encoder.fingerprint[:12]}…); rebuild the codebook with it"
        )
    if not 1 <= settings.k <= len(codebook):
        raise ValueError(f"k must be between 1 and the codebook's {len(codebook)} views, got {settings.k}")
    if not 0 <= settings.icp_iterations <= MAX_ICP_ITERATIONS:
        raise ValueError(f"icp_iterations must be between 0 and {MAX_ICP_ITERATIONS}, got {settings.icp_iterations}")
    model = codebook.model
    t0 = time.perf_counter()
    query = prepare_query(cloud, codebook, settings)
    t1 = time.perf_counter()
    candidates, similarity, angles = retrieve(query, codebook, encoder, settings.k)
    t2 = time.perf_counter()
    rotations, translations = candidate_poses(query, codebook, candidates, angles, settings)
    t3 = time.perf_counter()
    candidate_scores = score_poses(
        query,
        codebook,
        query.keypoints,
        rotations,
        translations,
        settings.candidate_inlier_distance * model.diameter,
        settings.candidate_free_space_weight,
        settings,
    )
    chosen = int(np.argmin(candidate_scores.cost))
    result = Refined(
        chosen,
        rotations[chosen],
        translations[chosen],
        PoseScores(*(s[chosen : chosen + 1] for s in candidate_scores)),
        False,
    )
    t4 = time.perf_counter()
    if refine:
        result = refine_hypotheses(query, codebook, rotations, translations, candidate_scores.cost, settings) or result
    t5 = time.perf_counter()

    # Model frame = object (mesh) frame shifted by the model centre.
    t_obj = result.t - result.R @ model.centre
    return Pose(
        R=result.R,
        t=t_obj,
        score=float(similarity[result.candidate]),
        fit=float(result.scores.fit[0]),
        view=int(candidates[result.candidate]),
        candidates=candidates,
        candidate_fit=candidate_scores.fit,
        timings={
            "prepare_query": t1 - t0,
            "retrieve": t2 - t1,
            "candidate_poses": t3 - t2,
            "score_poses": t4 - t3,
            "refine_hypotheses": t5 - t4,
            "total": t5 - t0,
        },
        refined=result.refined,
        inlier_fraction=float(result.scores.inlier_fraction[0]),
        free_space_violation=float(result.scores.free_space_violation[0]),
        kept_points=len(query.points),
    )


def _subsample(points: np.ndarray, count: int, seed: int) -> np.ndarray:
    """At most ``count`` of ``points``, drawn without replacement (seeded), C-contiguous."""
    if len(points) > count:
        points = points[np.random.default_rng(seed).choice(len(points), count, replace=False)]
    return np.ascontiguousarray(points)


def distinct_hypotheses(rotations: np.ndarray, order: np.ndarray, count: int, min_angle_deg: float) -> np.ndarray:
    """Indices of up to ``count`` of ``rotations`` ((K, 3, 3)), taken in
    ``order``, each at least ``min_angle_deg`` away from those taken before."""
    cos_min = np.cos(np.radians(min_angle_deg))
    kept: list[int] = []
    for j in order:
        # cos of the angle between two rotations: (trace(Raᵀ Rb) − 1) / 2.
        if all((np.einsum("ij,ij->", rotations[j], rotations[k]) - 1) / 2 < cos_min for k in kept):
            kept.append(int(j))
            if len(kept) == count:
                break
    return np.asarray(kept, dtype=np.intp)
