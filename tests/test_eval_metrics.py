"""Pose error metrics against hand-computed values and scipy."""

from __future__ import annotations

import numpy as np
import pytest
from edgepose.eval import (
    PoseErrors,
    add,
    add_or_s,
    add_s,
    auc,
    pose_errors,
    rotation_error_deg,
    translation_error_mm,
)
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

#: Three points 10 cm along each axis of the object frame.
AXES = 0.1 * np.eye(3)


def pose(R: np.ndarray = np.eye(3), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def random_poses(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    rotations = Rotation.random(n, random_state=rng).as_matrix()
    return [pose(R, rng.normal(0, 0.05, 3) + [0, 0, 0.7]) for R in rotations]


def prism(sides: int = 12, radius: float = 0.04, height: float = 0.1, rings: int = 5) -> np.ndarray:
    """Vertices of regular polygons stacked along z: symmetric under a turn of 2π/sides about z."""
    angles = 2 * np.pi * np.arange(sides) / sides
    ring = np.column_stack([radius * np.cos(angles), radius * np.sin(angles)])
    heights = np.linspace(-height / 2, height / 2, rings)
    return np.concatenate([np.column_stack([ring, np.full(sides, z)]) for z in heights])


def test_identity_pose_has_zero_error(rng):
    points = rng.normal(0, 0.05, (500, 3))
    T = random_poses(rng, 1)[0]
    assert add(points, T, T) == 0.0
    assert add_s(points, T, T) < 1e-12  # the relative pose is the identity up to rounding
    errors = pose_errors(points, T, T, diameter=0.2, symmetric=False)
    assert errors.rotation_deg == pytest.approx(0.0, abs=1e-6)
    assert errors.translation_mm == 0.0


def test_translation_offset_is_the_add(rng):
    points = rng.normal(0, 0.05, (300, 3))
    T_gt = random_poses(rng, 1)[0]
    T_est = T_gt.copy()
    T_est[:3, 3] += [0.003, -0.004, 0.0]  # 5 mm
    assert add(points, T_est, T_gt) == pytest.approx(0.005, rel=1e-9)
    assert translation_error_mm(T_est[:3, 3], T_gt[:3, 3]) == pytest.approx(5.0, rel=1e-9)


def test_quarter_turn_of_three_axis_points_by_hand():
    # Rz(90°): x → y, y → −x, z fixed. Moved distances: 0.1√2, 0.1√2, 0.
    T_est = pose(Rotation.from_euler("z", 90, degrees=True).as_matrix(), [0, 0, 0.5])
    T_gt = pose(t=[0, 0, 0.5])
    assert add(AXES, T_est, T_gt) == pytest.approx(2 * 0.1 * np.sqrt(2) / 3, rel=1e-12)
    # Closest estimated points: x's is y's image (0.1√2 away); y and z are matched exactly.
    assert add_s(AXES, T_est, T_gt) == pytest.approx(0.1 * np.sqrt(2) / 3, rel=1e-12)
    assert rotation_error_deg(T_est[:3, :3], T_gt[:3, :3]) == pytest.approx(90.0, abs=1e-9)


def test_add_s_never_exceeds_add(rng):
    points = rng.normal(0, 0.05, (400, 3))
    for T_est, T_gt in zip(random_poses(rng, 50), random_poses(rng, 50)):
        assert add_s(points, T_est, T_gt) <= add(points, T_est, T_gt) + 1e-12


def test_half_turn_about_symmetry_axis_is_free_for_add_s_only():
    points = prism(sides=12, radius=0.04)
    T_gt = pose(Rotation.from_euler("xy", [30, -50], degrees=True).as_matrix(), [0.05, 0.0, 0.6])
    T_est = T_gt @ pose(Rotation.from_euler("z", 180, degrees=True).as_matrix())
    assert add_s(points, T_est, T_gt) < 1e-12
    assert add(points, T_est, T_gt) == pytest.approx(2 * 0.04, rel=1e-9)  # every point crosses a diameter
    assert add_or_s(points, T_est, T_gt, symmetric=True) < 1e-12
    assert add_or_s(points, T_est, T_gt, symmetric=False) == pytest.approx(0.08, rel=1e-9)


@pytest.mark.parametrize("n", [1, 511, 512, 513, 3000])
def test_add_s_matches_kd_tree(rng, n):
    points = rng.normal(0, 0.05, (n, 3))
    T_est, T_gt = random_poses(rng, 2)
    est = points @ T_est[:3, :3].T + T_est[:3, 3]
    gt = points @ T_gt[:3, :3].T + T_gt[:3, 3]
    expected = cKDTree(est).query(gt)[0].mean()
    assert add_s(points, T_est, T_gt) == pytest.approx(expected, rel=1e-9)


def test_rotation_error_of_known_rotations():
    R_gt = Rotation.from_euler("zyx", [10, 20, 30], degrees=True).as_matrix()
    axis = np.array([1.0, 2.0, -2.0]) / 3.0
    for angle in (30.0, 0.5, 179.9):
        R_est = Rotation.from_rotvec(np.radians(angle) * axis).as_matrix() @ R_gt
        assert rotation_error_deg(R_est, R_gt) == pytest.approx(angle, abs=1e-6)
        assert rotation_error_deg(R_gt, R_est) == pytest.approx(angle, abs=1e-6)
    # A slightly non-orthonormal matrix (trace above 3) is clipped, not NaN.
    assert rotation_error_deg(np.eye(3) * (1 + 1e-12), np.eye(3)) == 0.0


def test_auc_extremes_and_hand_computed_example():
    assert auc(np.zeros(10)) == pytest.approx(1.0)
    assert auc([0.11, 0.5, np.inf, np.nan]) == 0.0
    # Errors 2 cm, 4 cm, 20 cm (a failure), n = 3: the PoseCNN sum is
    # 0.02·1/3 + 0.02·2/3 + (0.1 − 0.04)·2/3 = 0.06, over 0.1.
    assert auc([0.04, 0.2, 0.02]) == pytest.approx(0.6, rel=1e-12)
    # The same with a 5 cm range: 0.02·1/3 + 0.02·2/3 + 0.01·2/3 = 0.02667, over 0.05.
    assert auc([0.04, 0.2, 0.02], max_threshold=0.05) == pytest.approx((0.02 + 0.01 * 2 / 3) / 0.05, rel=1e-12)


def test_auc_of_many_errors_approaches_the_area_under_the_curve(rng):
    # Uniform errors on [0, 0.2]: accuracy(x) = x / 0.2 on [0, 0.1], area 0.25 of 0.1 × 1.
    errors = rng.uniform(0, 0.2, 200_000)
    assert auc(errors) == pytest.approx(0.25, abs=2e-3)


def test_auc_rejects_nonsense():
    with pytest.raises(ValueError, match="at least one"):
        auc([])
    with pytest.raises(ValueError, match="non-negative"):
        auc([0.01, -0.01])


def test_pose_errors_and_correctness_threshold():
    points = prism(sides=8, radius=0.05)
    diameter = float(np.linalg.norm([0.1, 0.1]))  # 2 × hypot(radius, height / 2): 14.1 cm
    T_gt = pose(t=[0.0, 0.0, 0.6])
    T_est = T_gt @ pose(Rotation.from_euler("z", 45, degrees=True).as_matrix(), [0.0, 0.0, 0.012])
    errors = pose_errors(points, T_est, T_gt, diameter=diameter, symmetric=True)
    assert isinstance(errors, PoseErrors)
    # An eighth of a turn maps the octagonal prism onto itself: only the 12 mm shift remains.
    assert errors.add_s == pytest.approx(0.012, rel=1e-9)
    assert errors.add == pytest.approx(np.hypot(2 * 0.05 * np.sin(np.pi / 8), 0.012), rel=1e-9)
    assert errors.add_or_s == errors.add_s
    assert errors.rotation_deg == pytest.approx(45.0)
    assert errors.translation_mm == pytest.approx(12.0)
    assert errors.correct_add_s and errors.correct_add_or_s  # 12 mm < 14.1 mm
    asymmetric = pose_errors(points, T_est, T_gt, diameter=diameter, symmetric=False)
    assert asymmetric.add_or_s == asymmetric.add and not asymmetric.correct_add_or_s  # 40 mm


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        add(np.zeros((5, 2)), np.eye(4), np.eye(4))
    with pytest.raises(ValueError, match=r"\(4, 4\)"):
        add_s(AXES, np.eye(3), np.eye(4))
