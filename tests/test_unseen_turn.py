"""View-dependent ambiguity: a mug whose handle the view hides is flagged
(the turn about its axis left open, alternatives spanning it, a confidence
below the strict rule); one whose handle is seen is not."""

from __future__ import annotations

import edgepose
import numpy as np
import pytest
import trimesh
from edgepose.eval import pose_errors, render_view
from edgepose.eval.view_ambiguity import feature_points, view_hides_feature
from edgepose.unseen_turn import NearAxis, near_axis
from edgepose.views import rotation_about


def _mug() -> trimesh.Trimesh:
    """An 8 cm cylinder, 10 cm tall, with a knob on its lid (so a view of
    its side tells up from down) and a box handle set off-centre in height
    (so the mug has no symmetry at all), metres."""
    body = trimesh.creation.cylinder(radius=0.04, height=0.1, sections=64)
    knob = trimesh.creation.cylinder(radius=0.015, height=0.012, sections=32)
    knob.apply_translation((0.0, 0.0, 0.056))
    handle = trimesh.creation.box(extents=(0.03, 0.012, 0.06))
    handle.apply_translation((0.052, 0.0, 0.015))
    return trimesh.util.concatenate([body, knob, handle])


@pytest.fixture(scope="module")
def mug():
    mesh = _mug()
    return mesh, edgepose.build_codebook(mesh)


def _view(handle_turn_deg: float) -> np.ndarray:
    """``T_cam_obj``: the mug upright in the image (its axis along the
    camera's -y), 60 cm away, its handle (object +x) turned about the axis:
    90° puts it straight behind the body, 0° to the image's right."""
    upright = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    T = np.eye(4)
    T[:3, :3] = upright @ rotation_about(np.array([0.0, 0, 1]), np.radians(handle_turn_deg))
    T[:3, 3] = (0.01, 0.02, 0.6)
    return T


def test_a_mug_has_a_near_symmetry_axis_and_a_box_has_none(mug):
    _, codebook = mug
    axis = near_axis(codebook.symmetry)
    assert axis is not None
    assert abs(axis.axis[2]) > 0.99  # the cylinder's axis (object z)
    assert np.linalg.norm(axis.point[:2]) < 0.003  # through the body's centre, not the handle's
    box = edgepose.build_codebook(trimesh.creation.box(extents=(0.12, 0.06, 0.04)), views=300)
    assert near_axis(box.symmetry) is None


def test_a_hidden_handle_leaves_the_turn_open_and_the_pose_says_so(mug):
    mesh, codebook = mug
    T = _view(90.0)
    pose = edgepose.estimate(render_view(mesh, T_cam_obj=T, seed=1).cloud, codebook)
    assert pose.unseen_turn is not None
    assert abs(pose.unseen_turn.axis[2]) > 0.99
    assert len(pose.unseen_turn.angles_deg) >= 6  # at least 90° of turns explain the view
    assert 0 < pose.unseen_turn.share < 0.5
    assert pose.evidence["unseen_turn_share"] == pose.unseen_turn.share
    assert pose.confidence < pose.strict_threshold
    model, d = codebook.model, codebook.model.diameter
    right = [
        pose_errors(model.mesh_points, p, T, d, False).correct_add_or_s
        for p in [pose.matrix] + [a.matrix for a in pose.alternatives]
    ]
    assert any(right)  # the truth is the pose or one of its alternatives
    assert len(pose.alternatives) >= 3


def test_a_seen_handle_fixes_the_turn(mug):
    mesh, codebook = mug
    T = _view(0.0)
    pose = edgepose.estimate(render_view(mesh, T_cam_obj=T, seed=1).cloud, codebook)
    assert pose.unseen_turn is None and "unseen_turn_share" not in pose.evidence
    assert pose_errors(codebook.model.mesh_points, pose.matrix, T, codebook.model.diameter, False).correct_add_or_s
    assert pose.confidence >= 0.5


def test_turning_off_the_unseen_turn_keeps_the_search_alone(mug):
    mesh, codebook = mug
    cloud = render_view(mesh, T_cam_obj=_view(90.0), seed=1).cloud
    off = edgepose.estimate(
        cloud, codebook, settings=edgepose.EstimateSettings().with_(**{"alternatives.unseen_turns": -1})
    )
    on = edgepose.estimate(cloud, codebook)
    assert off.unseen_turn is None
    np.testing.assert_array_equal(off.matrix, on.matrix)  # the pose itself is the same
    assert on.confidence < off.confidence


def test_a_tracked_frame_carries_the_open_turn(mug):
    mesh, codebook = mug
    T = _view(90.0)
    tracker = edgepose.Tracker(codebook)
    first = tracker.update(render_view(mesh, T_cam_obj=T, seed=1).cloud)
    T2 = T.copy()
    T2[0, 3] += 0.003
    second = tracker.update(render_view(mesh, T_cam_obj=T2, seed=2).cloud)
    assert second.mode == "tracked"
    assert second.unseen_turn is first.unseen_turn is not None
    assert second.confidence < second.strict_threshold


@pytest.mark.parametrize(
    ("handle_turn_deg", "hidden"), [(90.0, True), (0.0, False), (-45.0, False), (-90.0, False), (180.0, False)]
)
def test_the_ground_truth_says_whether_a_view_hides_the_handle(mug, handle_turn_deg, hidden):
    mesh, codebook = mug
    points = codebook.model.mesh_points
    features = feature_points(points, near_axis(codebook.symmetry), codebook.model.diameter)
    handle = points[:, 0] > 0.045  # the box handle stands 1.2–4.2 cm beyond the 4 cm body
    assert features.any() and handle[features].all()
    view = render_view(mesh, T_cam_obj=_view(handle_turn_deg), seed=2)
    assert view_hides_feature(points, features, view.T_cam_obj, view.depth, view.camera.K, view.mask) is hidden


def test_a_body_of_revolution_has_no_feature_for_a_view_to_hide():
    body = trimesh.creation.cylinder(radius=0.04, height=0.1, sections=64)
    points = np.asarray(body.sample(2000, seed=0))
    features = feature_points(points, NearAxis(np.array([0.0, 0, 1]), np.zeros(3)), 0.13)
    assert not features.any()
    view = render_view(body, T_cam_obj=_view(90.0), seed=2)
    assert not view_hides_feature(points, features, view.T_cam_obj, view.depth, view.camera.K, view.mask)
