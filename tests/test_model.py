"""Standard models from meshes and point clouds, against scipy and trimesh."""

from __future__ import annotations

import edgepose
import numpy as np
import pytest
import trimesh
from edgepose.io import read_cloud
from scipy.spatial import cKDTree
from scipy.spatial.distance import pdist


@pytest.mark.parametrize("name", ["banana", "mustard_bottle", "power_drill"])
def test_ycb_mesh_model_matches_reference_geometry(ycb_dir, name):
    path = ycb_dir / f"{name}.ply"
    model = edgepose.load_model(path)
    assert model.points.shape == (4096, 3) and model.points.dtype == np.float32
    assert model.normals.shape == (4096, 3)
    np.testing.assert_allclose(np.linalg.norm(model.normals, axis=1), 1.0, atol=1e-5)
    # Diameter and spacing against scipy, on the same points.
    assert model.diameter == pytest.approx(pdist(model.points).max(), rel=1e-5)
    nn, _ = cKDTree(model.points).query(model.points, k=2)
    assert model.spacing == pytest.approx(nn[:, 1].mean(), rel=1e-5)
    # Scale maps the farthest point onto the unit sphere.
    assert model.scale * np.linalg.norm(model.points, axis=1).max() == pytest.approx(1.0, rel=1e-5)
    # Against the mesh itself: diameter close to the hull's, points on the surface.
    tri = edgepose.model.read_mesh(path)
    hull_diameter = pdist(tri.convex_hull.vertices).max()
    assert model.diameter == pytest.approx(hull_diameter, rel=0.02)
    # Brute-force point-to-triangle distance for a subset: samples lie on the surface.
    samples = (model.points[::64] + model.centre).astype(np.float64)
    triangles = tri.triangles
    for p in samples:
        closest = trimesh.triangles.closest_point(triangles, np.broadcast_to(p, (len(triangles), 3)))
        assert (
            np.linalg.norm(closest - p, axis=1).min() < 1e-4
        )  # 0.1 mm; trimesh is loose on the scans' sliver triangles
    # Even coverage: no sample is far from its neighbours.
    assert nn[:, 1].max() < 4 * model.spacing


@pytest.mark.parametrize("ext", ["obj", "ply", "stl", "glb", "off"])
def test_every_mesh_format_loads_to_the_same_model(tmp_path, ext):
    box = trimesh.creation.box(extents=(0.04, 0.06, 0.1))
    box.apply_translation([0.3, 0.0, -0.1])
    path = tmp_path / f"box.{ext}"
    box.export(path)
    model = edgepose.load_model(path)
    assert model.diameter == pytest.approx(np.linalg.norm([0.04, 0.06, 0.1]), rel=0.02)
    np.testing.assert_allclose(model.centre, [0.3, 0.0, -0.1], atol=2e-3)
    # Outward normals: each points away from the box centre.
    assert np.all(np.einsum("ij,ij->i", model.points, model.normals) > 0)


def test_millimetre_files_are_detected_or_scaled_explicitly(tmp_path, ycb_dir):
    metres = edgepose.load_model(ycb_dir / "banana.ply")
    mesh = edgepose.model.read_mesh(ycb_dir / "banana.ply")
    mesh.apply_scale(1000.0)
    path = tmp_path / "banana_mm.stl"
    mesh.export(path)
    detected = edgepose.load_model(path)
    explicit = edgepose.load_model(path, scale=0.001)
    for model in (detected, explicit):
        assert model.diameter == pytest.approx(metres.diameter, rel=1e-3)
        np.testing.assert_allclose(model.centre, metres.centre, atol=1e-4)
    assert edgepose.detect_scale(0.2) == 1.0 and edgepose.detect_scale(200.0) == 0.001


def test_same_seed_same_model_other_seed_other_samples(ycb_dir):
    a = edgepose.load_model(ycb_dir / "banana.ply", seed=1)
    b = edgepose.load_model(ycb_dir / "banana.ply", seed=1)
    c = edgepose.load_model(ycb_dir / "banana.ply", seed=2)
    assert np.array_equal(a.points, b.points)
    assert not np.array_equal(a.points, c.points)
    assert c.diameter == pytest.approx(a.diameter, rel=0.01)


def test_point_cloud_model_orients_inward_normals_outward(rng):
    directions = rng.normal(size=(6000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    points = directions * 0.05 + [1.0, 2.0, 3.0]
    model = edgepose.model_from_points(points, -directions, n_points=2048)
    assert model.points.shape == (2048, 3)
    np.testing.assert_allclose(model.centre, [1.0, 2.0, 3.0], atol=3e-3)
    assert np.all(np.einsum("ij,ij->i", model.points, model.normals) > 0)
    assert model.diameter == pytest.approx(0.1, rel=0.01)


def test_bad_models_raise_named_errors(tmp_path):
    with pytest.raises(edgepose.MeshLoadError, match="no such file"):
        edgepose.load_model(tmp_path / "missing.ply")
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"\x00\x01garbage" * 100)
    with pytest.raises(edgepose.MeshLoadError, match="junk.ply"):
        edgepose.load_model(junk)
    flat = trimesh.Trimesh(vertices=[[0, 0, 0], [1, 0, 0], [2, 0, 0]], faces=[[0, 1, 2]], process=False)
    with pytest.raises(edgepose.InvalidModelError, match="zero surface area"):
        edgepose.load_model(flat)
    nan = trimesh.Trimesh(vertices=[[0, 0, np.nan], [1, 0, 0], [0, 1, 0]], faces=[[0, 1, 2]], process=False)
    with pytest.raises(edgepose.InvalidModelError, match="NaN"):
        edgepose.load_model(nan)
    with pytest.raises(edgepose.InvalidModelError, match=r"shape \(N, 3\)"):
        edgepose.model_from_points(np.zeros((10, 2)), np.zeros((10, 2)))
    with pytest.raises(edgepose.InvalidModelError, match="lengths differ"):
        edgepose.model_from_points(np.ones((10, 3)), np.ones((9, 3)))
    with pytest.raises(edgepose.InvalidModelError, match="scale"):
        edgepose.load_model(trimesh.creation.box(), scale=-1.0)
    # Every one of these is also a ValueError, and an EdgePoseError.
    assert issubclass(edgepose.MeshLoadError, ValueError)
    assert issubclass(edgepose.InvalidModelError, edgepose.EdgePoseError)


def test_a_mesh_naming_a_missing_texture_loads_without_a_warning(tmp_path, caplog):
    # BOP's models name a texture image that depth-only datasets leave out.
    box = trimesh.creation.box(extents=(0.1, 0.08, 0.06))
    text = box.export(file_type="ply", encoding="ascii").decode()
    text = text.replace("end_header", "comment TextureFile obj_000001.png\nend_header", 1)
    path = tmp_path / "obj_000001.ply"
    path.write_text(text)
    with caplog.at_level("DEBUG", logger="trimesh"):
        mesh = edgepose.read_mesh(path)
        points = read_cloud(path)
    assert len(mesh.faces) == 12 and points.shape == (8, 3)
    assert not [r for r in caplog.records if r.levelname in ("WARNING", "ERROR")]
