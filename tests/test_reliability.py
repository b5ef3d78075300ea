"""Reliability (issue 7): bad input gets a typed error, a Rust panic is an
exception, saves survive SIGKILL, poses are bit-identical across threads and
processes, and huge clouds cost bounded memory."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import tracemalloc
from concurrent.futures import ThreadPoolExecutor

import edgepose
import numpy as np
import pytest
import trimesh
from edgepose import _core
from edgepose.cloud import MIN_POINTS, as_cloud, clean_cloud
from edgepose.errors import InternalError
from edgepose.eval import pose_errors, render_view
from safetensors.numpy import load_file


@pytest.fixture(scope="module")
def view(drill):
    return render_view(drill[0], seed=4)


@pytest.fixture(scope="module")
def reference_pose(drill, view):
    return edgepose.estimate(view.cloud, drill[1])


# --- Rust panics ---------------------------------------------------------------------


@pytest.mark.parametrize("where", ["attached", "detached", "rayon"])
def test_a_rust_panic_is_an_edgepose_error_and_the_process_goes_on(drill, view, reference_pose, where):
    if not hasattr(_core, "_panic_for_tests"):
        pytest.skip("core built without the test-hooks feature (`make build` turns it on)")
    with pytest.raises(InternalError, match=r"\(Rust panic\): deliberate") as caught:
        _core._panic_for_tests("deliberate", where)
    assert isinstance(caught.value, edgepose.EdgePoseError) and isinstance(caught.value, Exception)
    # The core still works afterwards, with the same answer.
    assert np.array_equal(edgepose.estimate(view.cloud, drill[1]).matrix, reference_pose.matrix)


# --- clouds --------------------------------------------------------------------------


def test_any_memory_layout_and_nan_rows_give_the_identical_pose(drill, view, reference_pose):
    _, codebook = drill
    cloud = view.cloud
    wide = np.zeros((len(cloud), 6))
    wide[:, ::2] = cloud
    rng = np.random.default_rng(0)
    at = np.sort(rng.choice(len(cloud), 300, replace=False))
    junk = np.array([[np.nan, 0, 0], [0, np.inf, 0], [0, 0, -np.inf], [1e12, 0, 0]])[rng.integers(0, 4, 300)]
    with_junk = np.insert(cloud, at, junk, axis=0)
    fortran, strided = np.asfortranarray(cloud), wide[:, ::2]
    assert not fortran.flags.c_contiguous and not strided.flags.c_contiguous
    for variant in (fortran, strided, with_junk):
        pose = edgepose.estimate(variant, codebook)
        assert np.array_equal(pose.matrix, reference_pose.matrix)


def test_float32_and_integer_clouds_are_accepted(drill, view, reference_pose):
    _, codebook = drill
    as_f32 = edgepose.estimate(view.cloud.astype(np.float32), codebook)
    np.testing.assert_allclose(as_f32.matrix, reference_pose.matrix, atol=1e-3)
    integers = np.round(view.cloud * 1000).astype(np.int32)  # e.g. a sensor's raw millimetres
    assert np.array_equal(as_cloud(integers), integers.astype(np.float64))
    with pytest.raises(edgepose.InvalidCloudError, match="millimetres"):
        edgepose.estimate(integers, codebook)  # the units mistake is reported, not guessed
    metres = edgepose.estimate((integers / 1000).astype(np.float64), codebook)
    np.testing.assert_allclose(metres.matrix, reference_pose.matrix, atol=5e-3)


@pytest.mark.parametrize(
    "cloud, message",
    [
        (np.ones((100, 3), dtype=bool), "dtype bool"),
        (np.ones((100, 3), dtype=complex), "dtype complex128"),
        (np.array([[object()] * 3] * 100), "dtype object"),
        (np.array([["1", "2", "3"]] * 100), "dtype <U1"),
        (np.zeros(300), r"shape \(N, 3\), got \(300,\)"),
        (np.zeros((100, 4)), r"got \(100, 4\)"),
        (np.zeros((10, 10, 3)), r"reshape\(-1, 3\)"),
        ([[0.0, 0.0], [1.0]], "not array-like"),
        (np.zeros((0, 3)), f"0 valid points of 0 .*at least {MIN_POINTS}"),
        (np.full((500, 3), np.nan), "0 valid points of 500"),
        (np.full((500, 3), 1e300), "0 valid points of 500"),
    ],
)
def test_bad_clouds_name_the_problem(drill, cloud, message):
    with pytest.raises(edgepose.InvalidCloudError, match=message):
        edgepose.estimate(cloud, drill[1])


def test_too_few_points_coincident_points_and_wrong_units(drill, view):
    _, codebook = drill
    with pytest.raises(edgepose.InvalidCloudError, match=f"{MIN_POINTS - 1} valid points"):
        edgepose.estimate(view.cloud[: MIN_POINTS - 1], codebook)
    assert edgepose.estimate(view.cloud[:: len(view.cloud) // MIN_POINTS][:MIN_POINTS], codebook).matrix.shape == (4, 4)
    with pytest.raises(edgepose.InvalidCloudError, match="coincide"):
        edgepose.estimate(np.tile(view.cloud[:1], (500, 1)), codebook)
    with pytest.raises(edgepose.InvalidCloudError, match="other units"):
        edgepose.estimate(view.cloud / 1000.0, codebook)  # kilometres


def test_millions_of_points_are_subsampled_in_bounded_memory(drill, view):
    _, codebook = drill
    huge = np.tile(view.cloud.astype(np.float32), (400, 1))  # ~4 M points, 48 MB
    tracemalloc.start()
    try:
        points = as_cloud(huge, max_points=2048)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert points.shape == (2048, 3) and points.dtype == np.float64
    assert peak < 8_000_000, f"peak {peak / 1e6:.1f} MB while cleaning a {huge.nbytes / 1e6:.0f} MB cloud"
    pose = edgepose.estimate(huge, codebook)
    model_points = codebook.model.points + codebook.model.centre
    e = pose_errors(model_points, pose.matrix, view.T_cam_obj, codebook.model.diameter, symmetric=False)
    assert e.correct_add_or_s


# --- meshes --------------------------------------------------------------------------


def test_unusable_meshes_raise_model_errors(tmp_path):
    empty = tmp_path / "empty.ply"
    empty.write_bytes(b"")
    with pytest.raises(edgepose.MeshLoadError, match="empty.ply"):
        edgepose.load_model(empty)
    points_only = tmp_path / "points.ply"
    trimesh.PointCloud(np.random.default_rng(0).random((50, 3))).export(points_only)
    with pytest.raises(edgepose.MeshLoadError, match="no triangle mesh"):
        edgepose.load_model(points_only)
    square = trimesh.Trimesh([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0]], [[0, 1, 2], [0, 2, 3]])
    with pytest.raises(edgepose.InvalidModelError, match="flat"):
        edgepose.load_model(square)
    tilted_triangle = trimesh.Trimesh([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0.05]], [[0, 1, 2]])
    with pytest.raises(edgepose.InvalidModelError, match="flat"):
        edgepose.load_model(tilted_triangle)
    with pytest.raises(edgepose.InvalidModelError, match="outside 0..2"):
        edgepose.load_model(trimesh.Trimesh(np.eye(3) * 0.1, [[0, 1, 5]], process=False))
    # A few triangles are fine when they enclose a volume.
    tetrahedron = trimesh.Trimesh(
        np.vstack([np.zeros(3), np.eye(3) * 0.1]), [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
    )
    assert edgepose.load_model(tetrahedron).diameter == pytest.approx(0.1 * np.sqrt(2), rel=0.02)


@pytest.mark.parametrize(
    "extents, scale, shown",
    [
        ((2000.0, 1000.0, 500.0), 1.0, "2.29e+03 m"),  # a kilometre-sized "object"
        ((2e6, 1e6, 5e5), None, "2.29e+03 m"),  # read as millimetres, still absurd
        ((2e-5, 1e-5, 1e-5), None, "2.45e-05 m"),  # micrometres
        ((0.2, 0.1, 0.1), 1e-4, "2.45e-05 m"),  # a wrong explicit scale
    ],
)
def test_absurd_units_are_reported(extents, scale, shown):
    with pytest.raises(edgepose.InvalidModelError, match=re.escape(shown) + " across.*scale"):
        edgepose.load_model(trimesh.creation.box(extents=extents), scale=scale)


def test_flat_point_models_are_refused():
    rng = np.random.default_rng(0)
    sheet = np.c_[rng.random((500, 2)) * 0.1, np.zeros(500)]
    with pytest.raises(edgepose.InvalidModelError, match="flat"):
        edgepose.model_from_points(sheet, np.tile([0.0, 0.0, 1.0], (500, 1)))


def test_altered_network_manifest_is_a_model_files_error(tmp_path):
    models = tmp_path / "models"
    shutil.copytree(edgepose.encoder.MODELS_DIR, models)
    manifest = json.loads((models / "manifest.json").read_text())
    del manifest["inputs"]
    (models / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(edgepose.ModelFilesError, match="malformed"):
        edgepose.Encoder(models)
    (models / "manifest.json").write_text("{")
    with pytest.raises(edgepose.ModelFilesError, match="cannot read"):
        edgepose.Encoder(models)


def test_an_encoder_graph_with_other_inputs_is_a_model_files_error(tmp_path):
    # An encoder exported before the core computed its inputs (or any other
    # graph) is refused on load, not when the first estimate runs it.
    models = tmp_path / "models"
    shutil.copytree(edgepose.encoder.MODELS_DIR, models)
    shutil.copy(models / "irr.onnx", models / "encoder.onnx")
    manifest = json.loads((models / "manifest.json").read_text())
    manifest["files"]["encoder.onnx"] = hashlib.sha256((models / "encoder.onnx").read_bytes()).hexdigest()
    (models / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(edgepose.ModelFilesError, match=r"takes inputs \['observed', 'candidates'\].*re-export"):
        edgepose.Encoder(models)


# --- saving survives SIGKILL ---------------------------------------------------------

_SAVER = textwrap.dedent(
    """
    import sys
    import edgepose

    a, b = (edgepose.Codebook.load(p) for p in sys.argv[1:3])
    print("ready", flush=True)
    while True:
        a.save(sys.argv[3])
        b.save(sys.argv[3])
    """
)


def test_killing_a_save_midway_never_leaves_a_broken_codebook(drill, ycb_dir, tmp_path):
    a, b = tmp_path / "a.codebook", tmp_path / "b.codebook"
    drill[1].save(a)
    edgepose.build_codebook(ycb_dir / "banana.ply", views=200).save(b)
    # Saves are not byte-identical across processes (header key order), so
    # compare what loads: every tensor of the old or of the new codebook.
    versions = [load_file(str(a)), load_file(str(b))]
    work = tmp_path / "work"
    work.mkdir()
    target = work / "object.codebook"
    shutil.copy(a, target)
    rng = np.random.default_rng(7)
    for trial in range(5):
        saver = subprocess.Popen(
            [sys.executable, "-c", _SAVER, str(a), str(b), str(target)], stdout=subprocess.PIPE, text=True
        )
        assert saver.stdout.readline().strip() == "ready"
        threading.Event().wait(float(rng.uniform(0.05, 0.4)))  # let it save a few times
        os.kill(saver.pid, signal.SIGKILL)
        saver.wait()
        assert saver.returncode == -signal.SIGKILL
        assert len(edgepose.Codebook.load(target)) in (2100, 200), f"trial {trial}"
        found = load_file(str(target))
        assert any(found.keys() == v.keys() and all(np.array_equal(found[k], v[k]) for k in v) for v in versions), (
            f"trial {trial}: {target.name} is neither the old nor the new codebook"
        )
    leftovers = [p.name for p in work.iterdir() if p != target]
    assert all(name.startswith(".object.codebook.") and name.endswith(".tmp") for name in leftovers), leftovers


# --- determinism ---------------------------------------------------------------------

_ESTIMATOR = textwrap.dedent(
    """
    import sys
    import numpy as np
    import edgepose

    codebook = edgepose.Codebook.load(sys.argv[1])
    for path in sys.argv[2:]:
        print(edgepose.estimate(np.load(path), codebook).matrix.tobytes().hex())
    """
)


def test_same_input_gives_bit_identical_poses_in_other_processes(drill, tmp_path):
    mesh, codebook = drill
    path = tmp_path / "drill.codebook"
    codebook.save(path)
    clouds = []
    for seed in (11, 12, 13):
        clouds.append(tmp_path / f"cloud{seed}.npy")
        np.save(clouds[-1], render_view(mesh, seed=seed).cloud)
    here = [edgepose.estimate(np.load(c), edgepose.Codebook.load(path)).matrix.tobytes().hex() for c in clouds]
    outputs = []
    for hash_seed, rayon_threads in (("1", "1"), ("2", "2")):
        env = dict(os.environ, PYTHONHASHSEED=hash_seed, RAYON_NUM_THREADS=rayon_threads)
        run = subprocess.run(
            [sys.executable, "-c", _ESTIMATOR, str(path), *map(str, clouds)],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
        outputs.append(run.stdout.split())
    assert outputs[0] == outputs[1] == here


def test_many_threads_with_onnxruntime_threads_give_the_serial_poses(drill):
    mesh, codebook = drill
    encoder = edgepose.Encoder(threads=2)  # onnxruntime's own pool on top of ours and rayon's
    clouds = [render_view(mesh, seed=s).cloud for s in range(20, 36)]
    serial = [edgepose.estimate(c, codebook, encoder=encoder).matrix for c in clouds]
    with ThreadPoolExecutor(max_workers=8) as pool:
        for _ in range(2):
            parallel = list(pool.map(lambda c: edgepose.estimate(c, codebook, encoder=encoder).matrix, clouds))
            assert all(np.array_equal(p, s) for p, s in zip(parallel, serial))


def test_bad_depth_images_and_intrinsics_raise_clear_errors():
    depth = np.full((4, 5), 1000, np.uint16)
    K = [[500.0, 0, 2], [0, 500.0, 2], [0, 0, 1]]
    bad_intrinsics = [
        ([[0, 0, 2], [0, 500, 2], [0, 0, 1]], "pinhole"),  # fx = 0 would divide by zero
        (np.full((3, 3), np.nan), "pinhole"),
        ([[1, 2], [3]], "9 numbers"),
        ("abc", "9 numbers"),
    ]
    for bad_K, message in bad_intrinsics:
        with pytest.raises(edgepose.InvalidCloudError, match=message):
            edgepose.cloud_from_depth(depth, bad_K)
    for scale in (0.0, -1.0, float("nan")):
        with pytest.raises(edgepose.InvalidCloudError, match="depth_scale"):
            edgepose.cloud_from_depth(depth, K, depth_scale=scale)
    with pytest.raises(edgepose.InvalidCloudError, match="hold numbers"):
        edgepose.cloud_from_depth(np.full((4, 5), "a"), K)
    cloud = edgepose.cloud_from_depth(depth, K)
    assert cloud.shape == (20, 3) and np.allclose(cloud[:, 2], 1.0)


def test_depth_images_of_every_number_type_and_layout_give_the_same_points():
    rng = np.random.default_rng(3)
    metres = rng.uniform(0.4, 1.5, (30, 40))
    metres[5, :7] = 0.0  # not measured
    mask = rng.random((30, 40)) < 0.3
    K = np.array([[520.0, 0, 19.5], [0, 510.0, 14.0], [0, 0, 1]])
    millimetres = np.round(metres * 1000)
    v, u = np.nonzero(mask & (metres > 0))
    z = millimetres[v, u] / 1000
    expected = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
    images = {
        "uint16": (millimetres.astype(np.uint16), 1000.0),
        "int32": (millimetres.astype(np.int32), 1000.0),
        "float32 mm": (millimetres.astype(np.float32), 1000.0),
        "float64 m": (millimetres / 1000, 1.0),
        "big-endian": (millimetres.astype(">f8"), 1000.0),
        "a strided view": (np.repeat(millimetres, 2, axis=1)[:, ::2].astype(np.uint16), 1000.0),
    }
    for name, (depth, scale) in images.items():
        cloud = edgepose.cloud_from_depth(depth, K, mask, depth_scale=scale)
        assert cloud.dtype == np.float64, name
        np.testing.assert_allclose(cloud, expected, rtol=1e-12, atol=1e-12, err_msg=name)
    nan_depth = metres.copy()
    nan_depth[mask] = np.nan
    assert len(edgepose.cloud_from_depth(nan_depth, K, mask, depth_scale=1.0)) == 0


def test_clean_cloud_draws_at_most_max_points_reproducibly_in_any_float_layout(drill, view):
    diameter = drill[1].model.diameter
    cloud = view.cloud.astype(np.float64)
    drawn = clean_cloud(cloud, diameter, 256)
    assert drawn.shape == (256, 3) and drawn.dtype == np.float32
    assert np.array_equal(drawn, clean_cloud(cloud, diameter, 256))
    assert np.array_equal(drawn, clean_cloud(cloud.astype(">f8"), diameter, 256))
    wide = np.zeros((len(cloud), 5))
    wide[:, 1:4] = cloud
    assert np.array_equal(drawn, clean_cloud(wide[:, 1:4], diameter, 256))  # a strided view, not copied
    rows = {tuple(p) for p in cloud.astype(np.float32)}
    assert all(tuple(p) in rows for p in drawn) and len({tuple(p) for p in drawn}) == 256
    assert np.array_equal(clean_cloud(cloud, diameter, 10**6), cloud.astype(np.float32))


@pytest.mark.parametrize(
    "wrong, kind",
    [(None, "NoneType"), ("codebooks/power_drill.codebook", "str"), (np.zeros(3), "ndarray")],
)
def test_a_codebook_of_the_wrong_type_is_named_at_every_public_door(drill, wrong, kind):
    mesh, codebook = drill
    view = render_view(mesh, seed=5)
    mask = view.mask
    calls = {
        "estimate": lambda: edgepose.estimate(view.cloud, wrong),
        "estimate_many": lambda: edgepose.estimate_many(view.depth, view.camera.K, [(mask, wrong)], depth_scale=1.0),
        "Tracker": lambda: edgepose.Tracker(wrong),
    }
    for door, call in calls.items():
        with pytest.raises(edgepose.InvalidArgumentError, match="codebook must be an edgepose.Codebook") as caught:
            call()
        assert isinstance(caught.value, TypeError) and isinstance(caught.value, edgepose.EdgePoseError), door
        assert kind in repr(type(wrong)) or repr(wrong)[:10] in str(caught.value), door


def test_settings_and_frame_objects_of_the_wrong_type_are_named(drill):
    mesh, codebook = drill
    view = render_view(mesh, seed=5)
    with pytest.raises(edgepose.InvalidArgumentError, match="settings must be an edgepose.EstimateSettings"):
        edgepose.estimate(view.cloud, codebook, settings={"k": 8})
    with pytest.raises(edgepose.InvalidArgumentError, match=r"objects\[0\] must be a \(mask, codebook\) pair"):
        edgepose.estimate_many(view.depth, view.camera.K, [codebook], depth_scale=1.0)
    with pytest.raises(edgepose.InvalidArgumentError, match="settings must be an edgepose.EstimateSettings"):
        edgepose.Tracker(codebook, settings=None)


@pytest.mark.parametrize("wrong", [None, 3, b"power_drill.ply", np.zeros((4, 3))])
def test_file_doors_name_an_argument_that_is_not_a_path(wrong):
    from edgepose.eval.bop import BopDataset
    from edgepose.io import parse_intrinsics, read_cloud, read_depth_png, read_mask_png, read_pose

    calls = {
        "Codebook.load": (lambda: edgepose.Codebook.load(wrong), "path must be a file path"),
        "read_mesh": (lambda: edgepose.read_mesh(wrong), "path must be a file path"),
        "load_model": (lambda: edgepose.load_model(wrong), "source must be a mesh file path"),
        "build_codebook": (lambda: edgepose.build_codebook(wrong), "source must be a mesh file path"),
        "read_cloud": (lambda: read_cloud(wrong), "path must be a file path"),
        "read_depth_png": (lambda: read_depth_png(wrong), "path must be a file path"),
        "read_mask_png": (lambda: read_mask_png(wrong), "path must be a file path"),
        "read_pose": (lambda: read_pose(wrong), "path must be a file path"),
        "parse_intrinsics": (lambda: parse_intrinsics(wrong), "intrinsics must be a file path"),
        "BopDataset": (lambda: BopDataset(wrong), "root must be a file path"),
    }
    for door, (call, message) in calls.items():
        with pytest.raises(edgepose.InvalidArgumentError, match=message) as caught:
            call()
        assert isinstance(caught.value, TypeError), door


def test_a_codebook_save_to_a_non_path_is_named(drill):
    _, codebook = drill
    with pytest.raises(edgepose.InvalidArgumentError, match="path must be a file path"):
        codebook.save(None)


@pytest.mark.parametrize("scale", [None, "1000", True, np.array([1000.0])])
def test_a_depth_scale_that_is_not_one_number_is_named(scale):
    depth = np.full((4, 5), 1000, np.uint16)
    K = [[500.0, 0, 2], [0, 500.0, 2], [0, 0, 1]]
    with pytest.raises(edgepose.InvalidCloudError, match="depth_scale must be a positive number"):
        edgepose.cloud_from_depth(depth, K, depth_scale=scale)


def test_masks_are_bool_or_integer_and_a_float_map_is_refused(drill):
    depth = np.full((4, 5), 1000, np.uint16)
    K = [[500.0, 0, 2], [0, 500.0, 2], [0, 0, 1]]
    mask = np.zeros((4, 5), np.uint8)
    mask[1:3, 1:4] = 255  # OpenCV's 0/255 mask
    assert len(edgepose.cloud_from_depth(depth, K, mask)) == 6
    assert len(edgepose.cloud_from_depth(depth, K, mask > 0)) == 6
    for wrong in (mask.astype(np.float32) / 255, np.full((4, 5), "x"), mask.astype(object)):
        with pytest.raises(edgepose.InvalidCloudError, match="mask must be bool or integer"):
            edgepose.cloud_from_depth(depth, K, wrong)
    _, codebook = drill
    with pytest.raises(edgepose.InvalidCloudError, match="mask must be bool or integer"):
        edgepose.estimate_many(depth, K, [(mask.astype(np.float64), codebook)])


def test_absurd_intrinsics_never_give_non_finite_points():
    # Found by benches/fuzz.py: a focal length and depth scale of 5e-266 pass
    # the pinhole check, and the points they made overflowed to inf.
    depth = np.full((4, 5), 0.8, np.float32)
    K = [[5.4e-266, 0, -0.7], [0, 573.6, 2], [0, 0, 1]]
    cloud = edgepose.cloud_from_depth(depth, K, depth_scale=5.4e-266)
    assert np.isfinite(cloud).all()
    assert len(cloud) <= 4  # only the column over the principal point (x = 0) is finite, if any


def test_a_focal_length_that_sends_the_points_to_infinity_is_survived(drill):
    # Found by benches/fuzz.py: a huge fy made the scene window's bounds
    # infinite, and int() raised OverflowError inside estimate.
    mesh, codebook = drill
    view = render_view(mesh, seed=5)
    K = view.camera.K.copy()
    K[1, 1] = 1e308
    try:
        pose = edgepose.estimate(view.cloud, codebook, depth=view.depth, K=K, depth_scale=1.0)
    except edgepose.EdgePoseError:
        return
    assert np.isfinite(pose.matrix).all()
