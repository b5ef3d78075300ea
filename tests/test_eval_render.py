"""Synthetic depth views against analytic ray casting, scipy and sensor statistics."""

from __future__ import annotations

import time

import edgepose
import numpy as np
import pytest
import trimesh
from edgepose.eval import LINEMOD_CAMERA, Camera, RenderedView, depth_to_cloud, random_pose, render_view
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

CAM = LINEMOD_CAMERA
NOISE_FREE = dict(depth_noise=0.0, quantization=0.0, dropout=0.0)
BOX_EXTENTS = np.array([0.10, 0.08, 0.06])


def pose(R: np.ndarray = np.eye(3), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def pixel_rays(camera: Camera) -> np.ndarray:
    """(H, W, 3) camera-frame ray directions through pixel centres, scaled to z = 1."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    return np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(u.shape)], axis=-1)


def box_depth(T_cam_obj: np.ndarray, extents: np.ndarray, camera: Camera) -> np.ndarray:
    """Depth of a centred box along every pixel ray by the slab method; inf on a miss."""
    R, t = T_cam_obj[:3, :3], T_cam_obj[:3, 3]
    origin = -R.T @ t  # the camera centre in the object frame
    directions = pixel_rays(camera) @ R  # rows: R.T @ d
    with np.errstate(divide="ignore"):
        near = (-extents / 2 - origin) / directions
        far = (extents / 2 - origin) / directions
    enter = np.minimum(near, far).max(axis=-1)
    leave = np.maximum(near, far).min(axis=-1)
    return np.where((enter <= leave) & (enter > 0), enter, np.inf)  # z = ray parameter, as d_z = 1


@pytest.fixture(scope="module")
def mustard(ycb_dir) -> trimesh.Trimesh:
    return edgepose.model.read_mesh(ycb_dir / "mustard_bottle.ply")


def test_camera_matrix():
    np.testing.assert_array_equal(CAM.K, [[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1]])
    assert (CAM.width, CAM.height) == (640, 480)


def test_noise_free_box_depth_matches_ray_casting():
    box = trimesh.creation.box(extents=BOX_EXTENTS)
    T = pose(Rotation.from_euler("xyz", [25, -40, 70], degrees=True).as_matrix(), [0.03, -0.02, 0.5])
    view = render_view(box, T_cam_obj=T, **NOISE_FREE)
    expected = box_depth(T, BOX_EXTENTS, CAM)
    hit = np.isfinite(expected)
    assert 5000 < hit.sum() < 40000
    # Coverage agrees except for pixel centres lying on the silhouette itself.
    assert np.sum(view.mask != hit) <= 3
    both = view.mask & hit
    np.testing.assert_allclose(view.depth[both], expected[both], rtol=1e-6)  # float32 depth image
    assert np.all(view.depth[~view.mask] == 0)
    # Every cloud point lies on the box surface (the nearest face, at that).
    local = (view.cloud - T[:3, 3]) @ T[:3, :3]
    assert np.all(np.abs(local) <= BOX_EXTENTS / 2 + 1e-6)
    assert np.all(np.abs(np.abs(local) - BOX_EXTENTS / 2).min(axis=1) < 1e-6)


def test_cloud_projects_back_onto_its_mask_pixels():
    box = trimesh.creation.box(extents=BOX_EXTENTS)
    view = render_view(box, seed=3)
    projected = view.cloud @ CAM.K.T
    uv = projected[:, :2] / projected[:, 2:]
    rows, cols = np.nonzero(view.mask)
    np.testing.assert_allclose(uv, np.column_stack([cols, rows]), atol=1e-6)
    # The object sits where its pose says: the cloud's centroid is within a box radius of the centre.
    centre = view.T_cam_obj[:3, 3]
    assert np.linalg.norm(view.cloud.mean(axis=0) - centre) < np.linalg.norm(BOX_EXTENTS) / 2


def test_ycb_view_lies_on_the_posed_mesh(mustard):
    view = render_view(mustard, seed=5, **NOISE_FREE)
    assert isinstance(view, RenderedView)
    T = view.T_cam_obj
    local = (view.cloud - T[:3, 3]) @ T[:3, :3]
    surface, _ = trimesh.sample.sample_surface(mustard, 400_000, seed=0)
    distance, _ = cKDTree(surface).query(local)
    # Dense samples are ~0.4 mm apart: visible points lie on the surface.
    assert np.percentile(distance, 99) < 1.5e-3
    # And they are the near side: the object's far half (seen from the camera) is hidden.
    depth_in_cam = (surface @ T[:3, :3].T + T[:3, 3])[:, 2]
    assert view.cloud[:, 2].mean() < depth_in_cam.mean()


def test_ycb_view_is_fast_and_dense(mustard):
    times = []
    for seed in range(3):
        start = time.perf_counter()
        view = render_view(mustard, seed=seed)
        times.append(time.perf_counter() - start)
    assert np.median(times) < 1.0
    assert 1000 < len(view.cloud) < 50_000
    assert view.depth.dtype == np.float32 and view.depth.shape == (480, 640)
    assert view.cloud.dtype == np.float64


def test_same_seed_same_view_other_seed_other_pose(mustard):
    a, b = render_view(mustard, seed=7), render_view(mustard, seed=7)
    c = render_view(mustard, seed=8)
    np.testing.assert_array_equal(a.cloud, b.cloud)
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.T_cam_obj, b.T_cam_obj)
    assert not np.allclose(a.T_cam_obj, c.T_cam_obj)


def test_random_pose_is_a_uniform_rotation_with_the_centre_in_view(rng):
    centre = np.array([0.01, -0.02, 0.03])
    rotations = []
    for _ in range(2000):
        T = random_pose(rng, CAM, (0.5, 0.8), centre=centre)
        R = T[:3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        p = T[:3, :3] @ centre + T[:3, 3]
        u, v, _ = CAM.K @ p / p[2]
        assert 0.5 <= p[2] <= 0.8
        assert 0.25 * 640 <= u <= 0.75 * 640 and 0.25 * 480 <= v <= 0.75 * 480
        rotations.append(R)
    # A uniform (Haar) rotation has zero mean matrix.
    assert np.abs(np.mean(rotations, axis=0)).max() < 0.05


def test_dropout_removes_the_requested_fraction(mustard):
    T = render_view(mustard, seed=2).T_cam_obj
    full = render_view(mustard, T_cam_obj=T, **NOISE_FREE)
    thinned = render_view(mustard, T_cam_obj=T, depth_noise=0.0, quantization=0.0, dropout=0.3)
    assert len(thinned.cloud) / len(full.cloud) == pytest.approx(0.7, abs=0.03)
    assert not np.any(thinned.mask & ~full.mask)


def test_occluders_hide_part_of_the_object_from_in_front(mustard):
    T = render_view(mustard, seed=4).T_cam_obj
    clear = render_view(mustard, T_cam_obj=T, **NOISE_FREE)
    for seed in range(5):
        occluded = render_view(mustard, T_cam_obj=T, seed=seed, occluders=2, **NOISE_FREE)
        hidden = clear.mask & ~occluded.mask
        assert 0 < len(occluded.cloud) < len(clear.cloud)
        assert not np.any(occluded.mask & ~clear.mask)
        # The occluders are measured in the depth image, nearer than the object they hide.
        assert np.all(occluded.depth[hidden] > 0)
        assert np.all(occluded.depth[hidden] < clear.depth[hidden])


def flat_plate(size: float = 0.2) -> trimesh.Trimesh:
    """A square of side ``size`` in the object's z = 0 plane."""
    h = size / 2
    vertices = [[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]]
    return trimesh.Trimesh(vertices=vertices, faces=[[0, 1, 2], [0, 2, 3]], process=False)


def test_depth_noise_and_quantisation_on_a_plate_facing_the_camera():
    T = pose(t=[0.0, 0.0, 0.6])
    noisy = render_view(flat_plate(), T_cam_obj=T, depth_noise=0.002, quantization=0.0, dropout=0.0)
    z = noisy.cloud[:, 2]
    assert len(z) > 20_000
    assert z.mean() == pytest.approx(0.6, abs=1e-4)
    assert z.std() == pytest.approx(0.002, rel=0.03)
    quantised = render_view(flat_plate(), T_cam_obj=T, depth_noise=0.001, quantization=0.001, dropout=0.0)
    z = quantised.cloud[:, 2]
    np.testing.assert_allclose(z * 1000, np.round(z * 1000), atol=1e-4)  # whole millimetres
    # Rounding adds a uniform error of variance q²/12.
    assert z.std() == pytest.approx(np.sqrt(0.001**2 + 0.001**2 / 12), rel=0.05)


def test_noise_free_plate_is_exact_and_covers_its_projection():
    view = render_view(flat_plate(0.2), T_cam_obj=pose(t=[0.0, 0.0, 0.5]), **NOISE_FREE)
    np.testing.assert_array_equal(view.cloud[:, 2], np.float32(0.5))
    # Pixel centres with |u − cx| ≤ fx·0.1/0.5 and |v − cy| ≤ fy·0.1/0.5.
    v, u = np.mgrid[0:480, 0:640]
    inside = (np.abs(u - CAM.cx) <= CAM.fx * 0.2) & (np.abs(v - CAM.cy) <= CAM.fy * 0.2)
    np.testing.assert_array_equal(view.mask, inside)


def test_depth_to_cloud_inverts_the_projection(rng):
    rows = rng.integers(0, 480, 200)
    cols = rng.integers(0, 640, 200)
    rows, cols = np.unique(np.column_stack([rows, cols]), axis=0).T
    z = rng.uniform(0.3, 2.0, len(rows))
    points = z[:, None] * (np.column_stack([cols, rows, np.ones_like(z)]) @ np.linalg.inv(CAM.K).T)
    depth = np.zeros((480, 640))
    depth[rows, cols] = z
    np.testing.assert_allclose(depth_to_cloud(depth, CAM), points, rtol=1e-12)
    # Millimetre images with a scale, and a mask that keeps every other point.
    depth_mm = np.round(depth * 1000).astype(np.uint16)
    mask = np.zeros((480, 640), dtype=bool)
    mask[rows[::2], cols[::2]] = True
    cloud = depth_to_cloud(depth_mm, CAM, mask=mask, depth_scale=1000.0)
    np.testing.assert_allclose(cloud, points[::2], atol=1e-3)  # depth rounded to 0.5 mm, x and y by ≤ 0.6 mm


def test_depth_to_cloud_keeps_only_positive_finite_depths():
    depth = np.zeros((480, 640), dtype=np.float32)
    depth[10, :5] = [0.0, -1.0, np.nan, np.inf, 0.5]
    cloud = depth_to_cloud(depth, CAM)
    np.testing.assert_allclose(cloud, [[(4 - CAM.cx) * 0.5 / CAM.fx, (10 - CAM.cy) * 0.5 / CAM.fy, 0.5]])
    with pytest.raises(ValueError, match="shape"):
        depth_to_cloud(np.zeros((480, 639)), CAM)
