"""``estimate(cloud, codebook)``: the 6D pose of an object from its segmented
depth cloud (../shared/DESIGN.md, step 7).

1. clean the cloud; its centroid gives the ray to the object;
2. turn the cloud so that ray is the optical axis (viewpoint correction),
   centre, scale and resample it to a map;
3. encode the map; cosine top-K over the codebook's codes (Rust);
4. in-plane angle of each candidate (IRR head, one batched call);
5. verify each candidate pose by how close the map's keypoints land to the
   model (Rust kd-tree); the closest wins;
6. translation from the centroids; unless ``refine=False``, point-to-plane
   ICP against the model (Rust) from the best few distinct candidates,
   keeping the best fit (this tells a near-symmetric object's
   turned-over pose from the true one).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from edgepose import _core
from edgepose.cloud import clean_cloud
from edgepose.codebook import Codebook, CodebookError
from edgepose.encoder import Encoder, default_encoder
from edgepose.maps import normalize_to_map
from edgepose.views import ray_alignment

#: Clouds larger than this are subsampled (seeded) first: bounded time and memory, and
#: 2,048 points already cover an object densely for a 512-point map.
MAX_CLOUD_POINTS = 2048
#: Points of the cloud used by ICP.
ICP_POINTS = 1024
#: ICP converges in tens of iterations; more is a caller's mistake, not a wish.
MAX_ICP_ITERATIONS = 1000
#: Keypoints (the first farthest-point samples of the map) used to verify candidates.
KEYPOINTS = 32
#: Distinct candidate poses refined by ICP; the lowest fit wins. A
#: near-symmetric object (a bottle turned about its axis) verifies almost equally
#: well either way up; the ICP fit of each hypothesis tells them apart.
HYPOTHESES = 3
#: Points and ICP iterations used to compare the hypotheses; the winner is then
#: refined with ``ICP_POINTS`` points and the caller's iterations.
HYPOTHESIS_POINTS = 256
HYPOTHESIS_ITERATIONS = 10
#: Candidate rotations closer than this (degrees) to a kept one are the same hypothesis.
DISTINCT_DEG = 20.0


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
    """Mean distance (metres) from the observed points to the model at this pose:
    the verification distance of the keypoints, or, when refined, the point-to-plane
    RMSE of the ICP inliers of the best-fitting hypothesis."""
    view: int
    """Index of the chosen codebook viewpoint."""
    candidates: np.ndarray
    """(K,) viewpoint indices of the cosine top-K, best code first."""
    candidate_fit: np.ndarray
    """(K,) keypoint verification distance of each candidate, metres."""
    timings: dict = field(default_factory=dict)
    """Seconds per stage: prepare, encode, search, irr, verify, refine, total."""
    refined: bool = False
    """Whether ICP refined the pose (``refine=True`` and ICP found enough
    points near the model); ``fit`` is then an ICP RMSE."""

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) float64 ``T_cam_obj``."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R, self.t
        return T


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


def estimate(
    cloud: object,
    codebook: Codebook,
    *,
    refine: bool = True,
    k: int = 16,
    encoder: Encoder | None = None,
    icp_iterations: int = 20,
) -> Pose:
    """The pose ``T_cam_obj`` of ``codebook``'s object in ``cloud``: an (N, 3)
    array of camera-frame points in metres (float32/64, or anything with
    ``.points``), segmented to that object. Deterministic: the same input
    gives the same pose.

    ``k`` codebook views are verified; ``refine=False`` skips ICP;
    ``icp_iterations`` bounds the final ICP polish of the best hypothesis
    (0: the hypotheses' coarse ICP only)."""
    encoder = encoder or default_encoder()
    if encoder.fingerprint != codebook.fingerprint:
        raise CodebookError(
            f"the codebook was built by encoder {codebook.fingerprint[:12]}…, a different encoder than the "
            f"one given ({encoder.fingerprint[:12]}…); rebuild the codebook with it"
        )
    if not 1 <= k <= len(codebook):
        raise ValueError(f"k must be between 1 and the codebook's {len(codebook)} views, got {k}")
    if not 0 <= icp_iterations <= MAX_ICP_ITERATIONS:
        raise ValueError(f"icp_iterations must be between 0 and {MAX_ICP_ITERATIONS}, got {icp_iterations}")
    model = codebook.model
    t0 = time.perf_counter()

    points = clean_cloud(cloud, model.diameter, MAX_CLOUD_POINTS)
    centroid = points.mean(axis=0)
    r_corr = ray_alignment(centroid)
    corrected = ((points - centroid) @ r_corr.T).astype(np.float32)
    query_map, _ = normalize_to_map(corrected, model.scale, codebook.map_points)
    t1 = time.perf_counter()

    code, spectrum = encoder.encode(query_map[None])
    t2 = time.perf_counter()
    candidates, similarity = _core.top_k(codebook.codes, code[0], k)
    candidates = candidates.astype(np.intp)
    t3 = time.perf_counter()
    angles = encoder.in_plane_angles(spectrum[0], codebook.spectra[candidates]).astype(np.float64)
    t4 = time.perf_counter()

    # Candidate poses, model frame → camera: R = R_corrᵀ · Rz(θ) · R_view.
    c, s = np.cos(angles), np.sin(angles)
    rz = np.zeros((len(angles), 3, 3))
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = c, -s, s, c, 1.0
    rotations = r_corr.T @ rz @ codebook.viewpoints.rotations[candidates]
    translations = centroid - np.einsum("kij,kj->ki", rotations, codebook.centroids[candidates])
    keypoints = (query_map[:KEYPOINTS] / model.scale) @ r_corr.astype(np.float32) + centroid.astype(np.float32)
    fit = codebook.index.verify(np.ascontiguousarray(keypoints, dtype=np.float32), rotations, translations)
    chosen = int(np.argmin(fit))
    rotation, translation, best_fit = rotations[chosen], translations[chosen], float(fit[chosen])
    refined = False
    t5 = time.perf_counter()

    if refine:
        cloud_f32 = points.astype(np.float32)
        coarse = _subsample(cloud_f32, HYPOTHESIS_POINTS, seed=1)
        starts = distinct_hypotheses(rotations, np.argsort(fit, kind="stable"), HYPOTHESES, DISTINCT_DEG)
        max_distance = 0.1 * model.diameter
        hyp_R, hyp_t, _, _, inliers, rmse = codebook.index.refine(
            coarse, rotations[starts], translations[starts], HYPOTHESIS_ITERATIONS, max_distance
        )
        # Compare fits only between hypotheses that explain (nearly) as many points.
        usable = np.isfinite(rmse) & (inliers >= max(16, 0.9 * inliers.max()))
        if usable.any():
            pick = int(np.argmin(np.where(usable, rmse, np.inf)))
            chosen, refined = int(starts[pick]), True
            rotation, translation, best_fit = hyp_R[pick], hyp_t[pick], float(rmse[pick])
            if icp_iterations > 0:
                fine_R, fine_t, _, _, fine_inliers, fine_rmse = codebook.index.refine(
                    _subsample(cloud_f32, ICP_POINTS, seed=2), hyp_R[pick : pick + 1], hyp_t[pick : pick + 1],
                    icp_iterations, max_distance,
                )
                if fine_inliers[0] >= 16 and np.isfinite(fine_rmse[0]):
                    rotation, translation, best_fit = fine_R[0], fine_t[0], float(fine_rmse[0])
    t6 = time.perf_counter()

    # Model frame = object (mesh) frame shifted by the model centre.
    t_obj = translation - rotation @ model.centre
    return Pose(
        R=rotation,
        t=t_obj,
        score=float(similarity[chosen]),
        fit=best_fit,
        view=int(candidates[chosen]),
        candidates=candidates,
        candidate_fit=fit,
        timings={
            "prepare": t1 - t0, "encode": t2 - t1, "search": t3 - t2, "irr": t4 - t3,
            "verify": t5 - t4, "refine": t6 - t5, "total": t6 - t0,
        },
        refined=refined,
    )
