"""The compiled core's binding: its stub file matches the module, its results
are typed, and it raises edgepose's own exceptions."""

from __future__ import annotations

import ast
import dataclasses
import inspect
from pathlib import Path

import edgepose
import numpy as np
import pytest
from edgepose import _core
from edgepose.cloud import _clean_settings
from edgepose.errors import InvalidCloudError, InvalidModelError

STUB = Path(edgepose.__file__).parent / "_core.pyi"


def _stub() -> tuple[dict[str, list[str]], dict[str, dict[str, list[str] | None]]]:
    """Functions (name → parameters) and classes (name → member →
    parameters, None for properties) declared in ``_core.pyi``; a parameter
    reads ``name``, ``*name`` when keyword-only, ``**name`` for keywords
    collected, and ends in ``=`` when it has a default."""
    functions: dict[str, list[str]] = {}
    classes: dict[str, dict[str, list[str] | None]] = {}

    def parameters(node: ast.FunctionDef) -> list[str]:
        args = node.args
        positional = args.posonlyargs + args.args
        defaulted = {a.arg for a in positional[len(positional) - len(args.defaults) :]}
        defaulted |= {a.arg for a, d in zip(args.kwonlyargs, args.kw_defaults) if d is not None}
        names = [a.arg for a in positional] + [f"*{a.arg}" for a in args.kwonlyargs]
        names += [f"**{args.kwarg.arg}"] if args.kwarg else []
        return [n + ("=" if n.lstrip("*") in defaulted else "") for n in names if n != "self"]

    for node in ast.parse(STUB.read_text()).body:
        if isinstance(node, ast.FunctionDef):
            functions[node.name] = parameters(node)
        elif isinstance(node, ast.ClassDef):
            members: dict[str, list[str] | None] = {}
            for item in node.body:
                if isinstance(item, ast.FunctionDef):
                    is_property = any(isinstance(d, ast.Name) and d.id == "property" for d in item.decorator_list)
                    members[item.name] = None if is_property else parameters(item)
            classes[node.name] = members
    return functions, classes


def _runtime_parameters(obj) -> list[str]:
    """``obj``'s parameters as :func:`_stub` writes them (kind and default too)."""
    stars = {inspect.Parameter.KEYWORD_ONLY: "*", inspect.Parameter.VAR_KEYWORD: "**"}
    return [
        stars.get(p.kind, "") + p.name + ("=" if p.default is not p.empty else "")
        for p in inspect.signature(obj).parameters.values()
        if p.name != "self"
    ]


def test_the_stub_declares_exactly_the_modules_functions_and_classes():
    functions, classes = _stub()
    runtime = {name for name in dir(_core) if not name.startswith("__")}
    if not hasattr(_core, "_panic_for_tests"):  # a build without the test-hooks feature
        functions.pop("_panic_for_tests")
    assert set(functions) | set(classes) == runtime
    for name, params in functions.items():
        assert _runtime_parameters(getattr(_core, name)) == params, name


def test_the_stub_declares_each_class_member_with_its_parameters():
    _, classes = _stub()
    for class_name, members in classes.items():
        cls = getattr(_core, class_name)
        runtime = {name for name in vars(cls) if not name.startswith("__")}
        declared = {name for name in members if not name.startswith("__")}
        assert declared == runtime, class_name
        for name, params in members.items():
            if name == "__init__":
                assert _runtime_parameters(cls) == params, class_name
            elif params is None:
                assert inspect.isgetsetdescriptor(vars(cls)[name]), f"{class_name}.{name} is not a property"
            elif not name.startswith("__"):
                assert _runtime_parameters(getattr(cls, name)) == params, f"{class_name}.{name}"


def _box_model() -> _core.StandardModel:
    """A 4 × 6 × 8 cm box, 512 points."""
    import trimesh

    mesh = trimesh.creation.box(extents=(0.04, 0.06, 0.08))
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    return _core.StandardModel.from_mesh(vertices, np.asarray(mesh.faces, dtype=np.uint32), 512, 0)


def test_icp_results_are_typed_with_one_entry_per_start():
    model = _box_model()
    index = _core.ModelIndex(model)
    truth = np.array([0.01, -0.02, 0.5])
    cloud = np.ascontiguousarray(model.points + truth.astype(np.float32))
    starts_R = np.stack([np.eye(3), np.eye(3)])
    starts_t = np.array([truth + [0.004, 0, 0], truth + [0, -0.003, 0.002]])
    icp = index.refine(cloud, starts_R, starts_t, 30, 0.02)
    assert isinstance(icp, _core.IcpResults) and len(icp) == 2
    assert icp.rotations.shape == (2, 3, 3) and icp.translations.shape == (2, 3)
    assert icp.iterations.dtype == np.uint32 and icp.converged.dtype == np.bool_
    assert (icp.inliers > 400).all() and (icp.rmse < 1e-3).all()
    np.testing.assert_allclose(icp.translations, [truth, truth], atol=1e-4)
    with pytest.raises(AttributeError):
        icp.rmse = np.zeros(2)  # frozen
    split = index.refine(cloud, starts_R, starts_t, 30, 0.02, two_cores=True)
    for name in ("rotations", "translations", "iterations", "converged", "inliers", "rmse"):
        np.testing.assert_array_equal(getattr(split, name), getattr(icp, name))
    second = icp.row(1)
    assert len(second) == 1
    for name in ("rotations", "translations", "iterations", "converged", "inliers", "rmse"):
        np.testing.assert_array_equal(getattr(second, name), getattr(icp, name)[1:])
    with pytest.raises(IndexError, match="ICP result 2 asked for, but there are 2"):
        icp.row(2)
    # A finer convergence (the symmetry search's) takes more iterations, a
    # coarse one stops at the first update.
    fine = index.refine(cloud, starts_R, starts_t, 30, 0.02, converged=1e-9)
    coarse = index.refine(cloud, starts_R, starts_t, 30, 0.02, converged=1.0)
    assert (fine.iterations > icp.iterations).all() and (coarse.iterations == 1).all() and coarse.converged.all()


def test_the_model_is_built_once_and_shared_by_maps_and_index():
    model = _box_model()
    assert len(model) == 512 and model.points.shape == (512, 3) and model.centre.shape == (3,)
    assert 0.1 < model.diameter < 0.11 and model.scale == pytest.approx(1 / np.linalg.norm(model.points, axis=1).max())
    rotations = edgepose.fibonacci_viewpoints(4).rotations
    maps, centroids, visible = _core.compute_maps(model, rotations, 64)
    assert maps.shape == (4, 64, 3) and centroids.shape == (4, 3) and (visible > 0).all()
    assert len(_core.ModelIndex(model)) == 512


def test_an_index_with_other_normals_answers_as_one_built_for_them():
    model = _box_model()
    index = _core.ModelIndex(model)
    # The same points with other normals.
    rng = np.random.default_rng(0)
    normals = model.normals + rng.normal(0, 0.05, model.normals.shape).astype(np.float32)
    normals = np.ascontiguousarray(normals / np.linalg.norm(normals, axis=1, keepdims=True), dtype=np.float32)
    tilted = _core.StandardModel(model.points, normals, model.centre, model.scale, model.diameter, model.spacing)
    shared, fresh = index.with_model(tilted), _core.ModelIndex(tilted)
    points = np.ascontiguousarray(model.points[::4] + rng.normal(0, 0.003, (128, 3)).astype(np.float32))
    R = np.stack([np.eye(3), edgepose.fibonacci_viewpoints(3).rotations[1]])
    t = np.array([[0.0, 0.0, 0.0], [0.002, 0.0, -0.001]])
    np.testing.assert_array_equal(shared.distances(points, R, t, True), fresh.distances(points, R, t, True))
    assert not np.array_equal(shared.distances(points, R, t, True), index.distances(points, R, t, True))
    moved = _core.StandardModel(
        model.points + np.float32(1e-6), model.normals, model.centre, model.scale, model.diameter, model.spacing
    )
    with pytest.raises(ValueError, match="points differ"):
        index.with_model(moved)


def test_the_core_raises_edgeposes_own_exceptions():
    model = _box_model()
    index = _core.ModelIndex(model)
    eye = np.eye(3)[None]
    with pytest.raises(InvalidCloudError, match=r"cloud must have shape \(N, 3\)"):
        index.refine(np.zeros((5, 2), np.float32), eye, np.zeros((1, 3)), 5, 0.01)
    with pytest.raises(InvalidCloudError, match="observed"):
        index.align_translations(np.zeros((5, 4), np.float32), eye, np.zeros((1, 3)), 1, 0.01)
    with pytest.raises(InvalidCloudError, match=r"cloud must have shape \(N, 3\)"):
        index.pair_poses(np.zeros((5, 2), np.float32), 192, 2, 8)
    with pytest.raises(ValueError, match="positive"):
        index.pair_poses(np.zeros((50, 3), np.float32), 0, 2, 8)
    # Degenerate clouds (one point repeated, NaNs) vote for nothing rather than fail.
    for cloud in (np.full((50, 3), 0.5, np.float32), np.full((50, 3), np.nan, np.float32)):
        rotations, translations, votes = index.pair_poses(cloud, 192, 2, 8)
        assert rotations.shape == (0, 3, 3) and translations.shape == (0, 3) and votes.shape == (0,)
    with pytest.raises(InvalidModelError, match=r"lid\.obj: .*zero surface area"):
        flat = np.zeros((3, 3))
        _core.StandardModel.from_mesh(flat, np.array([[0, 1, 2]], np.uint32), 64, 0, source="lid.obj")
    with pytest.raises(InvalidModelError, match="non-empty"):
        _core.StandardModel(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros(3), 1.0, 1.0, 0.1)
    with pytest.raises(InvalidCloudError, match="empty"):
        _core.normalize_to_map(np.zeros((0, 3), np.float32), 1.0, 16)
    with pytest.raises(ValueError, match="spacing"):
        _core.DepthGrid(np.zeros((4, 3), np.float32), float("nan"))
    with pytest.raises(InvalidCloudError, match=r"shape \(N, 3\)"):
        _core.DepthGrid(np.zeros((4, 2), np.float32), 0.01)
    with pytest.raises(InvalidCloudError, match="valid points"):
        _core.clean_cloud(np.full((40, 3), np.nan), 0.1, _clean_settings(2048))
    with pytest.raises(InvalidCloudError, match="mask shape"):
        _core.clean_depth_cloud(np.ones((4, 4)), np.ones((4, 5), bool), np.eye(3), 1.0, 0.1, _clean_settings(2048))
    with pytest.raises(ValueError, match="reference 2"):
        index.pose_distances(np.eye(3)[None].repeat(2, 0), np.zeros((2, 3)), 2, False, 64)


def test_segmentation_defaults_come_from_the_core_and_every_field_reaches_it():
    core = _core.SegmentSettings()
    python = edgepose.SegmentSettings()
    for name, value in dataclasses.asdict(python).items():
        assert getattr(core, name) == value, name
    changed = edgepose.SegmentSettings(shadow_spacings=1.5, ramp_neighbours=7, steep_faces=False).core()
    assert (changed.shadow_spacings, changed.ramp_neighbours, changed.steep_faces) == (1.5, 7, False)
    with pytest.raises(TypeError, match='no field "shadow"'):
        _core.SegmentSettings(shadow=1.0)
    settings = edgepose.EstimateSettings().with_(**{"segmentation.shadow_spacings": 2.0, "retrieve.k": 8})
    assert settings.segmentation.shadow_spacings == 2.0 and settings.retrieve.k == 8
    assert settings.flat()["segmentation.shadow_spacings"] == 2.0
