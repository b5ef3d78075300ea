"""Stages 2 and 3 of :func:`edgepose.estimate`: the codebook views most
similar to the query's map (cosine top-K in Rust, in-plane angles from the
IRR head), those views as candidate poses, and the poses point pairs vote
for (the second search).

Poses are model frame → camera; metres.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from edgepose import _core
from edgepose.codebook import Codebook
from edgepose.encoder import Encoder
from edgepose.settings import DEFAULT_SETTINGS, EstimateSettings
from edgepose.stages.query import Query
from edgepose.views import rotation_about_z


class Retrieval(NamedTuple):
    """Stage 2's outcome: the codebook views most similar to the query."""

    views: np.ndarray
    """(k,) viewpoint indices, most similar first."""
    similarity: np.ndarray
    """(k,) cosine similarity of each view's code to the query's."""
    angles: np.ndarray
    """(k,) in-plane angle to each view, radians."""
    code: np.ndarray
    """(D,) the query map's unit code."""


def retrieve(
    query: Query,
    codebook: Codebook,
    encoder: Encoder,
    k: int,
) -> Retrieval:
    """Stage 2: the map's code and its ``k`` most similar codebook views, with
    the in-plane angle to each."""
    codes, spectra = encoder.encode(query.map[None])
    code, spectrum = codes[0], spectra[0]
    candidates, similarity = _core.top_k(codebook.codes, code, k)
    candidates = candidates.astype(np.intp)
    angles = encoder.in_plane_angles(spectrum, codebook.spectra[candidates]).astype(np.float64)
    return Retrieval(candidates, similarity, angles, code)


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
    if settings.retrieve.align_iterations > 0:
        translations = codebook.index.align_translations(
            query.keypoints,
            rotations,
            translations,
            settings.retrieve.align_iterations,
            settings.retrieve.candidate_inlier_distance * codebook.model.diameter,
            two_cores=settings.retrieve.candidates_on_two_cores,
        )
    return rotations, translations


def pair_poses(
    query: Query, codebook: Codebook, settings: EstimateSettings = DEFAULT_SETTINGS
) -> tuple[np.ndarray, np.ndarray]:
    """Stage 3 without the codebook's views: poses voted for by pairs of
    oriented points of the query and the model (point-pair features, Rust),
    ``(R (P, 3, 3), t (P, 3))`` model frame → camera, most votes first, at
    most ``settings.second_search.pair_poses``. Each pair is local, so they find the
    object when most of it is hidden and the map's code matches no view."""
    rotations, translations, _ = codebook.index.pair_poses(
        query.points,
        settings.second_search.pair_scene_points,
        settings.second_search.pair_reference_stride,
        settings.second_search.pair_poses,
    )
    return rotations, translations


def nearest_views(codebook: Codebook, rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """(P,) the codebook viewpoint nearest to the camera's direction in each
    pose (model frame → camera)."""
    towards_camera = -np.einsum("pji,pj->pi", rotations, translations)
    towards_camera /= np.linalg.norm(towards_camera, axis=1, keepdims=True)
    return np.argmax(towards_camera @ codebook.viewpoints.directions.T, axis=1).astype(np.intp)
