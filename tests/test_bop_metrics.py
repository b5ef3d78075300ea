"""BOP challenge errors (VSD, MSSD, MSPD) against hand-computed values and
the BOP toolkit's rules (thodan/bop_toolkit)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from edgepose.eval import bop_metrics
from edgepose.eval.bop_metrics import (
    BOP_MSPD_THRESHOLDS,
    BOP_MSSD_THRESHOLDS,
    BOP_VSD_DELTA,
    BOP_VSD_DELTAS,
    BOP_VSD_TAUS,
    BOP_VSD_THRESHOLDS,
    bop_mspd_thresholds,
    bop_symmetry_transforms,
    mspd,
    mssd,
    vsd,
)
from edgepose.eval.render import Camera, rasterize_depth
from edgepose.symmetry import NO_SYMMETRY, Symmetry
from scipy.spatial.transform import Rotation

#: A small camera for VSD: 64 × 48 px, 60 px focal length, centre between pixels.
CAMERA = Camera(60.0, 60.0, 31.5, 23.5, 64, 48)
#: Intrinsics for MSSD / MSPD.
K = np.array([[500.0, 0.0, 320.0], [0.0, 400.0, 240.0], [0.0, 0.0, 1.0]])
#: Steps of a continuous symmetry at max_sym_disc_step = 0.01: ceil(π / 0.01).
STEPS = 315


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def turn(R: np.ndarray, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def render(mesh: trimesh.Trimesh, R: np.ndarray, t, camera: Camera = CAMERA) -> np.ndarray:
    """Depth (metres) of ``mesh`` at pose (R, t), 0 where empty."""
    depth = rasterize_depth(mesh.vertices @ R.T + np.asarray(t), mesh.faces, camera)
    return np.where(np.isfinite(depth), depth, 0.0)


# ------------------------------------------------------------------ constants


def test_bop19_constants():
    assert np.allclose(BOP_VSD_TAUS, np.linspace(0.05, 0.5, 10))
    assert np.array_equal(BOP_VSD_TAUS, np.arange(0.05, 0.51, 0.05))  # the toolkit's exact floats
    assert np.array_equal(BOP_VSD_THRESHOLDS, BOP_VSD_TAUS)
    assert np.array_equal(BOP_MSSD_THRESHOLDS, BOP_VSD_TAUS)
    assert BOP_MSPD_THRESHOLDS.tolist() == [5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0, 45.0, 50.0]
    assert BOP_VSD_DELTA == 0.015
    assert BOP_VSD_DELTAS["itodd"] == 0.005 and BOP_VSD_DELTAS["ycbv"] == 0.015 and BOP_VSD_DELTAS["lmo"] == 0.015
    with pytest.raises(ValueError):
        BOP_VSD_TAUS[0] = 1.0


def test_mspd_thresholds_scale_with_image_width():
    # The toolkit multiplies MSPD by 640 / width before comparing with 5 … 50 px.
    assert np.array_equal(bop_mspd_thresholds(640), BOP_MSPD_THRESHOLDS)
    assert bop_mspd_thresholds(1280)[0] == 10.0 and bop_mspd_thresholds(1280)[-1] == 100.0
    assert bop_mspd_thresholds(320)[1] == 5.0


# ---------------------------------------------------------- symmetry transforms


def test_no_symmetry_is_the_identity_alone():
    transforms = bop_symmetry_transforms(NO_SYMMETRY)
    assert transforms.shape == (1, 4, 4) and np.array_equal(transforms[0], np.eye(4))


def test_discrete_symmetries_follow_the_identity():
    turns = np.stack([turn(rot_z(np.pi / 2 * k)) for k in (1, 2, 3)])
    transforms = bop_symmetry_transforms(Symmetry(turns, np.zeros((0, 6))))
    assert transforms.shape == (4, 4, 4)
    assert np.array_equal(transforms[0], np.eye(4)) and np.array_equal(transforms[1:], turns)


def test_continuous_symmetry_discretisation_matches_the_toolkit():
    point = np.array([0.02, -0.01, 0.0])
    symmetry = Symmetry(np.zeros((0, 4, 4)), np.array([[0.0, 0.0, 1.0, *point]]))
    transforms = bop_symmetry_transforms(symmetry)
    # ceil(π / 0.01) = 315 angles i · 2π/315, i = 0 … 314: identity included, 2π not.
    assert len(transforms) == STEPS == int(np.ceil(np.pi / 0.01))
    assert np.allclose(transforms[0], np.eye(4), atol=1e-15)
    for i in (1, 100, 314):
        R = rot_z(i * 2 * np.pi / STEPS)
        assert np.allclose(transforms[i], turn(R, point - R @ point), atol=1e-12)
    # Every turn keeps the axis point where it is (t = −R·offset + offset).
    assert np.allclose(transforms[:, :3, :3] @ point + transforms[:, :3, 3], point, atol=1e-15)
    # A coarser step: ceil(π / 0.5) = 7.
    assert len(bop_symmetry_transforms(symmetry, max_sym_disc_step=0.5)) == 7


def test_discrete_and_continuous_symmetries_combine_like_the_toolkit():
    flip = turn(np.diag([1.0, -1.0, -1.0]))  # 180° about x: a can's top-to-bottom flip
    symmetry = Symmetry(flip[None], np.array([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0]]))
    transforms = bop_symmetry_transforms(symmetry)
    assert len(transforms) == 2 * STEPS
    assert np.allclose(transforms[0], np.eye(4), atol=1e-15)
    # Discrete turn outer, continuous turn inner: index d · 315 + c holds C_c · D_d.
    C5 = turn(rot_z(5 * 2 * np.pi / STEPS))
    assert np.allclose(transforms[5], C5, atol=1e-12)
    assert np.allclose(transforms[STEPS + 5], C5 @ flip, atol=1e-12)


def test_two_continuous_axes_are_concatenated_not_composed():
    axes = np.array([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]])
    transforms = bop_symmetry_transforms(Symmetry(np.zeros((0, 4, 4)), axes))
    assert len(transforms) == 2 * STEPS
    assert np.allclose(transforms[STEPS], np.eye(4), atol=1e-15)  # each axis starts at the identity


# ---------------------------------------------------------------- MSSD / MSPD

#: The origin and a point 10 cm along each object axis.
POINTS = np.vstack([np.zeros(3), 0.1 * np.eye(3)])
IDENTITY = np.eye(4)[None]


def test_identical_poses_score_zero():
    R = Rotation.from_euler("xyz", [0.3, -0.5, 1.2]).as_matrix()
    t = np.array([0.05, -0.02, 0.9])
    box = trimesh.creation.box(extents=(0.1, 0.06, 0.04))
    half_turn = Symmetry(turn(rot_z(np.pi))[None], np.zeros((0, 6)))
    for transforms in (IDENTITY, bop_symmetry_transforms(half_turn)):
        assert mssd(R, t, R, t, box.vertices, transforms) == 0.0
        assert mspd(R, t, R, t, box.vertices, transforms, K) == 0.0


def test_translation_offset():
    R, t_gt = np.eye(3), np.array([0.0, 0.0, 1.0])
    t_est = t_gt + [0.01, 0.02, 0.0]
    # Every point moves by the offset: √(0.01² + 0.02²) m.
    assert mssd(R, t_est, R, t_gt, POINTS, IDENTITY) == pytest.approx(np.hypot(0.01, 0.02), abs=1e-12)
    # In the image a point at depth z moves (fx·0.01/z, fy·0.02/z) = (5, 8) px at the nearest depth z = 1 m.
    assert mspd(R, t_est, R, t_gt, POINTS, IDENTITY, K) == pytest.approx(np.hypot(5.0, 8.0), abs=1e-9)
    # (3, 1) translations, as the toolkit passes them, are accepted.
    assert mssd(R, t_est[:, None], R, t_gt[:, None], POINTS, IDENTITY) == pytest.approx(np.hypot(0.01, 0.02))


def test_box_half_turn_is_free_with_its_discrete_symmetry():
    box = trimesh.creation.box(extents=(0.1, 0.06, 0.04))
    R_gt = Rotation.from_euler("xyz", [0.4, 0.2, -0.7]).as_matrix()
    t = np.array([0.02, 0.01, 0.8])
    R_est = R_gt @ rot_z(np.pi)
    half_turn = bop_symmetry_transforms(Symmetry(turn(rot_z(np.pi))[None], np.zeros((0, 6))))
    assert mssd(R_est, t, R_gt, t, box.vertices, half_turn) < 1e-12
    assert mspd(R_est, t, R_gt, t, box.vertices, half_turn, K) < 1e-9
    # Without it, a corner (±5, ±3, ·) cm moves to (∓5, ∓3, ·): 2·√(5² + 3²) cm.
    assert mssd(R_est, t, R_gt, t, box.vertices, IDENTITY) == pytest.approx(2 * np.hypot(0.05, 0.03), abs=1e-12)
    assert mspd(R_est, t, R_gt, t, box.vertices, IDENTITY, K) > 50.0


def test_cylinder_turn_about_an_offset_axis():
    # Points on a 3 cm circle about the vertical line through (2, −1, 0) cm, at three heights.
    r, centre = 0.03, np.array([0.02, -0.01, 0.0])
    angles = np.random.default_rng(0).uniform(0, 2 * np.pi, 60)
    points = np.concatenate(
        [np.column_stack([r * np.cos(angles), r * np.sin(angles), np.full(60, z)]) + centre for z in (-0.04, 0, 0.04)]
    )
    symmetry = Symmetry(np.zeros((0, 4, 4)), np.array([[0.0, 0.0, 1.0, *centre]]))
    transforms = bop_symmetry_transforms(symmetry)
    T_gt = turn(Rotation.from_euler("xyz", [0.5, -0.3, 0.2]).as_matrix(), (0.0, 0.0, 0.7))
    angle = 0.7
    T_est = T_gt @ turn(rot_z(angle), centre - rot_z(angle) @ centre)
    args = (T_est[:3, :3], T_est[:3, 3], T_gt[:3, :3], T_gt[:3, 3], points)
    # The nearest sampled turn is 35 · 2π/315; every point is r from the axis, so
    # the largest distance is the chord of the leftover angle.
    leftover = angle - 35 * 2 * np.pi / STEPS
    assert mssd(*args, transforms) == pytest.approx(2 * r * np.sin(leftover / 2), rel=1e-6)
    assert mssd(*args, transforms) < 2 * r * np.sin(np.pi / STEPS / 2) + 1e-12
    assert mssd(*args, IDENTITY) == pytest.approx(2 * r * np.sin(angle / 2), rel=1e-9)
    assert mspd(*args, transforms, K) < 0.2 < 10 < mspd(*args, IDENTITY, K)
    # The axis through the origin instead is not a symmetry of these points.
    wrong = bop_symmetry_transforms(Symmetry(np.zeros((0, 4, 4)), np.array([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0]])))
    assert mssd(*args, wrong) > 0.005


def toolkit_style(R_est, t_est, R_gt, t_gt, points, transforms, K=None):
    """MSSD (K None) or MSPD by the toolkit's loop over symmetries."""

    def image(pts, R, t):
        p = pts @ R.T + t
        return p if K is None else (p @ K.T)[:, :2] / (p @ K.T)[:, 2:]

    est = image(points, R_est, t_est)
    return min(
        np.linalg.norm(est - image(points, R_gt @ S[:3, :3], R_gt @ S[:3, 3] + t_gt), axis=1).max() for S in transforms
    )


def test_mssd_mspd_agree_with_a_loop_over_symmetries(monkeypatch):
    monkeypatch.setattr(bop_metrics, "_SYM_CHUNK_POINTS", 500)  # several chunks of transforms
    rng = np.random.default_rng(1)
    points = rng.normal(0, 0.03, (100, 3))
    symmetry = Symmetry(turn(np.diag([1.0, -1.0, -1.0]))[None], np.array([[0.0, 0.0, 1.0, 0.01, 0.0, 0.0]]))
    transforms = bop_symmetry_transforms(symmetry, max_sym_disc_step=0.1)
    for _ in range(3):
        R_gt, R_est = Rotation.random(2, random_state=rng).as_matrix()
        t_gt = rng.normal(0, 0.05, 3) + [0, 0, 0.8]
        t_est = t_gt + rng.normal(0, 0.01, 3)
        args = (R_est, t_est, R_gt, t_gt, points, transforms)
        assert mssd(*args) == pytest.approx(toolkit_style(*args), rel=1e-12)
        assert mspd(*args, K) == pytest.approx(toolkit_style(*args, K), rel=1e-12)


# ------------------------------------------------------------------------ VSD

K_SMALL = CAMERA.K
#: A 10 × 10 cm plate, 1 mm thick, facing the camera 50 cm away: columns 26–37
#: and rows 18–29 (its edges fall half-way between pixel centres).
PLATE = trimesh.creation.box(extents=(0.1, 0.1, 0.001))
PLATE_DIAMETER = float(np.sqrt(0.1**2 + 0.1**2 + 0.001**2))
I3 = np.eye(3)
T_PLATE = np.array([0.0, 0.0, 0.5])
#: The plate moved right by 4 px (60 px · x / 0.5 m = 4): columns 30–41.
T_RIGHT = T_PLATE + [4 * 0.5 / 60, 0.0, 0.0]
ONES = np.ones(len(BOP_VSD_TAUS))


def plate_vsd(depth_test: np.ndarray, t_est=T_RIGHT) -> np.ndarray:
    return vsd(
        I3, t_est, I3, T_PLATE, depth_test, K_SMALL, PLATE.vertices, PLATE.faces, 0.015, BOP_VSD_TAUS, PLATE_DIAMETER
    )


def test_plate_masks_are_as_reasoned():
    rows, cols = np.nonzero(render(PLATE, I3, T_PLATE))
    assert (cols.min(), cols.max(), rows.min(), rows.max(), len(rows)) == (26, 37, 18, 29, 144)
    rows, cols = np.nonzero(render(PLATE, I3, T_RIGHT))
    assert (cols.min(), cols.max(), rows.min(), rows.max(), len(rows)) == (30, 41, 18, 29, 144)


def test_vsd_same_pose_is_zero():
    assert np.array_equal(plate_vsd(render(PLATE, I3, T_PLATE), T_PLATE), np.zeros(10))
    # The step cost is |Δd| / diameter ≥ τ: at τ = 0 even a perfect pixel costs 1.
    depth = render(PLATE, I3, T_PLATE)
    errors = vsd(I3, T_PLATE, I3, T_PLATE, depth, K_SMALL, PLATE.vertices, PLATE.faces, 0.015, [0.0, 0.05], 0.1)
    assert errors.tolist() == [1.0, 0.0]
    can = trimesh.creation.cylinder(radius=0.03, height=0.08, sections=24)
    R = Rotation.from_euler("xyz", [0.6, -0.4, 0.3]).as_matrix()
    t = np.array([0.01, -0.02, 0.45])
    errors = vsd(R, t, R, t, render(can, R, t), K_SMALL, can.vertices, can.faces, 0.015, BOP_VSD_TAUS, 0.1)
    assert np.array_equal(errors, np.zeros(10))


def test_vsd_without_overlap_is_one():
    # 24 px to the right (columns 50–61): no pixel in common.
    assert np.array_equal(plate_vsd(render(PLATE, I3, T_PLATE), T_PLATE + [0.2, 0.0, 0.0]), ONES)


def test_vsd_partial_overlap():
    # Visible: gt columns 26–37, est 30–41 (its columns 38–41 have no test
    # depth, so count as visible); same depth where both are: 1 − 96/192.
    assert np.allclose(plate_vsd(render(PLATE, I3, T_PLATE)), 0.5)


def test_vsd_depth_offset_against_tau():
    # A 1 × 1 m wall filling a narrow camera's view; the estimate is s further
    # (or nearer). Union = intersection = every pixel, whose distances differ
    # by s·‖(x̂, ŷ, 1)‖ ∈ [s, 1.02 s]: with s = 0.225 · diameter every pixel
    # costs 1 for τ ≤ 0.2 and 0 for τ ≥ 0.25.
    camera = Camera(200.0, 200.0, 31.5, 23.5, 64, 48)
    wall = trimesh.creation.box(extents=(1.0, 1.0, 0.1))
    diameter = float(np.sqrt(2.01))
    t_gt = np.array([0.0, 0.0, 0.5])
    depth_test = render(wall, I3, t_gt, camera)
    assert (depth_test > 0).all()
    expected = (BOP_VSD_TAUS < 0.225).astype(float)
    assert expected.tolist() == [1, 1, 1, 1, 0, 0, 0, 0, 0, 0]
    for s in (0.225 * diameter, -0.3):  # 0.3 m nearer: 0.212–0.216 of the diameter
        errors = vsd(
            I3,
            t_gt + [0, 0, s],
            I3,
            t_gt,
            depth_test,
            camera.K,
            wall.vertices,
            wall.faces,
            0.015,
            BOP_VSD_TAUS,
            diameter,
        )
        assert np.array_equal(errors, expected)


def test_vsd_occluded_pixels_follow_bop19_visibility():
    plate = render(PLATE, I3, T_PLATE)
    cols = np.arange(CAMERA.width)[None, :]
    # An occluder 30 cm away over columns ≤ 29 hides gt columns 26–29:
    # visible gt 30–37 (96 px), est 30–41 (144 px), common 30–37: 1 − 96/144.
    assert np.allclose(plate_vsd(np.where(cols <= 29, 0.3, plate)), 1 / 3)
    # Over columns ≥ 30 it hides all of the estimate: visible gt 26–29 only.
    assert np.array_equal(plate_vsd(np.where(cols >= 30, 0.3, plate)), ONES)
    # A surface 1 cm in front of the plate everywhere is within δ = 1.5 cm:
    # both stay visible, as with no occluder ...
    front = plate.max()
    assert np.allclose(plate_vsd(np.full(plate.shape, front - 0.01)), 0.5)
    # ... 3 cm in front hides everything: no visible pixel, error 1.
    assert np.array_equal(plate_vsd(np.full(plate.shape, front - 0.03)), ONES)
    # No depth measured anywhere: under bop19 every rendered pixel is visible
    # (bop18 would give 1 for every τ).
    assert np.array_equal(plate_vsd(np.zeros(plate.shape), T_PLATE), np.zeros(10))
    assert np.allclose(plate_vsd(np.zeros(plate.shape)), 0.5)


def full_image_vsd(R_est, t_est, R_gt, t_gt, depth_test, camera, mesh, delta, taus, diameter):
    """The toolkit's VSD on whole images, step by step."""
    xs, ys = np.meshgrid(np.arange(camera.width), np.arange(camera.height))

    def dist(d):
        return np.sqrt(((xs - camera.cx) / camera.fx * d) ** 2 + ((ys - camera.cy) / camera.fy * d) ** 2 + d**2)

    def visible(d_test, d_model):
        diff = d_model.astype(np.float32) - d_test.astype(np.float32)
        return ((diff <= delta) | (d_test == 0)) & (d_model > 0)

    d_test = dist(depth_test)
    d_est, d_gt = dist(render(mesh, R_est, t_est, camera)), dist(render(mesh, R_gt, t_gt, camera))
    v_gt = visible(d_test, d_gt)
    v_est = visible(d_test, d_est) | (v_gt & (d_est > 0))
    inter, union = v_gt & v_est, v_gt | v_est
    if not union.sum():
        return np.ones(len(taus))
    dists = np.abs(d_gt[inter] - d_est[inter]) / diameter
    return np.array([((dists >= tau).sum() + union.sum() - inter.sum()) / union.sum() for tau in taus])


def test_vsd_equals_the_full_image_computation():
    rng = np.random.default_rng(2)
    can = trimesh.creation.cylinder(radius=0.03, height=0.08, sections=24)
    for _ in range(4):
        R_gt, R_est = Rotation.random(2, random_state=rng).as_matrix()
        t_gt = np.array([*rng.normal(0, 0.03, 2), 0.45])
        t_est = t_gt + rng.normal(0, 0.015, 3)
        depth = render(can, R_gt, t_gt) + rng.normal(0, 0.003, (48, 64))
        depth[rng.random(depth.shape) < 0.2] = 0.0  # dropout
        depth[:, :20] = np.where(rng.random() < 0.5, 0.35, depth[:, :20])  # sometimes an occluder
        depth = np.clip(depth, 0.0, None).astype(np.float32)
        args = (R_est, t_est, R_gt, t_gt, depth)
        expected = full_image_vsd(*args, CAMERA, can, 0.015, BOP_VSD_TAUS, 0.1)
        errors = vsd(*args, K_SMALL, can.vertices, can.faces, 0.015, BOP_VSD_TAUS, 0.1)
        assert np.array_equal(errors, expected)
        assert 0.0 < errors[-1] <= errors[0] <= 1.0
