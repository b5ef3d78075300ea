"""Symmetry detection (edgepose.symmetry) on meshes made here and on the
shared YCB meshes, stored in codebooks, carried by poses and used by ADD(-S)."""

from __future__ import annotations

import json

import edgepose
import numpy as np
import pytest
import trimesh
from edgepose import detect_symmetry, load_model
from edgepose.codebook import Codebook, CodebookError
from edgepose.eval import YCB_SYMMETRIC, add_s, pose_errors
from edgepose.symmetry import NO_SYMMETRY, Symmetry


def placed(mesh: trimesh.Trimesh, seed: int) -> tuple[trimesh.Trimesh, np.ndarray]:
    """``mesh`` turned and moved at random (metres), and the transform used."""
    rng = np.random.default_rng(seed)
    T = trimesh.transformations.random_rotation_matrix(rng.random(3))
    T[:3, 3] = rng.uniform(-0.2, 0.2, 3)
    return mesh.copy().apply_transform(T), T


def angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def maps_onto_itself(symmetry: Symmetry, mesh: trimesh.Trimesh) -> float:
    """Largest ADD-S (metres) of the mesh's points under every turn of the group."""
    points = load_model(mesh).mesh_points
    return max(add_s(points, T, np.eye(4)) for T in symmetry.transforms(steps=12))


def test_cylinder_has_a_continuous_axis_and_a_flip():
    mesh, T = placed(trimesh.creation.cylinder(radius=0.03, height=0.12, sections=64), seed=1)
    s = detect_symmetry(load_model(mesh))
    assert len(s.continuous) == 1 and len(s.discrete) == 1
    axis, point = s.continuous[0, :3], s.continuous[0, 3:]
    assert abs(axis @ T[:3, 2]) > np.cos(np.radians(1.0))  # the cylinder's z, turned
    assert np.linalg.norm(np.cross(point - T[:3, 3], T[:3, 2])) < 1e-3  # the line passes through its centre
    assert angle_deg(s.discrete[0][:3, :3]) == pytest.approx(180, abs=1.0)
    assert maps_onto_itself(s, mesh) < 2e-3
    assert s.symmetric and "continuous" in s.describe()


def test_cone_has_a_continuous_axis_only():
    mesh, T = placed(trimesh.creation.cone(radius=0.04, height=0.1, sections=64), seed=2)
    s = detect_symmetry(load_model(mesh))
    assert len(s.continuous) == 1 and len(s.discrete) == 0
    assert abs(s.continuous[0, :3] @ T[:3, 2]) > np.cos(np.radians(1.0))


def test_box_has_three_half_turns_about_its_face_normals():
    mesh, T = placed(trimesh.creation.box([0.05, 0.1, 0.2]), seed=3)
    s = detect_symmetry(load_model(mesh))
    assert len(s.continuous) == 0 and len(s.discrete) == 3
    for turn in s.discrete:
        assert angle_deg(turn[:3, :3]) == pytest.approx(180, abs=1.0)
        w, v = np.linalg.eig(turn[:3, :3])
        axis = np.real(v[:, np.argmin(np.abs(w - 1))])
        assert max(abs(axis @ T[:3, k]) for k in range(3)) > np.cos(np.radians(1.0))
    assert maps_onto_itself(s, mesh) < 2e-3


def test_square_prism_and_cube_groups_are_complete():
    square = detect_symmetry(load_model(placed(trimesh.creation.box([0.05, 0.05, 0.2]), seed=4)[0]))
    cube = detect_symmetry(load_model(placed(trimesh.creation.box([0.1, 0.1, 0.1]), seed=5)[0]))
    assert len(square.discrete) == 7  # the dihedral group of order 8, identity aside
    assert len(cube.discrete) == 23  # the cube's 24 turns


def test_asymmetric_parts_have_none(drill):
    mesh, codebook = drill
    assert not detect_symmetry(codebook.model).symmetric
    # A box with a peg off-centre on one face: no turn maps it onto itself.
    peg = trimesh.creation.box([0.02, 0.02, 0.03])
    peg.apply_translation([0.03, 0.02, 0.065])
    lopsided = trimesh.util.concatenate([trimesh.creation.box([0.1, 0.08, 0.1]), peg])
    assert not detect_symmetry(load_model(lopsided)).symmetric


def test_near_turns_are_found_where_a_small_detail_breaks_a_symmetry():
    """The box with a small peg is no symmetric object, but its half turns
    move only the peg: near turns, each kept within NEAR_MEAN_DIAMETERS of
    the surface and none a symmetry. Exact symmetries leave none."""
    from edgepose.symmetry import NEAR_MEAN_DIAMETERS, doubtful_turns

    peg = trimesh.creation.box([0.02, 0.02, 0.03])
    peg.apply_translation([0.03, 0.02, 0.065])
    model = load_model(trimesh.util.concatenate([trimesh.creation.box([0.1, 0.08, 0.1]), peg]))
    s = detect_symmetry(model)
    assert not s.symmetric and 1 <= len(s.near) and "near turn" in s.describe()
    points = model.mesh_points
    for T in s.near:
        assert angle_deg(T[:3, :3]) > 30
        # The turned points stay near the surface (ADD-S), though the pose differs (ADD).
        assert add_s(points, T, np.eye(4)) <= 1.5 * NEAR_MEAN_DIAMETERS * model.diameter
        assert pose_errors(points, T, np.eye(4), model.diameter, False).add > 0.1 * model.diameter
    # Tested by the confidence: the near turns, then the principal half turns
    # not among them (model frame).
    rotations, translations = doubtful_turns(model, s)
    assert len(s.near) <= len(rotations) <= 3 + len(s.near) and translations.shape == (len(rotations), 3)
    assert np.allclose(rotations[0], s.near[0][:3, :3])
    # A long box with a small peg: its near turns are its half turns about the principal axes.
    peg = trimesh.creation.box([0.015, 0.015, 0.015])
    peg.apply_translation([0.015, 0.025, 0.0875])
    long_box = load_model(trimesh.util.concatenate([trimesh.creation.box([0.06, 0.1, 0.16]), peg]))
    s = detect_symmetry(long_box)
    assert len(s.near) == 3 and len(doubtful_turns(long_box, s)[0]) == 3
    for exact in (
        trimesh.creation.box([0.06, 0.1, 0.16]),
        trimesh.creation.cylinder(0.03, 0.12),
        trimesh.creation.icosphere(subdivisions=3, radius=0.05),  # every turn a symmetry
    ):
        assert len(detect_symmetry(load_model(exact)).near) == 0


def test_near_turns_are_sought_about_axes_that_are_neither_principal_nor_normal():
    """A cube with an off-centre peg: its 120° turns about the body
    diagonals move only the peg, so a view of the cube's other faces cannot
    tell them from the pose. A diagonal is no principal axis (the peg sets
    those) and no face normal, the axes the symmetry probes try; the near
    turns' spread axes find it."""
    from edgepose.symmetry import NEAR_MEAN_DIAMETERS, rotation_axis

    peg = trimesh.creation.box([0.015, 0.015, 0.015])
    peg.apply_translation([0.02, 0.01, 0.055])
    model = load_model(trimesh.util.concatenate([trimesh.creation.box([0.1, 0.1, 0.1]), peg]))
    s = detect_symmetry(model)
    diagonals = np.array([[1, 1, 1], [1, 1, -1], [1, -1, 1], [-1, 1, 1]]) / np.sqrt(3)
    about_a_diagonal = [
        T
        for T in s.near
        if abs(angle_deg(T[:3, :3]) - 120) < 5
        and np.abs(diagonals @ rotation_axis(T[:3, :3])).max() > np.cos(np.radians(5))
    ]
    assert not s.symmetric and about_a_diagonal, s.describe()
    for T in about_a_diagonal:
        assert add_s(model.mesh_points, T, np.eye(4)) <= 1.5 * NEAR_MEAN_DIAMETERS * model.diameter


def test_shared_ycb_meshes_match_the_hand_list(ycb_dir):
    for path in sorted(ycb_dir.glob("*.ply")):
        s = detect_symmetry(load_model(path))
        assert s.symmetric == (path.stem in YCB_SYMMETRIC), (path.stem, s.describe())
    assert len(detect_symmetry(load_model(ycb_dir / "master_chef_can.ply")).continuous) == 1
    assert len(detect_symmetry(load_model(ycb_dir / "cracker_box.ply")).discrete) == 3


def test_codebook_stores_and_checks_its_symmetry(tmp_path):
    mesh, _ = placed(trimesh.creation.cylinder(radius=0.03, height=0.1, sections=48), seed=6)
    book = edgepose.build_codebook(mesh, views=60)
    assert book.symmetry.symmetric and "symmetry" in book.timings
    book.save(tmp_path / "can.codebook")
    loaded = Codebook.load(tmp_path / "can.codebook")
    assert np.allclose(loaded.symmetry.continuous, book.symmetry.continuous, atol=1e-6)
    assert np.allclose(loaded.symmetry.discrete, book.symmetry.discrete, atol=1e-6)
    assert np.allclose(loaded.symmetry.near, book.symmetry.near, atol=1e-6)
    # A pose carries the codebook's symmetries.
    view = edgepose.eval.render_view(mesh, seed=3)
    pose = edgepose.estimate(view.cloud, book, k=4)
    assert pose.ambiguous and pose.symmetry is book.symmetry
    assert pose_errors(book.model.mesh_points, pose.matrix, view.T_cam_obj, book.model.diameter, True).correct_add_or_s


def test_malformed_symmetries_are_rejected():
    with pytest.raises(ValueError, match="rigid turn"):
        Symmetry.from_json({"discrete": [list(np.eye(4).ravel() * 2)], "continuous": []})
    with pytest.raises(ValueError, match="unit vector"):
        Symmetry.from_json({"discrete": [], "continuous": [[0, 0, 2, 0, 0, 0]]})
    with pytest.raises(ValueError, match="NaN"):
        Symmetry.from_json({"discrete": [], "continuous": [[0, 0, float("nan"), 0, 0, 0]]})
    with pytest.raises(ValueError, match="near turn is not a rigid turn"):
        Symmetry.from_json({"discrete": [], "continuous": [], "near": [list(np.eye(4).ravel() * 2)]})
    assert Symmetry.from_json(json.loads(json.dumps(NO_SYMMETRY.to_json()))).describe() == "none"
    assert len(Symmetry.from_json({"discrete": [], "continuous": []}).near) == 0


def test_a_codebook_with_a_corrupt_symmetry_entry_does_not_load(tmp_path, drill):
    from edgepose.codebook import _checksum

    _, book = drill
    tensors = book._tensors()
    metadata = book._metadata(tensors)
    metadata["symmetry"] = json.dumps({"discrete": [[1.0] * 16], "continuous": []})
    metadata["checksum"] = _checksum(tensors, metadata)
    with pytest.raises(CodebookError, match="rigid turn"):
        Codebook._from_parts(tensors, metadata, edgepose.encoder.default_encoder(), "bad.codebook")


def test_turns_exactly_the_limit_apart_are_apart_whichever_way_the_arithmetic_rounds():
    from edgepose.symmetry import NEAR_MIN_ANGLE_DEG, _apart
    from edgepose.views import rotation_about

    axes = np.random.default_rng(0).normal(size=(300, 3))
    for axis in axes / np.linalg.norm(axes, axis=1, keepdims=True):
        for a, b in ((30, 60), (60, 90), (150, 180), (0, 30)):
            Ra, Rb = rotation_about(axis, np.radians(a)), rotation_about(axis, np.radians(b))
            assert _apart(Ra, Rb, NEAR_MIN_ANGLE_DEG) and _apart(Rb, Ra, NEAR_MIN_ANGLE_DEG)
        assert not _apart(np.eye(3), rotation_about(axis, np.radians(29.9)), NEAR_MIN_ANGLE_DEG)


@pytest.mark.parametrize("file, flips", [("cycloidal.ply", 0), ("cylinder.stl", 1), ("torus.STL", 1)])
def test_a_continuous_symmetry_has_at_most_a_flip_besides(file, flips):
    """A gear-like disc turned by about a tooth and tilted 8° fits loosely;
    it is no symmetry (it made 16 "discrete turns"). A cylinder's flip stays."""
    from conftest import SHARED_DATA
    from edgepose.model import read_mesh

    path = SHARED_DATA / "train_shapes" / "cad" / file
    if not path.is_file():
        pytest.skip(f"shared training mesh not found at {path}")
    mesh = read_mesh(path, scale=None)
    mesh.apply_scale(0.15 / np.linalg.norm(mesh.extents))
    s = detect_symmetry(load_model(mesh))
    assert len(s.continuous) == 1 and len(s.discrete) == flips, s.describe()
    axis = s.continuous[0, :3]
    for T in s.discrete:
        assert axis @ T[:3, :3] @ axis < -0.999, s.describe()
