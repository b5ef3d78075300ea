"""Reading the files a robot's stack hands over: point clouds (``.ply``,
``.pcd``, ``.npy``), 16-bit depth PNGs with their masks, camera intrinsics,
and poses.

Clouds are (N, 3) float64 arrays in the file's units (edgepose expects
metres); depth images are returned as stored (uint16 millimetres, usually)
and converted by :func:`edgepose.cloud_from_depth`. Every unreadable or
unsupported file raises :class:`FileFormatError` naming the file.
"""

from __future__ import annotations

import json
import os
import re
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from edgepose.cloud import pinhole_matrix
from edgepose.errors import EdgePoseError, InvalidCloudError, checked_path

#: Cloud file suffixes :func:`read_cloud` understands.
CLOUD_SUFFIXES = (".ply", ".pcd", ".npy")


class FileFormatError(EdgePoseError, ValueError):
    """A file that is missing, unreadable, or in an unsupported variant of its format."""


def read_cloud(path: str | os.PathLike) -> np.ndarray:
    """(N, 3) float64 points of a ``.ply`` (point cloud or mesh vertices),
    ``.pcd`` (ASCII or binary, x y z fields) or ``.npy`` ((N, 3) array) file."""
    path = _existing(path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        try:
            points = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise FileFormatError(f"{path}: not a readable .npy array ({e})") from None
    elif suffix == ".pcd":
        points = read_pcd(path)
    elif suffix == ".ply":
        points = _read_ply_points(path)
    else:
        raise FileFormatError(f"{path}: unsupported cloud file type {suffix!r} (use {', '.join(CLOUD_SUFFIXES)})")
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3 or not np.issubdtype(points.dtype, np.number):
        raise FileFormatError(f"{path}: expected (N, 3) numbers, got shape {points.shape} of {points.dtype}")
    return points.astype(np.float64)


def _read_ply_points(path: Path) -> np.ndarray:
    import trimesh

    try:
        loaded = trimesh.load(path, process=False, skip_materials=True)
    except Exception as e:  # trimesh raises many types for malformed files
        raise FileFormatError(f"{path}: not a readable PLY file ({e})") from None
    vertices = getattr(loaded, "vertices", None)
    if vertices is None:
        raise FileFormatError(f"{path}: holds no vertices")
    return np.asarray(vertices)


#: PCD ``TYPE``/``SIZE`` → numpy dtype.
_PCD_TYPES = {
    ("F", 4): "f4",
    ("F", 8): "f8",
    ("I", 1): "i1",
    ("I", 2): "i2",
    ("I", 4): "i4",
    ("I", 8): "i8",
    ("U", 1): "u1",
    ("U", 2): "u2",
    ("U", 4): "u4",
    ("U", 8): "u8",
}


def read_pcd(path: str | os.PathLike) -> np.ndarray:
    """(N, 3) x y z of a PCL ``.pcd`` file with ``DATA ascii`` or ``DATA binary``
    (other fields are skipped; NaN rows are kept, as the estimator drops them).
    ``binary_compressed`` files are refused: re-save them as binary."""
    path = _existing(path)
    blob = path.read_bytes()
    header: dict[str, list[str]] = {}
    offset = 0
    while "DATA" not in header:
        end = blob.find(b"\n", offset)
        if end < 0:
            raise FileFormatError(f"{path}: PCD header has no DATA line")
        line = blob[offset:end].decode("ascii", errors="replace").strip()
        offset = end + 1
        if line and not line.startswith("#"):
            key, *values = line.split()
            header[key.upper()] = values
    try:
        fields = header["FIELDS"]
        sizes = [int(s) for s in header["SIZE"]]
        types = [t.upper() for t in header["TYPE"]]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(fields))]
        points = int(header["POINTS"][0]) if "POINTS" in header else int(header["WIDTH"][0]) * int(header["HEIGHT"][0])
        data = header["DATA"][0].lower()
    except (KeyError, IndexError, ValueError) as e:
        raise FileFormatError(f"{path}: malformed PCD header ({e})") from None
    if not {"x", "y", "z"} <= set(fields) or not len(fields) == len(sizes) == len(types) == len(counts):
        raise FileFormatError(f"{path}: PCD needs x y z fields with one SIZE/TYPE/COUNT each, got FIELDS {fields}")
    if data == "ascii":
        try:
            columns = [sum(counts[: fields.index(axis)]) for axis in "xyz"]
            table = np.loadtxt(blob[offset:].decode("ascii").splitlines(), ndmin=2, usecols=columns)
        except (ValueError, UnicodeDecodeError) as e:
            raise FileFormatError(f"{path}: malformed ASCII PCD data ({e})") from None
        return table[:points]
    if data == "binary":
        try:
            dtype = np.dtype(
                [
                    (f"{name}_{i}" if count > 1 else name, _PCD_TYPES[(t, s)], (count,) if count > 1 else ())
                    for i, (name, s, t, count) in enumerate(zip(fields, sizes, types, counts))
                ]
            )
        except KeyError as e:
            raise FileFormatError(f"{path}: unsupported PCD field type/size {e}") from None
        if len(blob) - offset < points * dtype.itemsize:
            raise FileFormatError(f"{path}: PCD data holds fewer than the {points} points its header declares")
        records: Any = np.frombuffer(blob, dtype=dtype, count=points, offset=offset)  # structured: fields by name
        return np.stack([records[axis].astype(np.float64) for axis in "xyz"], axis=1)
    raise FileFormatError(
        f"{path}: PCD 'DATA {data}' is not supported (use ascii or binary, e.g. pcl_convert_pcd_ascii_binary)"
    )


def read_depth_png(path: str | os.PathLike) -> np.ndarray:
    """(H, W) depth image of a single-channel PNG, as stored: uint16 for the
    usual 16-bit millimetre images."""
    image = _read_png(path)
    if image.ndim != 2:
        raise FileFormatError(f"{path}: a depth image must have one channel, got shape {image.shape}")
    return image


def read_mask_png(path: str | os.PathLike) -> np.ndarray:
    """(H, W) bool mask of a PNG: true where the pixel is non-zero: its
    palette index in a palette image, any colour channel otherwise. Alpha is
    ignored (an opaque mask has alpha 255 everywhere)."""
    image = _read_png(path, palette_indices=True)
    if image.ndim == 2:
        return image != 0
    colour = image[..., :-1] if image.shape[2] in (2, 4) else image  # LA, RGBA, PA: drop alpha
    return np.asarray(colour.any(axis=2))


def _read_png(path: str | os.PathLike, palette_indices: bool = False) -> np.ndarray:
    """The PNG's pixels; palette images as RGBA, or as their palette indices."""
    from PIL import Image, UnidentifiedImageError

    path = _existing(path)
    try:
        with Image.open(path) as image:
            if image.mode in ("P", "PA") and not palette_indices:
                image = image.convert("RGBA")
            elif image.mode == "I;16B":
                image = image.convert("I;16")
            return np.asarray(image)
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError, EOFError, struct.error, zlib.error) as e:
        # Pillow reports a damaged chunk as SyntaxError, a cut stream as EOFError or struct.error.
        raise FileFormatError(f"{path}: not a readable image ({type(e).__name__}: {e})") from None


def write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an (H, W) uint8/uint16 or (H, W, 3) uint8 array as a PNG."""
    from PIL import Image

    image = np.ascontiguousarray(image)
    if image.dtype == np.bool_:
        image = image.astype(np.uint8) * 255
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path, format="PNG", optimize=True)


def parse_intrinsics(text: str) -> np.ndarray:
    """(3, 3) camera matrix K from 9 numbers (row-major, separated by commas
    or spaces) or from a JSON file holding a 3×3 list, 9 numbers, an object
    with ``K``/``cam_K`` (BOP), or ``fx``, ``fy``, ``cx``, ``cy``."""
    path = checked_path(text, "intrinsics")
    if path.suffix.lower() == ".json" or path.is_file():
        path = _existing(path)
        try:
            value = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            raise FileFormatError(f"{path}: not valid JSON ({e})") from None
        source = str(path)
        if isinstance(value, dict):
            if all(k in value for k in ("fx", "fy", "cx", "cy")):
                value = [value["fx"], 0, value["cx"], 0, value["fy"], value["cy"], 0, 0, 1]
            else:
                value = value.get("K", value.get("cam_K"))
    else:
        source = "--K"
        try:
            value = [float(x) for x in re.split(r"[,\s]+", text.strip().strip("[]")) if x]
        except ValueError:
            raise FileFormatError(f"--K: {text!r} is neither a JSON file nor 9 numbers") from None
    try:
        return pinhole_matrix(value)
    except InvalidCloudError as e:
        raise FileFormatError(f"{source}: {e}") from None


def read_pose(path: str | os.PathLike) -> np.ndarray:
    """(4, 4) float64 ``T_cam_obj`` from a ``.npy`` file or a JSON file with a
    4×4 list, 16 numbers, or an object with ``matrix`` (as ``edgepose
    estimate`` prints) or BOP's ``cam_R_m2c`` + ``cam_t_m2c`` (millimetres)."""
    path = _existing(path)
    try:
        if path.suffix.lower() == ".npy":
            value = np.load(path, allow_pickle=False)
        else:
            value = json.loads(path.read_text())
            if isinstance(value, dict) and "cam_R_m2c" in value:
                T = np.eye(4)
                T[:3, :3] = np.reshape(value["cam_R_m2c"], (3, 3))
                T[:3, 3] = np.reshape(value["cam_t_m2c"], 3) / 1000.0
                value = T
            elif isinstance(value, dict):
                value = value["matrix"]
        T = np.asarray(value, dtype=np.float64).reshape(4, 4)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise FileFormatError(f"{path}: not a 4×4 pose ({e})") from None
    if not (np.isfinite(T).all() and np.allclose(T[3], [0, 0, 0, 1])):
        raise FileFormatError(f"{path}: not a rigid 4×4 pose: {T.tolist()}")
    return T


def _existing(path: str | os.PathLike) -> Path:
    path = checked_path(path)
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    return path
