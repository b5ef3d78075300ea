"""Viewpoints: directions on a Fibonacci sphere, each with a virtual camera
(OpenCV: x right, y down, z forward) looking at the object's centre."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from edgepose import _core

DEFAULT_VIEWS = 2100


@dataclass(frozen=True)
class Viewpoints:
    """Camera directions and their rotations, object frame."""

    directions: np.ndarray
    """(V, 3) float64 unit vectors from the object's centre towards each camera."""
    rotations: np.ndarray
    """(V, 3, 3) float64 rotations object → view frame: ``p_view = R_v @ p_obj``."""

    def __len__(self) -> int:
        return len(self.directions)


def fibonacci_viewpoints(n: int = DEFAULT_VIEWS) -> Viewpoints:
    """``n`` near-uniform viewpoints; the same ``n`` always gives the same views."""
    if n < 1:
        raise ValueError(f"need at least one viewpoint, got {n}")
    directions, rotations = _core.fibonacci_viewpoints(n)
    return Viewpoints(directions, rotations)


def view_rotation(direction: np.ndarray) -> np.ndarray:
    """(3, 3) rotation object → view frame of a camera on ``direction`` (object
    frame, any length) looking at the centre. Image "down" follows the
    object's −z (−y when looking along z)."""
    return _core.view_rotation(np.ascontiguousarray(direction, dtype=np.float64))


def ray_alignment(centroid: np.ndarray) -> np.ndarray:
    """Viewpoint correction: the smallest rotation (camera frame → corrected
    frame) that turns the ray through ``centroid`` (camera frame, metres) onto
    the optical axis +z. An observed cloud rotated by it looks as if the
    camera faced the object head-on, like the codebook's virtual cameras."""
    return _core.ray_alignment(np.ascontiguousarray(centroid, dtype=np.float64))


def rotation_about_z(angles: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations by ``angles`` (radians, any shape) about the optical axis +z."""
    angles = np.asarray(angles, dtype=np.float64)
    c, s = np.cos(angles), np.sin(angles)
    R = np.zeros((*angles.shape, 3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -s, s, c, 1.0
    return R


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` (radians) about the unit ``axis`` (Rodrigues)."""
    K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K


def rotation_angle(R: np.ndarray) -> float:
    """Turn angle of a rotation, radians in [0, π]."""
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def rotation_axis(R: np.ndarray) -> np.ndarray:
    """Unit axis of a rotation (the eigenvector of eigenvalue 1)."""
    w, v = np.linalg.eig(R)
    axis = np.real(v[:, np.argmin(np.abs(w - 1))])
    return axis / np.linalg.norm(axis)
