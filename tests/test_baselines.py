"""The peer baselines (optional ``baselines`` extra): each recovers the pose
of a rendered view of a real YCB mesh, in the original mesh frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("open3d")
pytest.importorskip("cv2")

import edgepose  # noqa: E402
from edgepose.errors import InvalidCloudError  # noqa: E402
from edgepose.eval import pose_errors, render_view  # noqa: E402
from edgepose.eval.baselines import (  # noqa: E402
    NO_POSE,
    Open3DBaseline,
    OpenCVPPFBaseline,
    PoseMethod,
)
from edgepose.model import read_mesh  # noqa: E402

SEEDS = (0, 1, 2)
#: Moves the mesh origin well away from the object, so a pose returned in the
#: centred model frame instead of the mesh frame fails by ~25 cm.
ORIGIN_SHIFT = np.array([0.2, -0.1, 0.1])


@pytest.fixture(scope="module")
def drill(ycb_dir: Path):
    """The power drill (asymmetric), its origin shifted, its metric points
    (mesh frame, metres) and diameter, and three rendered views."""
    mesh = read_mesh(ycb_dir / "power_drill.ply")
    mesh.apply_translation(ORIGIN_SHIFT)
    model = edgepose.load_model(mesh)
    points = model.mesh_points
    views = [render_view(mesh, seed=s) for s in SEEDS]
    return mesh, points, model.diameter, views


@pytest.fixture(scope="module", params=["open3d", "opencv-ppf"])
def method(request, drill) -> PoseMethod:
    mesh = drill[0]
    m = Open3DBaseline() if request.param == "open3d" else OpenCVPPFBaseline()
    m.prepare(mesh)
    return m


def test_baseline_recovers_rendered_pose(method: PoseMethod, drill) -> None:
    _, points, diameter, views = drill
    correct = 0
    for view in views:
        T = method.estimate(view.cloud)
        assert T.shape == (4, 4) and T.dtype == np.float64
        np.testing.assert_allclose(T[3], [0, 0, 0, 1])
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6)
        errors = pose_errors(points, T, view.T_cam_obj, diameter, symmetric=False)
        correct += errors.correct_add_s
    assert correct >= 2, f"{method.name}: {correct}/3 views within ADD-S < 0.1 × diameter"


def test_baseline_satisfies_protocol(method: PoseMethod) -> None:
    assert isinstance(method, PoseMethod)
    assert isinstance(method.name, str) and method.name


def test_too_few_points_gives_no_pose(method: PoseMethod) -> None:
    cloud = np.array([[0.0, 0.0, 0.5], [0.01, 0.0, 0.5], [0.0, 0.01, 0.5]])
    np.testing.assert_array_equal(method.estimate(cloud), NO_POSE)


def test_non_finite_points_are_dropped(method: PoseMethod, drill) -> None:
    _, points, diameter, views = drill
    cloud = views[0].cloud.copy()
    cloud[::50] = np.nan
    T = method.estimate(cloud)
    assert np.isfinite(T).all()


def test_wrong_cloud_shape_raises(method: PoseMethod) -> None:
    with pytest.raises(InvalidCloudError):
        method.estimate(np.zeros((100, 2)))


def test_estimate_before_prepare_raises() -> None:
    with pytest.raises(RuntimeError, match="prepare"):
        Open3DBaseline().estimate(np.zeros((100, 3)))
