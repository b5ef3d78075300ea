"""Codebooks: everything edgepose needs to find one object's pose, built once
per object in seconds and stored as one safetensors file (no pickle; the
header is bounded JSON and each tensor's size is checked on load).

Loading trusts nothing: the file size is capped before reading, safetensors
checks every tensor's offsets against the bytes actually present (so a header
claiming huge shapes allocates nothing), and a sha256 over the header fields
and every tensor's bytes (``checksum`` in the header) catches flipped bits
that would otherwise load silently as different numbers.

A codebook holds, per viewpoint: the encoder's unit code, the angular
spectrum (for the in-plane angle), the view rotation and the centroid of the
visible model points; and once: the standard model, its scale, diameter and
centre, its rotational symmetries (:mod:`edgepose.symmetry`) and which
search found them, the fingerprint of the encoder that made the codes and,
when built from a mesh file, the sha256 of that file (so a catalogue build
can tell an up-to-date codebook from a stale one by reading the codebook
alone).

A saved file is a function of its contents only (header keys in a fixed
order, no timestamps): the same mesh and encoder give the same bytes on any
machine, in any process.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
import tempfile
import time
import warnings
from dataclasses import InitVar, dataclass, field
from pathlib import Path

import numpy as np

from edgepose import _core
from edgepose.encoder import Encoder, default_encoder
from edgepose.errors import EdgePoseError, InvalidArgumentError, checked_path
from edgepose.maps import DEFAULT_MAP_POINTS, compute_maps
from edgepose.model import DEFAULT_MODEL_POINTS, MeshSource, StandardModel, load_model
from edgepose.settings import usable_cores
from edgepose.symmetry import NO_SYMMETRY, SEARCH_FINGERPRINT, Symmetry, detect_symmetry, doubtful_turns
from edgepose.views import DEFAULT_VIEWS, Viewpoints, fibonacci_viewpoints

FORMAT = "edgepose-codebook"
#: 2: header ``checksum`` (sha256 of the metadata and tensors) added.
#: 3: header ``symmetry`` (the object's detected rotational symmetries) added.
#: 4: ``symmetry`` records the object's near turns (``Symmetry.near``) too.
VERSION = 4
#: A codebook file larger than this is not a codebook (bounds what loading reads).
MAX_FILE_BYTES = 64 * 1024 * 1024


class CodebookError(EdgePoseError):
    """A codebook file that is unreadable, corrupt, of another format version,
    or made by a different encoder than the one in use."""


class StaleCodebookWarning(UserWarning):
    """A codebook whose symmetries and near turns an older symmetry search
    found (:attr:`Codebook.symmetry_search`): it works, but without what the
    current search finds (turns the confidence tests and the turned-pose
    check may switch to); rebuild it (``edgepose build``)."""


@dataclass(frozen=True, eq=False)
class Codebook:
    """One object's viewpoint codebook. Immutable; safe to share between threads."""

    model: StandardModel
    viewpoints: Viewpoints
    codes: np.ndarray
    """(V, D) float32 unit codes, one per viewpoint."""
    spectra: np.ndarray
    """(V, S) float32 angular spectra, one per viewpoint."""
    centroids: np.ndarray
    """(V, 3) float64 centroid of each view's visible model points, model frame, metres."""
    fingerprint: str
    """sha256 of the encoder that made ``codes``."""
    map_points: int = DEFAULT_MAP_POINTS
    source_sha256: str | None = None
    """sha256 of the mesh file's bytes it was built from (None: built from an
    in-memory mesh or model, or saved by an older edgepose)."""
    symmetry: Symmetry = NO_SYMMETRY
    """The object's rotational symmetries, object frame: poses differing by
    them are equally right (detected when built)."""
    symmetry_search: str | None = None
    """Which symmetry search found ``symmetry`` (:data:`edgepose.symmetry.SEARCH_FINGERPRINT`
    when built; None: given by hand, or saved by an older edgepose)."""
    timings: dict = field(default_factory=dict)
    """Build time per stage, seconds (empty for a loaded codebook)."""
    index: _core.ModelIndex = field(init=False, repr=False)
    doubtful_turns: tuple[np.ndarray, np.ndarray] = field(init=False, repr=False)
    """The model's turns the confidence tests a pose against (:func:`edgepose.symmetry.doubtful_turns`)."""
    points_index: InitVar[_core.ModelIndex | None] = None
    """An index of the same model points (a build's symmetry search made
    one) whose kd-tree and cells ``index`` shares rather than builds again."""

    def __post_init__(self, points_index: _core.ModelIndex | None) -> None:
        index = _core.ModelIndex(self.model.core) if points_index is None else points_index.with_model(self.model.core)
        object.__setattr__(self, "index", index)
        object.__setattr__(self, "doubtful_turns", doubtful_turns(self.model, self.symmetry))

    def __len__(self) -> int:
        return len(self.codes)

    def save(self, path: str | os.PathLike) -> None:
        """Write the codebook to ``path`` atomically: a crash mid-save leaves
        either the old file or the new one, never a broken one."""
        from safetensors.numpy import save

        path = checked_path(path)
        tensors = self._tensors()
        _write_atomically(path, _canonical_header(save(tensors, self._metadata(tensors))))

    def _tensors(self) -> dict[str, np.ndarray]:
        """The stored arrays, in their file dtypes."""
        tensors = {
            "codes": self.codes.astype(np.float16),
            "spectra": self.spectra.astype(np.float16),
            "view_rotations": self.viewpoints.rotations.astype(np.float32),
            "view_centroids": self.centroids.astype(np.float32),
            "model_points": self.model.points.astype(np.float32),
            "model_normals": self.model.normals.astype(np.float16),
        }
        return {k: np.ascontiguousarray(v) for k, v in tensors.items()}

    def _metadata(self, tensors: dict[str, np.ndarray]) -> dict[str, str]:
        metadata = {
            "format": FORMAT,
            "version": str(VERSION),
            "encoder": self.fingerprint,
            "map_points": str(self.map_points),
            "model": json.dumps(
                {
                    "centre": self.model.centre.tolist(),
                    "scale": self.model.scale,
                    "diameter": self.model.diameter,
                    # Stored at the float32 precision the maps use it at (files of
                    # earlier builds hold it so; the core's sum is now ordered).
                    "spacing": float(np.float32(self.model.spacing)),
                }
            ),
            "symmetry": json.dumps(self.symmetry.to_json()),
        }
        if self.source_sha256 is not None:
            metadata["source_sha256"] = self.source_sha256
        if self.symmetry_search is not None:
            metadata["symmetry_search"] = self.symmetry_search
        metadata["checksum"] = _checksum(tensors, metadata)
        return metadata

    @classmethod
    def load(cls, path: str | os.PathLike, encoder: Encoder | None = None) -> Codebook:
        """Read a codebook, checking its format, version, sizes and that it was
        made by ``encoder`` (the shipped one by default). Warns
        (:class:`StaleCodebookWarning`) when an older or unknown symmetry search made it."""
        book = cls._load(path, encoder)
        if book.symmetry_search != SEARCH_FINGERPRINT:
            warnings.warn(
                f"{path}: its symmetries and near turns were found by an older or unknown symmetry search; it "
                "works, but rebuild it (edgepose build, or build_codebook) for what the current search finds",
                StaleCodebookWarning,
                stacklevel=2,
            )
        return book

    @classmethod
    def _load(cls, path: str | os.PathLike, encoder: Encoder | None = None) -> Codebook:
        """:meth:`load` without the stale-search warning."""
        from safetensors import SafetensorError
        from safetensors.numpy import load

        path = checked_path(path)
        encoder = encoder or default_encoder()
        try:
            info = path.stat()
            if not stat.S_ISREG(info.st_mode):  # a FIFO or device would block or never end
                raise CodebookError(f"{path}: not a regular file")
            if info.st_size > MAX_FILE_BYTES:
                raise CodebookError(f"{path}: {info.st_size} bytes is too large for a codebook")
            with open(path, "rb") as f:
                blob = f.read(MAX_FILE_BYTES + 1)  # the file may have grown since stat()
            if len(blob) > MAX_FILE_BYTES:
                raise CodebookError(f"{path}: more than {MAX_FILE_BYTES} bytes is too large for a codebook")
            tensors = load(blob)
            metadata = _metadata(blob)
        except OSError as e:
            raise CodebookError(f"{path}: cannot read ({e.strerror or e})") from None
        except (SafetensorError, ValueError, UnicodeDecodeError) as e:
            raise CodebookError(f"{path}: not a valid codebook file ({e})") from None
        return cls._from_parts(tensors, metadata, encoder, str(path))

    @classmethod
    def _from_parts(
        cls,
        tensors: dict[str, np.ndarray],
        metadata: dict[str, str],
        encoder: Encoder,
        name: str,
        points_index: _core.ModelIndex | None = None,
    ) -> Codebook:
        """A codebook from stored arrays and header, after checking both
        (``points_index``: see :attr:`Codebook.points_index`)."""
        _check_header(tensors, metadata, encoder, name)
        try:
            info = json.loads(metadata["model"])
            for key, dtype in _DTYPES.items():
                if tensors[key].dtype != dtype:
                    raise CodebookError(f"{name}: {key} has dtype {tensors[key].dtype}, expected {np.dtype(dtype)}")
            codes = tensors["codes"].astype(np.float32)
            views = len(codes)
            if views < 1:
                raise CodebookError(f"{name}: holds no viewpoints")
            expected = {
                "codes": (views, encoder.code_size),
                "spectra": (views, encoder.spectrum_size),
                "view_rotations": (views, 3, 3),
                "view_centroids": (views, 3),
            }
            for key, shape in expected.items():
                if tensors[key].shape != shape:
                    raise CodebookError(f"{name}: {key} has shape {tensors[key].shape}, expected {shape}")
            if metadata["map_points"] != str(encoder.map_points):
                raise CodebookError(
                    f"{name}: made with {metadata['map_points']!r} points per map, "
                    f"the encoder takes {encoder.map_points}"
                )
            points = tensors["model_points"].astype(np.float32)
            normals = tensors["model_normals"].astype(np.float32)
            if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape or len(points) < 16:
                raise CodebookError(f"{name}: model points/normals have shapes {points.shape}/{normals.shape}")
            numbers = [info["scale"], info["diameter"], info["spacing"], *info["centre"]]
            if (
                not all(np.isfinite(numbers))
                or len(info["centre"]) != 3
                or not (info["scale"] > 0 and info["diameter"] > 0 and info["spacing"] >= 0)
            ):
                raise CodebookError(f"{name}: model metadata is not valid: {info}")
            arrays = ("codes", "spectra", "view_rotations", "view_centroids", "model_points", "model_normals")
            if not all(np.isfinite(tensors[a]).all() for a in arrays):
                raise CodebookError(f"{name}: contains NaN or infinite values")
            # The stored float32 rotations must be this edgepose's viewpoints;
            # use the exact float64 ones.
            viewpoints = fibonacci_viewpoints(views)
            drift = np.abs(tensors["view_rotations"] - viewpoints.rotations).max()
            if not drift < 1e-5:
                raise CodebookError(f"{name}: view rotations differ from the Fibonacci viewpoints by {drift:.2g}")
            model = StandardModel(
                points,
                normals,
                np.asarray(info["centre"], dtype=np.float64),
                float(info["scale"]),
                float(info["diameter"]),
                float(info["spacing"]),
            )
            return cls(
                model=model,
                viewpoints=viewpoints,
                codes=codes,
                spectra=tensors["spectra"].astype(np.float32),
                centroids=tensors["view_centroids"].astype(np.float64),
                fingerprint=metadata["encoder"],
                map_points=int(metadata["map_points"]),
                source_sha256=metadata.get("source_sha256"),
                symmetry=Symmetry.from_json(json.loads(metadata["symmetry"])),
                symmetry_search=metadata.get("symmetry_search"),
                points_index=points_index,
            )
        except KeyError as e:
            raise CodebookError(f"{name}: missing {e} in the codebook") from None
        except (TypeError, ValueError) as e:
            raise CodebookError(f"{name}: malformed codebook ({e})") from None


def _check_header(tensors: dict[str, np.ndarray], metadata: dict[str, str], encoder: Encoder, name: str) -> None:
    """CodebookError unless the header names this format and version, its
    checksum matches the arrays, and ``encoder`` made the codes."""
    if metadata.get("format") != FORMAT:
        raise CodebookError(f"{name}: not an edgepose codebook (format {metadata.get('format')!r})")
    if metadata.get("version") != str(VERSION):
        raise CodebookError(
            f"{name}: codebook format version {metadata.get('version')}, this edgepose reads {VERSION}; "
            "rebuild it with edgepose.build_codebook"
        )
    if metadata.get("checksum") != _checksum(tensors, metadata):
        raise CodebookError(f"{name}: checksum mismatch: the file is corrupt (flipped or altered bytes)")
    if metadata.get("encoder") != encoder.fingerprint:
        raise CodebookError(
            f"{name}: built by encoder {str(metadata.get('encoder'))[:12]}…, "
            f"but the encoder in use is {encoder.fingerprint[:12]}…; rebuild the codebook"
        )


def build_codebook(
    source: MeshSource | StandardModel,
    *,
    views: int = DEFAULT_VIEWS,
    n_points: int = DEFAULT_MODEL_POINTS,
    scale: float | None = None,
    encoder: Encoder | None = None,
) -> Codebook:
    """Codebook of one object: a mesh file or ``trimesh.Trimesh`` (see
    :func:`edgepose.load_model` for ``scale``), or a ready StandardModel.
    Building is offline work, so the default encoder uses every core."""
    import trimesh

    if not isinstance(source, (str, os.PathLike, trimesh.Trimesh, StandardModel)):
        raise InvalidArgumentError(
            f"source must be a mesh file path, a trimesh.Trimesh or an edgepose.StandardModel, got {source!r:.80}"
        )
    encoder = encoder or default_encoder(threads=usable_cores())
    t0 = time.perf_counter()
    # Hashed before reading: if the file changes in between, the codebook
    # records the older hash and a catalogue rebuild picks the change up.
    source_sha256 = file_sha256(source) if isinstance(source, (str, os.PathLike)) and Path(source).is_file() else None
    model = source if isinstance(source, StandardModel) else load_model(source, n_points=n_points, scale=scale)
    t1 = time.perf_counter()
    viewpoints = fibonacci_viewpoints(views)
    maps = compute_maps(model, viewpoints, encoder.map_points)
    t2 = time.perf_counter()
    codes, spectra = encoder.encode(maps.points)
    t3 = time.perf_counter()
    # One kd-tree and grid of cells over the model's points serves the
    # symmetry search and both codebooks below.
    index = _core.ModelIndex(model.core)
    symmetry = detect_symmetry(model, index)
    t_sym = time.perf_counter()
    built = Codebook(
        model,
        viewpoints,
        codes,
        spectra,
        maps.centroids,
        encoder.fingerprint,
        encoder.map_points,
        source_sha256,
        symmetry,
        SEARCH_FINGERPRINT,
        points_index=index,
    )
    # Through the stored dtypes, so a built codebook and its saved copy give identical poses.
    tensors = built._tensors()
    stored = Codebook._from_parts(tensors, built._metadata(tensors), encoder, "new codebook", index)
    t4 = time.perf_counter()
    object.__setattr__(
        stored,
        "timings",
        {
            "model": t1 - t0,
            "maps": t2 - t1,
            "encode": t3 - t2,
            "symmetry": t_sym - t3,
            "store": t4 - t_sym,
            "total": t4 - t0,
        },
    )
    return stored


#: The stored arrays' file dtypes (see ``Codebook._tensors``).
_DTYPES = {
    "codes": np.float16,
    "spectra": np.float16,
    "view_rotations": np.float32,
    "view_centroids": np.float32,
    "model_points": np.float32,
    "model_normals": np.float16,
}


def file_sha256(path: str | os.PathLike) -> str:
    """sha256 (hex) of a file's bytes, read in 1 MiB chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _canonical_header(blob: bytes) -> bytes:
    """A safetensors file with its JSON header rewritten with sorted keys.

    safetensors writes ``__metadata__`` from a hash map, in an order that
    changes from process to process; sorting makes the same codebook the same
    bytes everywhere. The tensors' bytes and offsets are unchanged; the header
    stays space-padded to a multiple of 8 bytes, as safetensors writes it."""
    size = int.from_bytes(blob[:8], "little")
    header = json.dumps(json.loads(blob[8 : 8 + size]), sort_keys=True, separators=(",", ":")).encode()
    header += b" " * (-len(header) % 8)
    return len(header).to_bytes(8, "little") + header + blob[8 + size :]


def _checksum(tensors: dict[str, np.ndarray], metadata: dict[str, str]) -> str:
    """sha256 of every header field but ``checksum`` and of every tensor's name,
    dtype, shape and bytes, in a fixed order: independent of the file's layout,
    so one flipped bit anywhere that still parses changes it."""
    digest = hashlib.sha256()
    fields = {k: v for k, v in metadata.items() if k != "checksum"}
    digest.update(json.dumps(fields, sort_keys=True).encode())
    for key in sorted(tensors):
        array = np.ascontiguousarray(tensors[key])
        digest.update(json.dumps([key, array.dtype.str, list(array.shape)]).encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def _metadata(blob: bytes) -> dict[str, str]:
    """The safetensors header's ``__metadata__`` (its size is bounded by the file's)."""
    header_size = int.from_bytes(blob[:8], "little")
    if header_size > len(blob) - 8:
        raise ValueError("header size exceeds the file")
    return json.loads(blob[8 : 8 + header_size].decode("utf-8")).get("__metadata__", {})


def _write_atomically(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    # mkstemp makes the file private (0600); a codebook keeps the mode of the
    # file it replaces, or is readable by all like any other data file.
    mode = stat.S_IMODE(path.stat().st_mode) if path.is_file() else 0o644
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
