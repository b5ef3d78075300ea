"""Real-scene robustness: flying pixels and mask erosion in cloud_from_depth,
background rejection in estimate's query preparation, the free-space term of
pose scoring, and whole estimates on stressed scenes. Hand-made clouds with
known background, occluders and flipped poses; real renders of a real mesh."""

from __future__ import annotations

import edgepose
import numpy as np
import pytest
import trimesh
from edgepose import _core
from edgepose.cloud import FLYING_PIXEL_JUMP, clean_cloud, depth_discontinuities, dilate, erode, median_depth
from edgepose.eval import pose_errors, render_scene, render_view
from edgepose.stages import near_the_cloud, on_support_plane, pair_poses, prepare_query, usable_icp

K = np.array([[500.0, 0, 80], [0, 500.0, 60], [0, 0, 1]])


def wall_with_square(square_depth=0.6, wall_depth=0.65, mixed_column=True):
    """A 160 × 120 depth image: a 40 × 40 px square object at ``square_depth``
    in front of a wall at ``wall_depth`` (metres), with a column of mixed
    ("flying") pixels halfway between them along the square's right edge.
    Returns (depth, true object mask, mixed pixel mask)."""
    depth = np.full((120, 160), wall_depth)
    obj = np.zeros(depth.shape, dtype=bool)
    obj[40:80, 60:100] = True
    depth[obj] = square_depth
    mixed = np.zeros(depth.shape, dtype=bool)
    if mixed_column:
        mixed[40:80, 100] = True
        depth[mixed] = (square_depth + wall_depth) / 2
    return depth, obj, mixed


def test_flying_pixels_at_depth_edges_are_dropped():
    depth, obj, mixed = wall_with_square()
    spilled = dilate(obj, 5)
    edges = depth_discontinuities(depth, depth > 0, spilled, FLYING_PIXEL_JUMP)
    assert edges[mixed].all(), "every mixed pixel differs from both of its sides"
    assert not edges[erode(obj, 1)].any(), "the object's inside has no discontinuity"
    assert not edges[spilled & ~dilate(obj, 3)].any(), "the flat wall beyond the edge has none"
    cloud = edgepose.cloud_from_depth(depth, K, spilled, depth_scale=1.0, max_jump=FLYING_PIXEL_JUMP)
    kept = edgepose.cloud_from_depth(depth, K, spilled, depth_scale=1.0)
    assert len(kept) == spilled.sum() and len(cloud) == spilled.sum() - edges.sum()
    # No kept point lies between the two surfaces.
    assert not ((cloud[:, 2] > 0.605) & (cloud[:, 2] < 0.645)).any()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_median_depth_is_numpys_median_of_z(dtype):
    rng = np.random.default_rng(5)
    for n in [1, 2, 3, 4, 17, 1535, 1536]:
        points = rng.normal(0.7, 0.1, (n, 3)).astype(dtype)
        assert median_depth(points) == float(np.median(points[:, 2])), n


def test_the_querys_median_depth_is_numpys_median_of_its_z():
    """The core's stage 1 gives the kept points' median depth as numpy does,
    for an odd and an even count."""
    rng = np.random.default_rng(6)
    for n in [600, 601, 1535, 1536]:
        points = rng.normal((0.02, -0.01, 0.7), (0.03, 0.03, 0.02), (n, 3)).astype(np.float32)
        kept, *_, depth = _core.prepare_query(points, 0.12, 1.0, 512, 32, 32, None)
        assert len(kept) == n and depth == float(np.median(kept[:, 2])), n


def test_erosion_shrinks_the_mask_before_back_projection():
    depth, obj, _ = wall_with_square(mixed_column=False)
    cloud = edgepose.cloud_from_depth(depth, K, obj, depth_scale=1.0, erode_px=3, max_jump=None)
    assert len(cloud) == 34 * 34
    with pytest.raises(edgepose.InvalidCloudError, match="erode_px"):
        edgepose.cloud_from_depth(depth, K, obj, depth_scale=1.0, erode_px=-1)
    with pytest.raises(edgepose.InvalidCloudError, match="max_jump"):
        edgepose.cloud_from_depth(depth, K, obj, depth_scale=1.0, max_jump=0.0)


def test_segmentation_drops_a_spilled_background_ring_and_keeps_an_occluded_object():
    depth, obj, _ = wall_with_square(mixed_column=False)
    ring = dilate(obj, 5) & ~obj
    # The object cut in two by a 6 px post in front (not in the mask).
    visible = obj.copy()
    visible[:, 77:83] = False
    cloud = edgepose.cloud_from_depth(depth, K, visible | ring, depth_scale=1.0, max_jump=None).astype(np.float32)
    keep, spacing = _core.segment_object(cloud, 0.07, edgepose.SegmentSettings().core())
    on_object = cloud[:, 2] < 0.62
    assert keep[on_object].all(), "both halves of the occluded object are kept"
    assert not keep[~on_object].any(), "the wall ring behind it is dropped"
    assert 0.0008 < spacing < 0.0016  # 0.6 m / 500 px = 1.2 mm between pixels


@pytest.mark.parametrize("steepness", [70.0, 75.0])
def test_segmentation_keeps_a_box_face_seen_nearly_edge_on(steepness):
    """A 21 × 16 × 6 cm box rendered at 0.7 m with its 16 × 6 cm end face
    ``steepness`` degrees from face-on: sparse in space, so steps 1 and 2 of
    the segmentation cut half of it away; step 3 puts it back."""
    box = trimesh.creation.box(extents=(0.21, 0.16, 0.06))
    turn = np.radians(90.0 - steepness)
    T = trimesh.transformations.rotation_matrix(turn, [0, 1, 0])
    T[2, 3] = 0.7
    cloud = clean_cloud(render_view(box, T_cam_obj=T, seed=3).cloud, 0.27, 2048)
    in_box = (cloud - T[:3, 3]) @ T[:3, :3]
    on_end = np.abs(in_box[:, 0]) > 0.105 - 0.002
    assert on_end.sum() > 100
    keep_before, _ = _core.segment_object(cloud, 0.27, edgepose.SegmentSettings(steep_faces=False).core())
    keep, _ = _core.segment_object(cloud, 0.27, edgepose.SegmentSettings().core())
    assert keep_before[on_end].mean() < 0.6, "the failure this step mends"
    assert keep[on_end].mean() > 0.9
    assert keep[~on_end].mean() > 0.99 and keep_before[~on_end].mean() > 0.99


def test_free_space_separates_the_true_pose_from_a_turned_over_one(drill):
    mesh, codebook = drill
    view = edgepose.eval.render_view(mesh, seed=5)
    query = prepare_query(view.cloud, codebook)
    T = view.T_cam_obj
    R = T[:3, :3]
    t_model = T[:3, 3] + R @ codebook.model.centre  # model frame = mesh frame shifted by the centre
    # Turned 180° about the camera-facing axis through the object's centre:
    # the back of the drill now faces the camera, in front of the seen surface.
    ray = t_model / np.linalg.norm(t_model)
    axis = np.cross(ray, [1.0, 0, 0])
    axis /= np.linalg.norm(axis)
    flip = 2 * np.outer(axis, axis) - np.eye(3)  # 180° about `axis`
    rotations = np.stack([R, flip @ R])
    translations = np.stack([t_model, t_model])
    d = codebook.model.diameter
    scores = codebook.index.score(query.keypoints, query.free_space, rotations, translations, 0.02 * d, 0.03 * d, 1)
    violation, inliers, scene = scores.free_space_violation, scores.inlier_fraction, scores.scene_violation
    assert len(scores) == 2
    assert violation[0] < 0.02 and inliers[0] > 0.9, (violation, inliers)
    assert query.free_space is query.free_space  # built once per query
    assert (scene == 0).all()  # no frame given
    assert violation[1] > 0.2, violation


@pytest.mark.parametrize("stress", ["visible70", "spill5", "occluded30_spill5", "sensor_holes", "on_table"])
def test_estimate_on_stressed_scenes(drill, stress):
    mesh, codebook = drill
    points = codebook.model.mesh_points
    correct = 0
    for seed in range(6):
        view = render_scene(mesh, stress, seed=seed)
        pose = edgepose.estimate(view.cloud, codebook)
        correct += pose_errors(points, pose.matrix, view.T_cam_obj, codebook.model.diameter, False).correct_add_or_s
        assert 0.0 <= pose.free_space_violation <= 1.0 and 0.0 <= pose.inlier_fraction <= 1.0
        assert 32 <= pose.kept_points <= len(view.cloud)
    assert correct >= 4, f"{correct}/6 correct at {stress}"


def test_missing_depth_beside_the_object_is_not_free_space(drill):
    # Patches without depth on the object (dark or shiny) and its steep rim
    # lost: the true pose's model points there are unknown space, not points
    # standing in front of the background measured just beyond them.
    mesh, codebook = drill
    points = codebook.model.mesh_points
    violations = []
    for seed in range(6):
        view = render_scene(mesh, "sensor_holes", seed=seed)
        pose = edgepose.estimate(view.cloud, codebook, depth=view.depth, K=view.K, depth_scale=1.0)
        if pose_errors(points, pose.matrix, view.T_cam_obj, codebook.model.diameter, False).correct_add_or_s:
            violations.append(pose.evidence["scene_violation"])
    assert len(violations) >= 5 and max(violations) < 0.005, violations


def test_poses_far_from_the_observed_points_are_not_plausible(drill):
    mesh, codebook = drill
    view = edgepose.eval.render_view(mesh, seed=4)
    query = prepare_query(view.cloud, codebook)
    radius = 1.0 / codebook.model.scale
    true_centre = view.T_cam_obj[:3, 3] + view.T_cam_obj[:3, :3] @ codebook.model.centre
    behind = true_centre + 2 * radius * query.centroid / np.linalg.norm(query.centroid)
    beside = true_centre + [1.5 * radius, 0, 0]
    near = near_the_cloud(query.centroid, codebook, np.stack([true_centre, behind, beside]))
    assert near.tolist() == [True, False, False]
    # The ICP results' rule (the core's): the same centres, and enough
    # inliers and a finite RMSE besides.
    translations = np.stack([true_centre, behind, beside, true_centre, true_centre])
    inliers = np.array([100, 100, 100, 15, 100], np.uint32)
    rmse = np.array([1e-3, 1e-3, 1e-3, 1e-3, np.nan])
    usable = usable_icp(query, codebook, inliers, rmse, translations, edgepose.EstimateSettings())
    assert usable.tolist() == [True, False, False, False, False]
    pose = edgepose.estimate(view.cloud, codebook)
    assert np.linalg.norm(pose.t + pose.R @ codebook.model.centre - query.centroid) <= 1.25 * radius


def test_point_pairs_find_a_mostly_hidden_object_that_the_view_codes_miss(drill):
    # 40 % visible: the map's code matches no codebook view near the truth on
    # most of these views (the first search alone gets 1 of the 6 right),
    # while the point pairs' strongest pose is right on each, and estimate's
    # second search, which adds them, on 5 or more.
    mesh, codebook = drill
    points, d = codebook.model.mesh_points, codebook.model.diameter
    add = lambda T, view: pose_errors(points, T, view.T_cam_obj, d, False).add  # noqa: E731
    first_only, strongest_pair, both = 0, 0, 0
    for seed in (4, 5, 7, 8, 9, 10):
        view = render_scene(mesh, "visible40", seed=seed)
        first_only += add(estimate_with(view, codebook, **{"second_search.pair_poses": 0}), view) < 0.1 * d
        rotations, translations = pair_poses(prepare_query(view.cloud, codebook), codebook)
        assert 1 <= len(rotations) <= edgepose.EstimateSettings().second_search.pair_poses
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = rotations[0], translations[0] - rotations[0] @ codebook.model.centre
        strongest_pair += add(T, view) < 0.1 * d
        pose = edgepose.estimate(view.cloud, codebook)
        both += add(pose.matrix, view) < 0.1 * d
        assert pose.searches == 2
    assert first_only <= 2 and strongest_pair >= 5 and both >= 5, (first_only, strongest_pair, both)


def estimate_with(view, codebook, **settings):
    return edgepose.estimate(view.cloud, codebook, settings=edgepose.EstimateSettings().with_(**settings)).matrix


@pytest.mark.parametrize("level", ["on_table", "spill5", "partial", "visible40", "eroded3"])
def test_the_surface_the_object_stands_on_is_found_around_the_mask(level):
    # A table the box rests on (the mask spilled onto it where the two meet,
    # no depth jump between them) and a wall behind it: the spilled points on
    # either are found, the box's own only in the millimetres above the
    # table. A cut mask, an occluder in front and an eroded mask put the
    # object's own face or the occluder around the mask: nothing is taken.
    box = trimesh.creation.box(extents=[0.16, 0.12, 0.08])
    camera = edgepose.eval.Camera(572.4 / 4, 573.6 / 4, 325.3 / 4, 242.0 / 4, 160, 120)
    for seed in range(4):
        view = render_scene(box, level, seed, camera=camera)
        seen = view.mask & (view.depth > 0)  # the cloud's pixels, in its order
        assert seen.sum() == len(view.cloud)
        on_object, mixed = view.true_mask[seen], view.flying_mask[seen]
        on = on_support_plane(view.cloud.astype(np.float32), view.depth, view.K, 1.0, 0.2154)
        assert on[on_object].mean() <= (0.03 if level == "on_table" else 0.0)
        if level in ("on_table", "spill5"):
            assert on[~on_object & ~mixed].mean() >= 0.9
        else:
            assert not on.any()


def test_the_surface_search_ignores_points_without_a_pixel_and_refuses_a_bad_K():
    # A point that projects nowhere (NaN, or far off the image) changes
    # nothing about the table found; a K that is not 3 × 3 is a clear error.
    box = trimesh.creation.box(extents=[0.16, 0.12, 0.08])
    camera = edgepose.eval.Camera(572.4 / 4, 573.6 / 4, 325.3 / 4, 242.0 / 4, 160, 120)
    view = render_scene(box, "on_table", 0, camera=camera)
    points = view.cloud.astype(np.float32)
    on = on_support_plane(points, view.depth, view.K, 1.0, 0.2154)
    assert on.any()
    odd = np.concatenate([points, [[np.nan, 0.0, 0.5], [1e30, -1e30, 0.5]]]).astype(np.float32)
    assert (on_support_plane(odd, view.depth, view.K, 1.0, 0.2154) == np.concatenate([on, [False, False]])).all()
    with pytest.raises(ValueError, match="K must be 3 × 3"):
        on_support_plane(points, view.depth, view.K[:2], 1.0, 0.2154)


def test_a_table_the_object_stands_on_costs_no_second_search_given_the_frame(drill):
    # The drill on a table, the mask spilled onto it: without the support
    # plane most views keep table points and fail the first search's
    # inlier test (second_search.retry_below_inlier_fraction), with it few do.
    mesh, codebook = drill
    searches = {True: 0, False: 0}
    for seed in range(6):
        view = render_scene(mesh, "on_table", seed=seed)
        for plane in (True, False):
            settings = edgepose.EstimateSettings(support_plane=plane)
            pose = edgepose.estimate(
                view.cloud, codebook, depth=view.depth, K=view.K, depth_scale=1.0, settings=settings
            )
            searches[plane] += pose.searches
    assert searches[True] < searches[False], searches


def test_a_frame_without_columns_is_no_scene_and_no_crash(drill):
    # Found by benches/fuzz.py: a (66, 0) depth image beside a good cloud.
    mesh, codebook = drill
    view = render_view(mesh, seed=3)
    empty = np.zeros((66, 0), np.float32)
    pose = edgepose.estimate(view.cloud, codebook, depth=empty, K=view.camera.K, depth_scale=1.0)
    assert np.isfinite(pose.matrix).all()
    tracker = edgepose.Tracker(codebook)
    tracker.update(view.cloud)
    frame = edgepose.track_many(empty, view.camera.K, [(np.zeros((66, 0), bool), tracker)], depth_scale=1.0)
    assert frame.poses == (None,) and isinstance(frame.errors[0], edgepose.InvalidCloudError)
