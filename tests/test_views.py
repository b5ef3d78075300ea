"""Viewpoints against a numpy re-implementation of the documented formulas."""

from __future__ import annotations

import edgepose
import numpy as np


def fibonacci_reference(n: int) -> np.ndarray:
    i = np.arange(n, dtype=np.float64)
    z = 1.0 - (2.0 * i + 1.0) / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def rotation_reference(d: np.ndarray) -> np.ndarray:
    z = -d / np.linalg.norm(d)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    y = -(up - z * up.dot(z))
    y /= np.linalg.norm(y)
    return np.stack([np.cross(y, z), y, z])


def test_python_viewpoints_equal_the_reference_formulas():
    views = edgepose.fibonacci_viewpoints(2100)
    assert views.directions.shape == (2100, 3) and views.rotations.shape == (2100, 3, 3)
    np.testing.assert_allclose(views.directions, fibonacci_reference(2100), atol=1e-12)
    for k in range(0, 2100, 37):
        np.testing.assert_allclose(views.rotations[k], rotation_reference(views.directions[k]), atol=1e-12)
        np.testing.assert_allclose(edgepose.view_rotation(views.directions[k] * 3.0), views.rotations[k], atol=1e-12)


def test_directions_are_near_uniform():
    d = edgepose.fibonacci_viewpoints(2100).directions
    cos = d @ d.T
    np.fill_diagonal(cos, -1.0)
    nearest = np.degrees(np.arccos(np.clip(cos.max(axis=1), -1, 1)))
    ideal = np.degrees(np.sqrt(4 * np.pi / 2100))  # ≈ 4.4°
    assert 0.8 * ideal < nearest.mean() < 1.05 * ideal
    assert nearest.min() > 0.6 * nearest.mean() and nearest.max() < 1.5 * nearest.mean()
    # Every hemisphere holds about half the views.
    for axis in np.eye(3):
        assert abs((d @ axis > 0).mean() - 0.5) < 0.01


def test_rotations_are_proper_and_cameras_look_at_the_centre():
    views = edgepose.fibonacci_viewpoints(500)
    r = views.rotations
    np.testing.assert_allclose(r @ r.transpose(0, 2, 1), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    ahead = np.einsum("vij,vj->vi", r, -views.directions)
    np.testing.assert_allclose(ahead, np.tile([0.0, 0.0, 1.0], (500, 1)), atol=1e-12)


def test_same_count_same_views():
    a, b = edgepose.fibonacci_viewpoints(300), edgepose.fibonacci_viewpoints(300)
    assert np.array_equal(a.rotations, b.rotations)
