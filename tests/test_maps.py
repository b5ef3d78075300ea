"""Visibility, farthest-point sampling and maps against references."""

from __future__ import annotations

import edgepose
import numpy as np
import pytest
import trimesh


def fps_reference(points: np.ndarray, m: int) -> np.ndarray:
    """Farthest-point sampling in numpy, float32 like the core: start at the
    point farthest from the centroid, first index on ties, pad by cycling."""
    points = points.astype(np.float32)
    centroid = points.sum(axis=0, dtype=np.float32) * np.float32(1.0 / len(points))
    current = int(np.argmax(((points - centroid) ** 2).sum(axis=1)))
    chosen = [current]
    min_sq = np.full(len(points), np.inf, dtype=np.float32)
    for _ in range(1, min(m, len(points))):
        d = ((points - points[current]) ** 2).sum(axis=1)
        min_sq = np.minimum(min_sq, d)
        current = int(np.argmax(min_sq))
        chosen.append(current)
    take = len(chosen)
    chosen += [chosen[k % take] for k in range(take, m)]
    return np.array(chosen)


@pytest.mark.parametrize("n, m", [(2000, 512), (517, 64), (9, 9), (5, 12), (1, 3)])
def test_fps_matches_numpy_reference(rng, n, m):
    points = rng.normal(size=(n, 3)).astype(np.float32)
    assert np.array_equal(edgepose.farthest_point_sample(points, m), fps_reference(points, m))


def test_fps_accepts_any_float_layout(rng):
    points = rng.normal(size=(300, 6))[:, ::2]  # float64, non-contiguous
    assert np.array_equal(edgepose.farthest_point_sample(points, 50), fps_reference(points, 50))


def sphere_model(n: int = 4096) -> edgepose.StandardModel:
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    return edgepose.load_model(mesh, n_points=n)


def test_a_sphere_shows_about_half_its_points_from_any_view():
    model = sphere_model()
    views = edgepose.fibonacci_viewpoints(50)
    maps = edgepose.compute_maps(model, views)
    share = maps.visible / len(model.points)
    assert np.all(np.abs(share - 0.47) < 0.04), share


def test_a_cube_seen_along_z_shows_exactly_its_top_face():
    model = edgepose.load_model(trimesh.creation.box(extents=(0.1, 0.1, 0.1)))
    rotation = edgepose.view_rotation(np.array([0.0, 0.0, 1.0]))
    seen = edgepose.visible_mask(model, rotation)
    on_top = model.normals[:, 2] > 0.99
    assert on_top.sum() > 500
    assert np.array_equal(seen, on_top)


def test_all_view_maps_equal_one_view_at_a_time():
    model = sphere_model(2048)
    views = edgepose.fibonacci_viewpoints(40)
    maps = edgepose.compute_maps(model, views, points_per_map=128)
    assert maps.points.shape == (40, 128, 3) and maps.points.dtype == np.float32
    for v in range(0, 40, 7):
        r = views.rotations[v]
        seen = edgepose.visible_mask(model, r)
        assert maps.visible[v] == seen.sum()
        in_view = model.points[seen] @ r.T.astype(np.float32)
        expected, centroid = edgepose.normalize_to_map(in_view, model.scale, 128)
        np.testing.assert_allclose(maps.points[v], expected, atol=1e-6)
        np.testing.assert_allclose(maps.centroids[v], r.T @ centroid, atol=1e-6)


def test_maps_are_centred_scaled_and_deterministic(ycb_dir):
    model = edgepose.load_model(ycb_dir / "power_drill.ply")
    views = edgepose.fibonacci_viewpoints(200)
    a = edgepose.compute_maps(model, views)
    b = edgepose.compute_maps(model, views)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.centroids, b.centroids)
    radius = np.linalg.norm(a.points, axis=2).max(axis=1)
    assert np.all(radius <= 2.0) and np.all(radius > 0.3)
    # Every view sees a real share of a closed object, and maps are full (no padding).
    assert np.all(a.visible >= 512)
    # Centroids lie inside the object's bounding sphere (model frame, metres).
    assert np.all(np.linalg.norm(a.centroids, axis=1) < model.radius)


def test_normalize_to_map_centres_and_scales(rng):
    cloud = rng.normal(size=(1000, 3)) * 0.02 + [0.1, -0.2, 0.7]
    m, centroid = edgepose.normalize_to_map(cloud, scale=10.0, m=256)
    np.testing.assert_allclose(centroid, cloud.mean(axis=0), atol=1e-6)
    chosen = edgepose.farthest_point_sample(cloud, 256)
    np.testing.assert_allclose(m, (cloud[chosen] - cloud.mean(axis=0)) * 10.0, atol=1e-5)
    with pytest.raises(ValueError, match="N > 0"):
        edgepose.normalize_to_map(np.zeros((0, 3)), 1.0)
