"""Stressed synthetic scenes (edgepose.eval.scenes): real rendering, checked
against the geometry the renderer was given."""

from __future__ import annotations

import dataclasses
import threading
import time

import edgepose
import numpy as np
import pytest
import trimesh
from edgepose.cloud import dilate, erode
from edgepose.eval import LINEMOD_CAMERA, STRESS_LEVELS, Camera, SceneView, Stress, render_scene, render_view
from edgepose.eval.render import rasterize_depth
from edgepose.eval.scenes import noise_sigma
from edgepose.eval.stress import HOLE_PATCHES, TABLE_ELEVATION_DEG
from scipy.ndimage import distance_transform_edt, label

#: LINEMOD's camera at a quarter of its resolution: 160 × 120.
SMALL = Camera(572.4 / 4, 573.6 / 4, 325.3 / 4, 242.0 / 4, 160, 120)
SEEDS = range(4)


@pytest.fixture(scope="module")
def box() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=[0.16, 0.12, 0.08])


def alone(mesh: trimesh.Trimesh, view: SceneView) -> np.ndarray:
    """Depth of the object rendered by itself in the view's pose (inf off it)."""
    T = view.T_cam_obj
    return rasterize_depth(np.asarray(mesh.vertices) @ T[:3, :3].T + T[:3, 3], np.asarray(mesh.faces), view.camera)


def test_levels_are_named_and_ordered():
    assert list(STRESS_LEVELS)[:4] == ["clean", "visible70", "visible40", "visible20"]
    for name in [
        "spill2",
        "spill5",
        "spill8",
        "eroded3",
        "partial",
        "noise_far",
        "occluded30_spill5",
        "sensor_holes",
        "on_table",
    ]:
        assert STRESS_LEVELS[name].name == name
    with pytest.raises(dataclasses.FrozenInstanceError):
        STRESS_LEVELS["clean"].visible = 0.5
    with pytest.raises(ValueError):
        Stress("bad", noise="gaussian")
    with pytest.raises(ValueError):
        Stress("bad", spill_px=3, background=False)
    with pytest.raises(ValueError):
        Stress("bad", holes=0.1, background=False)
    with pytest.raises(ValueError):
        Stress("bad", resting=True, background=False)


def test_clean_level_is_render_views_view(box):
    for seed in SEEDS:
        scene, view = render_scene(box, "clean", seed, camera=SMALL), render_view(box, seed=seed, camera=SMALL)
        np.testing.assert_array_equal(scene.cloud, view.cloud)
        np.testing.assert_array_equal(scene.T_cam_obj, view.T_cam_obj)
        assert scene.visible_fraction == 1.0 and scene.spill_fraction == 0.0


@pytest.mark.parametrize("level", ["visible70", "visible40", "visible20", "occluded30_spill5"])
def test_visible_fraction_hits_the_target_behind_a_solid_occluder(box, level):
    target = STRESS_LEVELS[level].visible
    for seed in SEEDS:
        view = render_scene(box, level, seed, camera=SMALL)
        full = alone(box, view)
        assert abs(view.visible_fraction - target) <= 0.05, (seed, view.visible_fraction)
        assert view.visible_fraction == pytest.approx(view.true_mask.sum() / np.isfinite(full).sum())
        hidden = np.isfinite(full) & ~view.true_mask
        # Hidden object pixels are covered by something nearer: the occluder.
        assert np.all(view.ideal_depth[hidden] < full[hidden])
        assert view.true_mask.sum() <= np.isfinite(full).sum()


def test_same_pose_as_clean_at_the_same_distance(box):
    # Paired levels: only the stress differs between levels for one seed.
    for seed in SEEDS:
        np.testing.assert_array_equal(
            render_scene(box, "spill5", seed, camera=SMALL).T_cam_obj,
            render_scene(box, "clean", seed, camera=SMALL).T_cam_obj,
        )


@pytest.mark.parametrize("level", ["spill2", "spill5", "spill8"])
def test_spilled_mask_takes_background_within_n_pixels(box, level):
    n = STRESS_LEVELS[level].spill_px
    for seed in SEEDS:
        view = render_scene(box, level, seed, camera=SMALL)
        assert view.visible_fraction == 1.0
        ring = view.mask & ~view.true_mask
        assert ring.sum() > 0 and view.spill_fraction > 0
        assert np.all(view.mask[view.true_mask])  # grown, never shrunk
        assert distance_transform_edt(~view.true_mask)[ring].max() <= n + 1e-9
        # The ring is background: the plane or a neighbour, farther than the object's nearest point.
        assert np.isfinite(view.ideal_depth[ring]).mean() > 0.9
        # Its points reach the cloud: more points than the object's own pixels give.
        assert len(view.cloud) > (view.true_mask & (view.depth > 0)).sum()


def test_eroded_mask_is_inside_the_true_mask(box):
    for seed in SEEDS:
        view = render_scene(box, "eroded3", seed, camera=SMALL)
        assert view.mask.any() and not np.any(view.mask & ~view.true_mask)
        lost = view.true_mask & ~view.mask
        assert distance_transform_edt(view.true_mask)[lost].max() <= 3 + 1e-9


def test_partial_mask_misses_a_quarter(box):
    for seed in SEEDS:
        view = render_scene(box, "partial", seed, camera=SMALL)
        assert not np.any(view.mask & ~view.true_mask)
        assert view.mask.sum() / view.true_mask.sum() == pytest.approx(0.75, abs=0.05)


def test_holes_take_depth_from_round_patches_of_the_object(box):
    holes = Stress("holes", holes=0.15, dropout=0.0)
    for seed in SEEDS:
        view = render_scene(box, holes, seed, camera=SMALL)
        lost = view.true_mask & (view.depth == 0)
        assert lost.sum() / view.true_mask.sum() == pytest.approx(0.15, abs=0.01)
        assert label(lost)[1] <= HOLE_PATCHES  # patches (touching ones merge), not scattered pixels
        assert (view.depth[~view.true_mask] > 0).all()  # the background keeps its depth
        # The cloud is the measured part of the mask: the holes are missing from it.
        assert len(view.cloud) == (view.mask & (view.depth > 0)).sum()


def test_steep_surfaces_lose_their_depth():
    plate = trimesh.creation.box(extents=[0.3, 0.3, 0.002])
    steep = Stress("steep", grazing_deg=75.0, dropout=0.0)
    kept = {}
    for tilt in (60, 80):
        T = np.eye(4)
        T[:3, :3] = trimesh.transformations.rotation_matrix(np.radians(tilt), [0, 1, 0])[:3, :3]
        T[2, 3] = 0.8
        view = render_scene(plate, steep, 0, T_cam_obj=T, camera=SMALL)
        inner = erode(view.true_mask, 2)
        assert inner.sum() > 50
        kept[tilt] = (view.depth[inner] > 0).mean()
    assert kept[60] > 0.95 and kept[80] < 0.05


def test_flying_pixels_lie_between_object_and_background(box):
    for seed in SEEDS:
        view = render_scene(box, "spill8", seed, camera=SMALL)
        fly = view.flying_mask
        ring = view.mask & ~view.true_mask & (view.depth > 0)
        assert fly.sum() > 0 and not np.any(fly & ~ring)
        assert fly.sum() / ring.sum() == pytest.approx(0.25, abs=0.05)
        behind = fly & (view.ideal_depth > view.ideal_depth[view.true_mask].max() + 0.02)
        assert behind.sum() > 0
        front = view.ideal_depth[view.true_mask].min()
        # α in [0.1, 0.9] of the way from the object to the background (1 mm noise and rounding aside).
        assert np.all(view.depth[behind] >= front - 0.005)
        assert np.all(view.depth[behind] < view.ideal_depth[behind] - 0.001)


def test_depth_noise_grows_with_distance_on_a_plane():
    plate = trimesh.creation.box(extents=[1.2, 1.0, 0.002])
    stress = STRESS_LEVELS["noise_far"]
    measured = {}
    for z in (1.0, 2.0):
        T = np.eye(4)
        T[2, 3] = z
        view = render_scene(plate, stress, 0, T_cam_obj=T, camera=SMALL)
        inner = erode(view.true_mask, 3) & (view.depth > 0)
        assert inner.sum() > 1000
        residual = view.depth[inner].astype(np.float64) - view.ideal_depth[inner]
        measured[z] = residual.std()
        expected = np.hypot(noise_sigma(stress, np.array(z)), 0.001 / np.sqrt(12))  # with 1 mm rounding
        assert measured[z] == pytest.approx(expected, rel=0.15)
    assert measured[2.0] > 2 * measured[1.0]
    assert noise_sigma(STRESS_LEVELS["clean"], np.array([0.5, 2.0])).tolist() == [0.001, 0.001]


def test_same_seed_same_scene_other_seed_other_scene(box):
    a, b = (
        render_scene(box, "occluded30_spill5", 11, camera=SMALL),
        render_scene(box, "occluded30_spill5", 11, camera=SMALL),
    )
    c = render_scene(box, "occluded30_spill5", 12, camera=SMALL)
    for field in ("cloud", "depth", "mask", "true_mask", "T_cam_obj", "flying_mask"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert a.visible_fraction == b.visible_fraction
    assert not np.allclose(a.T_cam_obj, c.T_cam_obj)


def test_morphology_matches_a_disk():
    mask = np.zeros((21, 21), dtype=bool)
    mask[10, 10] = True
    grown = dilate(mask, 3)
    rows, cols = np.nonzero(grown)
    assert np.all((rows - 10) ** 2 + (cols - 10) ** 2 <= 9) and grown.sum() == 29
    assert np.array_equal(erode(grown, 3), mask)
    full = np.ones((8, 8), dtype=bool)
    assert erode(full, 2).sum() == 16  # the image border counts as outside


def test_cloud_is_the_masked_depth(box):
    view = render_scene(box, "spill5", 3, camera=SMALL)
    # Built from the uint16 millimetre image with the library's defaults; equal to the float metres one.
    np.testing.assert_allclose(
        view.cloud, edgepose.cloud_from_depth(view.depth, view.K, view.mask, depth_scale=1.0), atol=1e-6
    )


def test_ycb_scene_renders_fast(ycb_dir):
    mustard = edgepose.model.read_mesh(ycb_dir / "mustard_bottle.ply")
    times = []
    for level in ["visible40", "spill8", "occluded30_spill5", "noise_far"]:
        start = time.perf_counter()
        view = render_scene(mustard, level, 5, camera=LINEMOD_CAMERA)
        times.append(time.perf_counter() - start)
        assert len(view.cloud) > 200
    assert np.median(times) < 1.0


def touching(view: SceneView) -> int:
    """Pixels just off the object's silhouette whose surface lies within 3 mm
    of the depth of the object's pixel nearest to them."""
    _, (r, c) = distance_transform_edt(~view.true_mask, return_indices=True)
    ring = dilate(view.true_mask, 1) & ~view.true_mask
    return int((np.abs(view.ideal_depth - view.ideal_depth[r, c])[ring] < 0.003).sum())


def test_a_resting_object_lies_on_a_face_on_the_table_it_touches(box):
    table = STRESS_LEVELS["on_table"]
    assert table.resting and table.spill_px == 5
    low, high = np.radians(TABLE_ELEVATION_DEG)
    for seed in SEEDS:
        view = render_scene(box, table, seed, camera=SMALL)
        # The box lies on a face: one of its axes, up or down, is the table's
        # normal, (0, −cos e, −sin e) in the camera frame for a camera looking
        # down on the table from e above it.
        axes = np.concatenate([view.T_cam_obj[:3, :3].T, -view.T_cam_obj[:3, :3].T])
        up = [a for a in axes if abs(a[0]) < 1e-9 and a[1] < 0 and a[2] < 0]
        assert len(up) == 1
        assert low - 1e-9 <= np.arctan2(-up[0][2], -up[0][1]) <= high + 1e-9
        # The view says where its table is: that normal, touching the box's lowest corner.
        normal, offset = view.support
        np.testing.assert_allclose(normal, up[0], atol=1e-9)
        corners = trimesh.bounds.corners(box.bounds) @ view.T_cam_obj[:3, :3].T + view.T_cam_obj[:3, 3]
        assert (corners @ normal).min() == pytest.approx(offset, abs=1e-9)
        # The table meets the silhouette at the object's own depth (a wall
        # stands 2 cm or more behind it): where it touches.
        assert touching(view) >= 3
        assert touching(render_scene(box, "spill5", seed, camera=SMALL)) == 0
    a, b = render_scene(box, table, 7, camera=SMALL), render_scene(box, table, 7, camera=SMALL)
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.T_cam_obj, b.T_cam_obj)
    # A given pose is kept, and the table still touches the object at its lowest point.
    given = render_scene(box, "spill5", 3, camera=SMALL).T_cam_obj
    view = render_scene(box, table, 3, T_cam_obj=given, camera=SMALL)
    np.testing.assert_array_equal(view.T_cam_obj, given)
    assert touching(view) >= 1


def test_a_sheet_without_volume_lies_flat_on_the_table():
    # Its centre of mass is undefined (NaN): trimesh's stable poses would
    # search forever for a centre inside its hull, so it is laid flat instead.
    sheet = trimesh.Trimesh(
        vertices=[[0, 0, 0], [0.12, 0, 0], [0, 0.1, 0], [0.12, 0.1, 0]], faces=[[0, 1, 2], [1, 3, 2]]
    )
    views = []
    worker = threading.Thread(
        target=lambda: views.append(render_scene(sheet, "on_table", 2, camera=SMALL)), daemon=True
    )
    worker.start()
    worker.join(60)
    assert not worker.is_alive() and len(views) == 1
    normal = views[0].T_cam_obj[:3, :3] @ [0.0, 0.0, 1.0]  # the sheet's normal, camera frame
    assert abs(normal[0]) < 1e-9 and np.linalg.norm(normal[1:]) == pytest.approx(1.0)  # the table's, up or down
    assert len(views[0].cloud) > 50
