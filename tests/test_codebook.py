"""Codebooks: building, the file format, and every way a file can be wrong."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

import edgepose
from edgepose.codebook import MAX_FILE_BYTES


@pytest.fixture(scope="module")
def drill_codebook(ycb_dir) -> edgepose.Codebook:
    return edgepose.build_codebook(ycb_dir / "power_drill.ply")


def test_built_codebook_holds_what_the_method_needs(drill_codebook):
    cb = drill_codebook
    assert len(cb) == 2100
    assert cb.codes.shape == (2100, 64) and cb.spectra.shape[0] == 2100
    np.testing.assert_allclose(np.linalg.norm(cb.codes, axis=1), 1.0, atol=2e-3)  # float16 storage
    np.testing.assert_allclose(cb.viewpoints.directions, edgepose.fibonacci_viewpoints(2100).directions, atol=1e-6)
    assert cb.fingerprint == edgepose.Encoder().fingerprint
    assert set(cb.timings) >= {"model", "maps", "encode", "total"}


def test_save_load_round_trip_is_exact_and_small(drill_codebook, tmp_path):
    path = tmp_path / "drill.codebook"
    drill_codebook.save(path)
    assert path.stat().st_size <= 1_000_000
    loaded = edgepose.Codebook.load(path)
    for name in ("codes", "spectra", "centroids"):
        assert np.array_equal(getattr(loaded, name), getattr(drill_codebook, name))
    assert np.array_equal(loaded.viewpoints.rotations, drill_codebook.viewpoints.rotations)
    assert np.array_equal(loaded.model.points, drill_codebook.model.points)
    assert loaded.model.diameter == drill_codebook.model.diameter


def test_saving_over_a_good_file_is_atomic(drill_codebook, tmp_path, monkeypatch):
    path = tmp_path / "drill.codebook"
    drill_codebook.save(path)
    before = path.read_bytes()

    def crash(*args, **kwargs):
        raise KeyboardInterrupt("killed mid-save")

    monkeypatch.setattr("edgepose.codebook.os.replace", crash)
    with pytest.raises(KeyboardInterrupt):
        drill_codebook.save(path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["drill.codebook"], "no temporary file left behind"


def _rewrite_header(blob: bytes, edit) -> bytes:
    size = struct.unpack("<Q", blob[:8])[0]
    header = json.loads(blob[8 : 8 + size])
    edit(header)
    text = json.dumps(header).encode()
    text += b" " * (-len(text) % 8)
    return struct.pack("<Q", len(text)) + text + blob[8 + size :]


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda b: b[: len(b) // 2], "not a valid codebook"),
        (lambda b: b[:4], "not a valid codebook"),
        (lambda b: b"\x00" * 64, "not a valid codebook"),
        (lambda b: b"solid cube\nfacet normal 0 0 1\n" * 10, "not a valid codebook"),
        (lambda b: struct.pack("<Q", 1 << 60) + b[8:], "not a valid codebook"),
        (lambda b: _rewrite_header(b, lambda h: h["__metadata__"].update(version="99")), "version 99"),
        (lambda b: _rewrite_header(b, lambda h: h["__metadata__"].update(encoder="0" * 64)), "built by encoder 000000000000"),
        (lambda b: _rewrite_header(b, lambda h: h["__metadata__"].update(format="other")), "not an edgepose codebook"),
        (lambda b: _rewrite_header(b, lambda h: h["__metadata__"].pop("model")), "missing 'model'"),
        (lambda b: _rewrite_header(b, lambda h: h["codes"].update(shape=[2100, 32])), "not a valid codebook"),
    ],
)
def test_damaged_files_raise_codebook_errors(drill_codebook, tmp_path, damage, message):
    good = tmp_path / "good.codebook"
    drill_codebook.save(good)
    bad = tmp_path / "bad.codebook"
    bad.write_bytes(damage(good.read_bytes()))
    with pytest.raises(edgepose.CodebookError, match=message):
        edgepose.Codebook.load(bad)


def test_flipped_bytes_never_crash(drill_codebook, tmp_path):
    good = tmp_path / "good.codebook"
    drill_codebook.save(good)
    blob = bytearray(good.read_bytes())
    rng = np.random.default_rng(3)
    for trial in range(40):
        damaged = bytearray(blob)
        for i in rng.integers(0, 600, size=4):  # the header region
            damaged[i] ^= 1 << int(rng.integers(8))
        path = tmp_path / f"flip{trial}.codebook"
        path.write_bytes(bytes(damaged))
        try:
            loaded = edgepose.Codebook.load(path)
        except edgepose.CodebookError:
            continue
        assert len(loaded) == 2100  # a flip that left the file valid still loads a whole codebook


def test_missing_and_oversized_files(tmp_path):
    with pytest.raises(edgepose.CodebookError, match="cannot read"):
        edgepose.Codebook.load(tmp_path / "absent.codebook")
    huge = tmp_path / "huge.codebook"
    with open(huge, "wb") as f:
        f.truncate(MAX_FILE_BYTES + 1)
    with pytest.raises(edgepose.CodebookError, match="too large"):
        edgepose.Codebook.load(huge)
