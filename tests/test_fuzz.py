"""Property-based fuzzing (hypothesis) of the two places untrusted bytes and
arrays enter edgepose: the codebook loader and estimate()'s input path.

Every input must end in a valid result (a whole codebook / a finite pose) or
an ``EdgePoseError``: any other exception, a crash or a hang fails. A hang is
caught by a faulthandler watchdog that dumps every thread's stack and exits.

This is the short CI run (``EDGEPOSE_FUZZ_EXAMPLES`` examples per property,
derandomised so CI is reproducible). The long run uses the same strategies
and checks: ``python benches/fuzz.py --seconds 600``.
"""

from __future__ import annotations

import faulthandler
import os
import re
import struct
import warnings
from contextlib import contextmanager
from pathlib import Path

import edgepose
import numpy as np
import pytest
from edgepose.cloud import checked_depth, clean_cloud, clean_depth_cloud
from edgepose.eval import render_view
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

EXAMPLES = int(os.environ.get("EDGEPOSE_FUZZ_EXAMPLES", "60"))
#: A single input taking longer than this is a hang, not slowness (an estimate takes milliseconds).
WATCHDOG_S = 120

FUZZ_SETTINGS = dict(
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.large_base_example],
)


_armed = False


@contextmanager
def watchdog():
    """Dump every thread's stack and exit if the block takes over
    :data:`WATCHDOG_S`. Inside an armed watchdog (the long run arms one per
    batch: arming costs ~1 ms) it adds nothing."""
    global _armed
    if _armed:
        yield
        return
    faulthandler.dump_traceback_later(WATCHDOG_S, exit=True)
    _armed = True
    try:
        yield
    finally:
        faulthandler.cancel_dump_traceback_later()
        _armed = False


# --- codebook loader -----------------------------------------------------------------


@st.composite
def damaged_codebooks(draw, blob: bytes) -> bytes:
    """``blob`` (a saved codebook) after one random kind of damage."""
    header_end = 8 + struct.unpack("<Q", blob[:8])[0]
    kind = draw(st.sampled_from(["flip", "truncate", "overwrite", "splice", "size", "number", "junk"]))
    data = bytearray(blob)
    if kind == "flip":  # a few bit flips, half of them in the header
        for _ in range(draw(st.integers(1, 8))):
            i = draw(st.integers(0, header_end - 1) | st.integers(0, len(data) - 1))
            data[i] ^= 1 << draw(st.integers(0, 7))
    elif kind == "truncate":
        data = data[: draw(st.integers(0, len(data) - 1))]
    elif kind == "overwrite":
        i = draw(st.integers(0, len(data) - 1))
        chunk = draw(st.binary(min_size=1, max_size=64))
        data[i : i + len(chunk)] = chunk
    elif kind == "splice":  # bytes inserted or removed: every later offset shifts
        i = draw(st.integers(0, len(data)))
        if draw(st.booleans()):
            data[i:i] = draw(st.binary(min_size=1, max_size=32))
        else:
            del data[i : i + draw(st.integers(1, 32))]
    elif kind == "size":  # the header-size field claims anything
        data[:8] = struct.pack("<Q", draw(st.integers(0, 2**64 - 1)))
    elif kind == "number":  # one number in the header (a shape, an offset) replaced
        header = data[8:header_end].decode()
        numbers = list(re.finditer(r"\d+", header))
        match = numbers[draw(st.integers(0, len(numbers) - 1))]
        value = str(draw(st.integers(0, 2**70) | st.integers(0, 5000)))
        header = header[: match.start()] + value + header[match.end() :]
        encoded = header.encode()
        data = bytearray(struct.pack("<Q", len(encoded)) + encoded + bytes(data[header_end:]))
    else:  # not a codebook at all
        data = bytearray(draw(st.binary(max_size=2048)))
    return bytes(data)


def check_load(damaged: bytes, path: Path, original: edgepose.Codebook) -> str:
    """Load ``damaged`` from ``path``: a CodebookError, or exactly ``original``.
    Returns the outcome's name (for the long run's tally)."""
    path.write_bytes(damaged)
    with watchdog():
        try:
            loaded = edgepose.Codebook.load(path)
        except edgepose.CodebookError:
            return "CodebookError"
    assert np.array_equal(loaded.codes, original.codes) and np.array_equal(loaded.model.points, original.model.points)
    return "loaded (unchanged content)"


# --- estimate input ------------------------------------------------------------------

_ANY_DTYPE = hnp.scalar_dtypes() | hnp.byte_string_dtypes() | hnp.unicode_string_dtypes() | st.just(np.dtype(object))


@st.composite
def random_arrays(draw) -> np.ndarray:
    """Arrays of any dtype and shape, mostly (N, 3), with any values: drawn
    element by element (small arrays: hypothesis' edge values, 0, NaN, inf)
    or as random bits (any size, fast)."""
    dtype = draw(_ANY_DTYPE)
    if dtype == np.dtype(object):
        shape = draw(hnp.array_shapes(min_dims=0, max_dims=3, max_side=8))
        return np.full(shape, draw(st.none() | st.floats() | st.text(max_size=3)), dtype=object)
    if draw(st.booleans()):
        shape = draw(st.tuples(st.integers(0, 40), st.just(3)) | hnp.array_shapes(min_dims=0, max_dims=3, max_side=8))
        return draw(hnp.arrays(dtype, shape))
    shape = draw(st.tuples(st.integers(0, 4000), st.just(3)) | hnp.array_shapes(min_dims=0, max_dims=3, max_side=40))
    bits = np.random.default_rng(draw(st.integers(0, 2**32 - 1))).bytes(int(np.prod(shape)) * dtype.itemsize)
    return np.frombuffer(bits, dtype=dtype).reshape(shape).copy()


@st.composite
def damaged_clouds(draw, cloud: np.ndarray) -> np.ndarray:
    """A real observed cloud, subsetted, damaged (NaN/inf/huge rows), rescaled,
    converted to another dtype and laid out differently."""
    n = draw(st.integers(0, len(cloud)))
    start = draw(st.integers(0, len(cloud) - n))
    points = cloud[start : start + n].copy()
    if n:
        bad = draw(st.lists(st.integers(0, n - 1), max_size=n))
        value = draw(st.sampled_from([np.nan, np.inf, -np.inf, 1e30, -1e300, 0.0]))
        points[bad, draw(st.integers(0, 2))] = value
    points *= draw(st.sampled_from([1.0, 1.0, 1.0, 1e-3, 1e3, -1.0]) | st.floats(1e-6, 1e6))
    points += draw(st.floats(-10, 10))
    dtype = draw(st.sampled_from([np.float64, np.float32, np.float16, np.int64, np.int16, np.uint8]))
    with np.errstate(all="ignore"):
        points = points.astype(dtype)
    layout = draw(st.sampled_from(["c", "fortran", "strided", "reversed"]))
    if layout == "fortran":
        points = np.asfortranarray(points)
    elif layout == "strided":
        wide = np.zeros((len(points), 6), dtype=points.dtype)
        wide[:, ::2] = points
        points = wide[:, ::2]
    elif layout == "reversed":
        points = points[::-1]
    return points


ESTIMATE_INPUTS = ("random", "cloud", "python")


def estimate_inputs(cloud: np.ndarray) -> st.SearchStrategy:
    return (
        random_arrays()
        | damaged_clouds(cloud)
        | st.none()
        | st.text(max_size=10)
        | st.lists(st.lists(st.floats(), max_size=4), max_size=60)
    )


def check_estimate(cloud: object, codebook: edgepose.Codebook) -> str:
    """A finite, rigid pose or an EdgePoseError; returns the outcome's name."""
    with watchdog():
        try:
            pose = edgepose.estimate(cloud, codebook)
        except edgepose.EdgePoseError as e:
            return type(e).__name__
    assert np.isfinite(pose.matrix).all() and np.isfinite(pose.fit)
    np.testing.assert_allclose(pose.R @ pose.R.T, np.eye(3), atol=1e-6)
    return "pose"


# --- depth frames, masks and intrinsics ----------------------------------------------

_NUMBERS = st.floats(allow_nan=True, allow_infinity=True) | st.integers(-(2**40), 2**40)
_ODD_VALUES = st.none() | st.text(max_size=4) | st.booleans() | _NUMBERS | st.lists(_NUMBERS, max_size=10)


@st.composite
def damaged_depths(draw, depth: np.ndarray) -> object:
    """A rendered depth image (float metres), damaged: holes, NaN/inf/negative
    patches, another dtype or unit, cropped, reshaped, or replaced."""
    kind = draw(st.sampled_from(["as_is", "patch", "dtype", "crop", "shape", "random", "odd"]))
    image = depth.copy()
    if kind == "patch":
        for _ in range(draw(st.integers(1, 4))):
            r, c = draw(st.integers(0, image.shape[0] - 1)), draw(st.integers(0, image.shape[1] - 1))
            h, w = draw(st.integers(1, 200)), draw(st.integers(1, 200))
            image[r : r + h, c : c + w] = draw(st.sampled_from([np.nan, np.inf, -np.inf, 0.0, -1.0, 1e30, 1e-9]))
    elif kind == "dtype":
        dtype = draw(st.sampled_from([np.uint16, np.int32, np.uint8, np.float16, np.int8, np.bool_, np.complex64]))
        with np.errstate(all="ignore"):
            image = (image * draw(st.sampled_from([1.0, 1000.0, 1e6]))).astype(dtype)
    elif kind == "crop":
        r, c = draw(st.integers(0, image.shape[0])), draw(st.integers(0, image.shape[1]))
        image = image[r : r + draw(st.integers(0, 300)), c : c + draw(st.integers(0, 300))]
    elif kind == "shape":
        image = draw(st.sampled_from([image[None], image[..., None], image.ravel(), image[:0], image.T]))
    elif kind == "random":
        return draw(random_arrays())
    elif kind == "odd":
        return draw(_ODD_VALUES)
    return image


@st.composite
def damaged_intrinsics(draw, K: np.ndarray) -> object:
    """A pinhole matrix, perturbed, degenerate, non-finite, reshaped or not a matrix."""
    kind = draw(st.sampled_from(["as_is", "entry", "scaled", "shape", "odd"]))
    if kind == "as_is":
        return K
    if kind == "entry":
        bad = K.copy()
        bad.flat[draw(st.integers(0, 8))] = draw(_NUMBERS.map(float))
        return bad
    if kind == "scaled":
        return K * draw(st.floats(-1e3, 1e3))
    if kind == "shape":
        return draw(st.sampled_from([K.ravel(), K[:2], K.tolist(), K.ravel()[:8], np.eye(4), K.astype(np.float16)]))
    return draw(_ODD_VALUES)


@st.composite
def damaged_masks(draw, mask: np.ndarray) -> object:
    """An object mask, grown, moved, emptied, full, of another dtype or shape."""
    kind = draw(st.sampled_from(["as_is", "none", "empty", "full", "shifted", "dtype", "shape", "odd"]))
    if kind == "none":
        return None
    if kind == "empty":
        return np.zeros_like(mask)
    if kind == "full":
        return np.ones_like(mask)
    if kind == "shifted":
        return np.roll(mask, (draw(st.integers(-300, 300)), draw(st.integers(-300, 300))), axis=(0, 1))
    if kind == "dtype":
        return mask.astype(draw(st.sampled_from([np.uint8, np.int64, np.float32, np.float64, object])))
    if kind == "shape":
        return draw(st.sampled_from([mask[1:], mask[:, :-1], mask[None], mask.ravel()]))
    if kind == "odd":
        return draw(_ODD_VALUES)
    return mask


@st.composite
def frame_inputs(draw, view) -> tuple:
    """``(depth, K, mask, depth_scale)`` of a rendered view (float metres):
    mostly one of them damaged and the others whole, so that the damage
    reaches past the first check; sometimes all, sometimes none."""
    damaged = draw(st.sampled_from(["depth", "K", "mask", "depth_scale", "all", "none"]))
    return (
        draw(damaged_depths(view.depth)) if damaged in ("depth", "all") else view.depth,
        draw(damaged_intrinsics(view.camera.K)) if damaged in ("K", "all") else view.camera.K,
        draw(damaged_masks(view.mask)) if damaged in ("mask", "all") else view.mask,
        draw(st.sampled_from([1.0, 1000.0]) | _ODD_VALUES) if damaged in ("depth_scale", "all") else 1.0,
    )


def check_cloud_from_depth(value: tuple) -> str:
    """(N, 3) finite points in front of the camera, or an EdgePoseError; and
    the points ``clean_depth_cloud`` keeps of the frame are those
    ``clean_cloud`` keeps of that cloud (or the same error)."""
    depth, K, mask, depth_scale = value
    with watchdog():
        try:
            cloud = edgepose.cloud_from_depth(depth, K, mask, depth_scale=depth_scale)
        except edgepose.EdgePoseError as e:
            return type(e).__name__
        assert cloud.ndim == 2 and cloud.shape[1] == 3 and cloud.dtype == np.float64
        assert np.isfinite(cloud).all() and (cloud[:, 2] > 0).all()
        depth, K = checked_depth(depth, K, depth_scale)
        kept = []
        for keep in (
            lambda: clean_cloud(cloud, 0.2, 256),
            lambda: clean_depth_cloud(depth, K, depth_scale, mask, 0.2, 256),
        ):
            try:
                kept.append(keep())
            except edgepose.InvalidCloudError as e:
                kept.append(str(e))
        assert type(kept[0]) is type(kept[1]) and np.array_equal(*kept), kept
    return "points"


FRAME_DOORS = ("estimate", "estimate_many", "Tracker.update_depth", "track_many")


def check_frame(value: tuple, door: str, cloud: np.ndarray, codebook: edgepose.Codebook) -> str:
    """A (damaged) frame at one of the :data:`FRAME_DOORS`, beside the view's
    own good ``cloud``: a finite pose, or an EdgePoseError (returned by
    ``estimate_many`` per object, or raised)."""
    depth, K, mask, depth_scale = value
    with watchdog():
        try:
            if door == "estimate":
                poses = [edgepose.estimate(cloud, codebook, depth=depth, K=K, depth_scale=depth_scale)]
            elif door == "estimate_many":
                frame = edgepose.estimate_many(depth, K, [(mask, codebook)] * 2, depth_scale=depth_scale, workers=1)
                if any(e is not None and not isinstance(e, edgepose.EdgePoseError) for e in frame.errors):
                    raise AssertionError(f"untyped error {frame.errors}")
                poses = [p for p in frame.poses if p is not None]
                if not poses:
                    return "errors per object"
            elif door == "Tracker.update_depth":
                poses = [edgepose.Tracker(codebook).update_depth(depth, K, mask, depth_scale)]
            else:  # a tracker that already follows the object: the tracked frame's path
                tracker = edgepose.Tracker(codebook)
                tracker.update(cloud)
                frame = edgepose.track_many(depth, K, [(mask, tracker)], depth_scale=depth_scale, workers=1)
                if any(e is not None and not isinstance(e, edgepose.EdgePoseError) for e in frame.errors):
                    raise AssertionError(f"untyped error {frame.errors}")
                poses = [p for p in frame.poses if p is not None]
                if not poses:
                    return "errors per object"
        except edgepose.EdgePoseError as e:
            return type(e).__name__
    for pose in poses:
        assert np.isfinite(pose.matrix).all() and np.isfinite(pose.fit)
        np.testing.assert_allclose(pose.R @ pose.R.T, np.eye(3), atol=1e-6)
    return "pose"


# --- BOP folders ---------------------------------------------------------------------

#: The files of a one-image BOP folder (relative to its root) the damage picks from.
BOP_FILES = (
    "models/models_info.json",
    "test/000000/scene_camera.json",
    "test/000000/scene_gt.json",
    "test/000000/scene_gt_info.json",
    "test_targets_bop19.json",
    "test/000000/depth/000001.png",
    "test/000000/mask_visib/000001_000000.png",
)


def small_bop_folder(real: Path, root: Path) -> dict[str, bytes]:
    """A one-image, one-object BOP folder at ``root`` cut from the real
    dataset ``real`` (scene 0, its first image, the first annotated object);
    returns each of :data:`BOP_FILES`' bytes."""
    import json

    scene = real / "test" / "000000"
    im = min(json.loads((scene / "scene_camera.json").read_text()), key=int)
    gt = json.loads((scene / "scene_gt.json").read_text())[im][0]
    info = json.loads((scene / "scene_gt_info.json").read_text())[im][0]
    camera = json.loads((scene / "scene_camera.json").read_text())[im]
    models = json.loads((real / "models" / "models_info.json").read_text())
    texts = {
        "models/models_info.json": json.dumps({str(gt["obj_id"]): models[str(gt["obj_id"])]}),
        "test/000000/scene_camera.json": json.dumps({"1": camera}),
        "test/000000/scene_gt.json": json.dumps({"1": [gt]}),
        "test/000000/scene_gt_info.json": json.dumps({"1": [info]}),
        "test_targets_bop19.json": json.dumps([{"scene_id": 0, "im_id": 1, "obj_id": gt["obj_id"], "inst_count": 1}]),
    }
    files = {name: text.encode() for name, text in texts.items()}
    files["test/000000/depth/000001.png"] = (scene / "depth" / f"{int(im):06d}.png").read_bytes()
    files["test/000000/mask_visib/000001_000000.png"] = (
        scene / "mask_visib" / f"{int(im):06d}_000000.png"
    ).read_bytes()
    write_bop_folder(root, files)
    return files


_written: dict[Path, bytes | None] = {}


def write_bop_folder(root: Path, files: dict[str, bytes | None]) -> None:
    """Make ``root`` hold ``files`` (None: absent), writing only the files
    that differ from what this process last wrote there."""
    for name, data in files.items():
        path = root / name
        if path in _written and _written[path] is data:
            continue
        path.parent.mkdir(parents=True, exist_ok=True)
        if data is None:
            path.unlink(missing_ok=True)
        else:
            path.write_bytes(data)
        _written[path] = data


@st.composite
def damaged_bop_files(draw, files: dict[str, bytes]) -> dict[str, bytes | None]:
    """The folder's files with one damaged: a JSON value replaced, a key
    dropped, the text truncated or spliced, the file removed or junk."""
    import json

    name = draw(st.sampled_from(BOP_FILES))
    data = files[name]
    kind = draw(st.sampled_from(["value", "drop", "truncate", "flip", "remove", "junk"]))
    if kind in ("value", "drop") and name.endswith(".json"):
        value = json.loads(data)
        holder, key = value, None
        while isinstance(holder, (dict, list)) and holder and draw(st.booleans()) is False:
            key = draw(st.sampled_from(sorted(holder) if isinstance(holder, dict) else list(range(len(holder)))))
            if not isinstance(holder[key], (dict, list)) or not holder[key]:
                break
            holder = holder[key]
        if isinstance(holder, (dict, list)) and holder:
            key = draw(st.sampled_from(sorted(holder) if isinstance(holder, dict) else list(range(len(holder)))))
            if kind == "drop":
                del holder[key]
            else:
                odd = st.none() | st.booleans() | _NUMBERS | st.text(max_size=6) | st.lists(_NUMBERS, max_size=17)
                holder[key] = draw(odd | st.dictionaries(st.text(max_size=3), _NUMBERS, max_size=3))
        else:
            value = draw(st.none() | _NUMBERS | st.text(max_size=6))
        data = json.dumps(value).encode()
    elif kind == "truncate":
        data = data[: draw(st.integers(0, max(len(data) - 1, 0)))]
    elif kind == "flip":
        damaged = bytearray(data)
        for _ in range(draw(st.integers(1, 8))):
            damaged[draw(st.integers(0, len(damaged) - 1))] ^= 1 << draw(st.integers(0, 7))
        data = bytes(damaged)
    elif kind == "remove":
        return {**files, name: None}
    else:
        data = draw(st.binary(max_size=256))
    return {**files, name: data}


def check_bop(root: Path) -> str:
    """Read every part of the folder a BOP run reads: a BopDatasetError (or
    another EdgePoseError), or well-formed objects, targets, cameras, poses,
    depth and masks."""
    from edgepose.eval.bop import BopDataset

    with watchdog():
        try:
            dataset = BopDataset(root)
            objects = dataset.objects
            targets = dataset.targets()
            for target in targets:
                image = dataset.image(target.scene_id, target.im_id)
                depth = image.depth()
                for gt in image.gts:
                    mask = image.mask(gt.gt_id)
                    assert mask.dtype == np.bool_ and mask.ndim == 2
                    assert gt.matrix.shape == (4, 4)
                assert depth.ndim == 2 and image.K.shape == (3, 3)
        except edgepose.EdgePoseError as e:
            return type(e).__name__
    assert all(o.diameter == o.diameter for o in objects.values())
    return "read"


# --- the CI run ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def saved(drill, tmp_path_factory):
    path = tmp_path_factory.mktemp("fuzz") / "drill.codebook"
    drill[1].save(path)
    return path.read_bytes(), path.with_name("damaged.codebook")


def test_fuzz_codebook_loader(drill, saved):
    blob, path = saved

    @settings(max_examples=EXAMPLES, derandomize=True, **FUZZ_SETTINGS)
    @given(damaged=damaged_codebooks(blob))
    def run(damaged):
        check_load(damaged, path, drill[1])

    run()


def test_fuzz_estimate_input(drill):
    mesh, codebook = drill
    cloud = render_view(mesh, seed=2).cloud

    @settings(max_examples=EXAMPLES, derandomize=True, **FUZZ_SETTINGS)
    @given(value=estimate_inputs(cloud))
    def run(value):
        check_estimate(value, codebook)

    run()


@pytest.fixture(scope="module")
def view(drill):
    return render_view(drill[0], seed=2)


def test_fuzz_cloud_from_depth(view):
    @settings(max_examples=EXAMPLES, derandomize=True, **FUZZ_SETTINGS)
    @given(value=frame_inputs(view))
    def run(value):
        check_cloud_from_depth(value)

    run()


@pytest.mark.parametrize("door", FRAME_DOORS)
def test_fuzz_frame_doors(drill, view, door):
    @settings(max_examples=max(EXAMPLES // 3, 10), derandomize=True, **FUZZ_SETTINGS)
    @given(value=frame_inputs(view))
    def run(value):
        check_frame(value, door, view.cloud, drill[1])

    run()


@pytest.fixture
def bop_files(tmp_path):
    """The files of a good one-image BOP folder cut from the real frames (written to ``tmp_path/good``)."""
    real = Path(__file__).resolve().parents[2] / "shared" / "data" / "ycbv_real"
    if not real.is_dir():
        pytest.skip(f"{real}: the real frames are not here")
    return small_bop_folder(real, tmp_path / "good")


def test_fuzz_bop_folder(bop_files, tmp_path):
    files = bop_files
    assert check_bop(tmp_path / "good") == "read"

    @settings(max_examples=EXAMPLES, derandomize=True, **FUZZ_SETTINGS)
    @given(damaged=damaged_bop_files(files))
    def run(damaged):
        write_bop_folder(tmp_path / "bop", damaged)
        check_bop(tmp_path / "bop")

    run()


def test_a_scene_file_that_is_not_an_object_is_a_dataset_error(bop_files, tmp_path):
    # Found by benches/fuzz.py: scene_gt.json holding a number raised AttributeError.
    files = bop_files
    for name in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"):
        for value in (b"3", b"[1, 2]", b'"text"'):
            root = tmp_path / f"{name}-{len(value)}"
            write_bop_folder(root, {**files, f"test/000000/{name}": value})
            assert check_bop(root) == "BopDatasetError", (name, value)
    root = tmp_path / "keys"
    write_bop_folder(root, {**files, "test/000000/scene_camera.json": b'{"one": {}}'})
    from edgepose.eval.bop import BopDataset, BopDatasetError

    with pytest.raises(BopDatasetError, match="not a number"):
        BopDataset(root).image_ids(0)


def test_a_depth_scale_that_is_not_a_positive_number_is_a_dataset_error(bop_files, tmp_path):
    # Found by benches/fuzz.py: a NaN depth_scale (JSON allows NaN) made every depth NaN, with numpy's warning.
    import json

    from edgepose.eval.bop import BopDataset, BopDatasetError

    camera = json.loads(bop_files["test/000000/scene_camera.json"])
    for value in ("NaN", "-1.0", "0", "Infinity"):
        root = tmp_path / value
        text = json.dumps({"1": {**camera["1"], "depth_scale": "X"}}).replace('"X"', value)
        write_bop_folder(root, {**bop_files, "test/000000/scene_camera.json": text.encode()})
        with pytest.raises(BopDatasetError, match="depth_scale must be a positive number"):
            BopDataset(root).image(0, 1)
    root = tmp_path / "huge"  # finite and positive: read; the depths that overflow are infinite, without a warning
    text = json.dumps({"1": {**camera["1"], "depth_scale": 1.7e308}})
    write_bop_folder(root, {**bop_files, "test/000000/scene_camera.json": text.encode()})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isinf(BopDataset(root).image(0, 1).depth()).any()


def test_an_infinite_number_where_a_bop_file_wants_a_whole_one_is_a_dataset_error(bop_files, tmp_path):
    # Found by benches/fuzz.py: JSON's Infinity as an inst_count or im_id raised OverflowError.
    targets = b'[{"scene_id": 0, "im_id": 1, "obj_id": 8, "inst_count": 1}]'
    for damaged in (
        targets.replace(b'"inst_count": 1', b'"inst_count": Infinity'),
        targets.replace(b"1,", b"Infinity,"),
    ):
        root = tmp_path / str(len(list(tmp_path.iterdir())))
        write_bop_folder(root, {**bop_files, "test_targets_bop19.json": damaged})
        assert check_bop(root) == "BopDatasetError", damaged
    gt = bop_files["test/000000/scene_gt.json"]
    root = tmp_path / "gt"
    write_bop_folder(
        root, {**bop_files, "test/000000/scene_gt.json": gt.replace(b'"obj_id": ', b'"obj_id": 1e400, "x": ')}
    )
    assert check_bop(root) == "BopDatasetError"
    from edgepose.eval.bop import BopDatasetError
    from edgepose.eval.bop_run import read_detections

    detections = tmp_path / "detections.json"
    detections.write_text(
        '[{"scene_id": 0, "image_id": Infinity, "category_id": 8, "score": 1.0, "segmentation": '
        '{"counts": [4], "size": [2, 2]}}]'
    )
    with pytest.raises(BopDatasetError, match="detection 0 malformed"):
        read_detections(detections)


def test_an_absurd_id_in_a_bop_file_is_a_dataset_error(bop_files, tmp_path):
    # Found by benches/fuzz.py: a scene_id of 1e255 named a folder too long for the system (OSError).
    from edgepose.eval.bop import BopDataset, BopDatasetError

    targets = b'[{"scene_id": 0, "im_id": 1, "obj_id": 8, "inst_count": 1}]'
    for damaged in (b'"scene_id": 1e255', b'"scene_id": -1', b'"im_id": 1e255, "x": 1'):
        root = tmp_path / str(len(list(tmp_path.iterdir())))
        key = damaged.split(b":")[0] + b": "
        text = targets.replace(key + (b"0" if b"scene" in key else b"1"), damaged)
        write_bop_folder(root, {**bop_files, "test_targets_bop19.json": text})
        assert check_bop(root) == "BopDatasetError", text
    with pytest.raises(BopDatasetError, match="no such scene folder"):
        BopDataset(root).image(10**300, 1)
