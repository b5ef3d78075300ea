"""``estimate(cloud, codebook)``: the 6D pose of an object from its segmented
depth cloud (../shared/DESIGN.md, step 7).

1. clean the cloud; its centroid gives the ray to the object;
2. turn the cloud so that ray is the optical axis (viewpoint correction),
   centre, scale and resample it to a map;
3. encode the map; cosine top-K over the codebook's codes (Rust);
4. in-plane angle of each candidate (IRR head, one batched call);
5. verify each candidate pose by how close the map's keypoints land to the
   model (Rust kd-tree); the closest wins;
6. translation from the centroids; point-to-plane ICP against the model
   (Rust) unless ``refine=False``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from edgepose import _core
from edgepose.cloud import clean_cloud
from edgepose.codebook import Codebook
from edgepose.encoder import Encoder, default_encoder
from edgepose.errors import InvalidCloudError
from edgepose.maps import normalize_to_map
from edgepose.views import ray_alignment

#: Clouds larger than this are subsampled (seeded) first: bounded time and memory, and
#: 2,048 points already cover an object densely for a 512-point map.
MAX_CLOUD_POINTS = 2048
#: Points of the cloud used by ICP.
ICP_POINTS = 1024
#: Keypoints (the first farthest-point samples of the map) used to verify candidates.
KEYPOINTS = 32


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
    the verification distance of the keypoints, or the ICP inlier RMSE when refined."""
    view: int
    """Index of the chosen codebook viewpoint."""
    candidates: np.ndarray
    """(K,) viewpoint indices of the cosine top-K, best code first."""
    candidate_fit: np.ndarray
    """(K,) keypoint verification distance of each candidate, metres."""
    timings: dict = field(default_factory=dict)
    """Seconds per stage: prepare, encode, search, irr, verify, refine, total."""
    refined: bool = False

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) float64 ``T_cam_obj``."""
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = self.R, self.t
        return T


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
    gives the same pose."""
    encoder = encoder or default_encoder()
    if encoder.fingerprint != codebook.fingerprint:
        raise InvalidCloudError("the codebook was built by a different encoder than the one given")
    if k < 1:
        raise ValueError(f"k must be at least 1, got {k}")
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
    best = int(np.argmin(fit))
    rotation, translation, best_fit = rotations[best], translations[best], float(fit[best])
    t5 = time.perf_counter()

    if refine:
        subset = points
        if len(points) > ICP_POINTS:
            subset = points[np.random.default_rng(1).choice(len(points), ICP_POINTS, replace=False)]
        rotation, translation, _, _, inliers, rmse = codebook.index.refine(
            np.ascontiguousarray(subset, dtype=np.float32), rotation, translation, icp_iterations, 0.1 * model.diameter
        )
        if inliers >= 16 and np.isfinite(rmse):
            best_fit = float(rmse)
    t6 = time.perf_counter()

    # Model frame = object (mesh) frame shifted by the model centre.
    t_obj = translation - rotation @ model.centre
    return Pose(
        R=rotation,
        t=t_obj,
        score=float(similarity[best]),
        fit=best_fit,
        view=int(candidates[best]),
        candidates=candidates,
        candidate_fit=fit,
        timings={
            "prepare": t1 - t0, "encode": t2 - t1, "search": t3 - t2, "irr": t4 - t3,
            "verify": t5 - t4, "refine": t6 - t5, "total": t6 - t0,
        },
        refined=refine,
    )
