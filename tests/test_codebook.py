"""Codebooks: building, the file format, and every way a file can be wrong."""

from __future__ import annotations

import json
import struct

import edgepose
import numpy as np
import pytest
from conftest import SHIPPED
from edgepose.codebook import MAX_FILE_BYTES, VERSION, _checksum


@pytest.fixture(scope="module")
def drill_codebook() -> edgepose.Codebook:
    """A codebook built here from the shipped drill mesh (no ../shared needed)."""
    return edgepose.build_codebook(SHIPPED / "power_drill.ply")


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


def test_saved_codebooks_are_readable_by_others_and_keep_their_mode(drill_codebook, tmp_path):
    path = tmp_path / "drill.codebook"
    drill_codebook.save(path)
    assert path.stat().st_mode & 0o777 == 0o644
    path.chmod(0o640)
    drill_codebook.save(path)
    assert path.stat().st_mode & 0o777 == 0o640


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


def _resealed(blob: bytes, edit) -> bytes:
    """``blob`` with its metadata edited and the checksum recomputed: what a
    file written that way (another version, another encoder) looks like."""
    from safetensors.numpy import load

    def edit_and_seal(header):
        edit(header["__metadata__"])
        header["__metadata__"]["checksum"] = _checksum(load(blob), header["__metadata__"])

    return _rewrite_header(blob, edit_and_seal)


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda b: b[: len(b) // 2], "not a valid codebook"),
        (lambda b: b[:4], "not a valid codebook"),
        (lambda b: b"\x00" * 64, "not a valid codebook"),
        (lambda b: b"solid cube\nfacet normal 0 0 1\n" * 10, "not a valid codebook"),
        (lambda b: struct.pack("<Q", 1 << 60) + b[8:], "not a valid codebook"),
        (lambda b: _rewrite_header(b, lambda h: h["__metadata__"].update(version="99")), "version 99"),
        (lambda b: _resealed(b, lambda m: m.update(version="1")), f"version 1, this edgepose reads {VERSION}"),
        (lambda b: _rewrite_header(b, lambda h: h["__metadata__"].update(encoder="0" * 64)), "checksum mismatch"),
        (lambda b: _resealed(b, lambda m: m.update(encoder="0" * 64)), "built by encoder 000000000000"),
        (lambda b: _rewrite_header(b, lambda h: h["__metadata__"].update(format="other")), "not an edgepose codebook"),
        (lambda b: _rewrite_header(b, lambda h: h["__metadata__"].pop("checksum")), "checksum mismatch"),
        (lambda b: _resealed(b, lambda m: m.pop("model")), "missing 'model'"),
        (lambda b: _resealed(b, lambda m: m.update(map_points="100000000")), "100000000' points per map"),
        (
            lambda b: _resealed(b, lambda m: m.update(model=m["model"].replace('"diameter": ', '"diameter": -'))),
            "model metadata",
        ),
        (lambda b: _rewrite_header(b, lambda h: h["codes"].update(shape=[2100, 32])), "not a valid codebook"),
        # Headers claiming huge arrays: checked against the bytes present, nothing allocated.
        (lambda b: _rewrite_header(b, lambda h: h["codes"].update(shape=[1 << 40, 64])), "not a valid codebook"),
        (
            lambda b: _rewrite_header(b, lambda h: h["codes"].update(shape=[1 << 32, 1 << 32, 1 << 32])),
            "not a valid codebook",
        ),
        (
            lambda b: _rewrite_header(b, lambda h: h["codes"].update(shape=[1 << 40, 64], data_offsets=[0, 1 << 47])),
            "not a valid codebook",
        ),
    ],
)
def test_damaged_files_raise_codebook_errors(drill_codebook, tmp_path, damage, message):
    good = tmp_path / "good.codebook"
    drill_codebook.save(good)
    bad = tmp_path / "bad.codebook"
    bad.write_bytes(damage(good.read_bytes()))
    with pytest.raises(edgepose.CodebookError, match=message):
        edgepose.Codebook.load(bad)


@pytest.mark.parametrize("region", ["header", "tensors"])
def test_every_flipped_bit_is_detected(drill_codebook, tmp_path, region):
    """One flipped bit, in the header or in the tensor bytes, never loads as a
    (silently different) codebook: each is a CodebookError."""
    good = tmp_path / "good.codebook"
    drill_codebook.save(good)
    blob = good.read_bytes()
    data_start = 8 + struct.unpack("<Q", blob[:8])[0]
    low, high = (0, data_start) if region == "header" else (data_start, len(blob))
    rng = np.random.default_rng(3)
    path = tmp_path / "flipped.codebook"
    for i in rng.integers(low, high, size=60):
        damaged = bytearray(blob)
        damaged[i] ^= 1 << int(rng.integers(8))
        path.write_bytes(bytes(damaged))
        with pytest.raises(edgepose.CodebookError):
            edgepose.Codebook.load(path)


def test_non_regular_files_are_refused_without_blocking(tmp_path):
    import os

    fifo = tmp_path / "pipe.codebook"
    os.mkfifo(fifo)  # reading it would block forever
    with pytest.raises(edgepose.CodebookError, match="not a regular file"):
        edgepose.Codebook.load(fifo)
    with pytest.raises(edgepose.CodebookError, match="not a regular file"):
        edgepose.Codebook.load(tmp_path)


def test_missing_and_oversized_files(tmp_path):
    with pytest.raises(edgepose.CodebookError, match="cannot read"):
        edgepose.Codebook.load(tmp_path / "absent.codebook")
    huge = tmp_path / "huge.codebook"
    with open(huge, "wb") as f:
        f.truncate(MAX_FILE_BYTES + 1)
    with pytest.raises(edgepose.CodebookError, match="too large"):
        edgepose.Codebook.load(huge)


def test_shipped_codebooks_are_up_to_date_with_this_edgepose(ycb_dir):
    """Rebuild them (``make codebooks``) after changing the encoder or the symmetry search."""
    from edgepose.catalog import BuildSettings, is_up_to_date
    from edgepose.codebook import file_sha256

    books = sorted(SHIPPED.glob("*.codebook"))
    assert len(books) == 5
    for book in books:
        assert is_up_to_date(book, file_sha256(ycb_dir / f"{book.stem}.ply"), BuildSettings()), book.name


def test_shipped_codebooks_hold_what_the_symmetry_search_finds_now(ycb_dir):
    """Catches a change to the search that its fingerprint does not show (the
    Rust core's distances or ICP): raise ``SEARCH_REVISION`` and rebuild them."""
    for book in sorted(SHIPPED.glob("*.codebook")):
        stored = edgepose.Codebook.load(book).symmetry
        found = edgepose.detect_symmetry(edgepose.load_model(ycb_dir / f"{book.stem}.ply"))
        for part in ("discrete", "continuous", "near"):
            a, b = getattr(stored, part), getattr(found, part)
            assert a.shape == b.shape and np.allclose(a, b, atol=1e-5), (book.name, part)


def test_a_maps_code_is_the_same_whatever_the_chunks_and_threads():
    """The encoder splits a batch into chunks run side by side; each map's
    code and spectrum come out bit for bit as from one call on one thread."""
    from edgepose.encoder import Encoder

    maps = np.random.default_rng(3).normal(size=(11, 512, 3)).astype(np.float32) * 0.4
    one = Encoder(threads=1).encode(maps, batch=64)
    for threads, batch in [(2, 3), (3, 1), (2, 64)]:
        codes, spectra = Encoder(threads=threads).encode(maps, batch=batch)
        assert np.array_equal(codes, one[0]) and np.array_equal(spectra, one[1]), (threads, batch)
    assert Encoder(threads=2).encode(maps[:0])[0].shape == (0, 64)
    with pytest.raises(ValueError, match="threads"):
        Encoder(threads=0)
