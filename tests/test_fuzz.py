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
from contextlib import contextmanager
from pathlib import Path

import edgepose
import numpy as np
import pytest
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


@contextmanager
def watchdog():
    faulthandler.dump_traceback_later(WATCHDOG_S, exit=True)
    try:
        yield
    finally:
        faulthandler.cancel_dump_traceback_later()


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
    """Arrays of any dtype and shape, mostly (N, 3), with any values."""
    dtype = draw(_ANY_DTYPE)
    shape = draw(st.tuples(st.integers(0, 400), st.just(3)) | hnp.array_shapes(min_dims=0, max_dims=3, max_side=40))
    if dtype == np.dtype(object):
        return np.full(shape, draw(st.none() | st.floats() | st.text(max_size=3)), dtype=object)
    return draw(hnp.arrays(dtype, shape))


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
