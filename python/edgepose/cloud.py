"""Observed point clouds: validation, cleaning and back-projection from depth.

Clouds are (N, 3) arrays in metres, camera frame (OpenCV: x right, y down,
z forward), already segmented to one object.
"""

from __future__ import annotations

import numbers
from functools import lru_cache

import numpy as np

from edgepose import _core
from edgepose.errors import InvalidCloudError

#: Fewer valid points than this cannot give a pose.
MIN_POINTS = 32
#: Coordinates larger than this (metres from the camera) are sensor garbage, not
#: points: such rows are dropped like NaN ones. Bounds every later computation.
MAX_COORDINATE = 1e6
#: A cloud spanning more than this many object diameters is not the object
#: alone: millimetres, or an unsegmented scene.
MAX_EXTENT_DIAMETERS = 5.0
#: A cloud spanning less than this fraction of the object's diameter holds no
#: shape to match (all points coincide, or the wrong units, e.g. kilometres).
MIN_EXTENT_DIAMETERS = 0.02
#: Depth units per metre of millimetre depth images (16-bit PNGs, as BOP and
#: most RGB-D sensors store them): ``cloud_from_depth``'s default.
DEPTH_SCALE_MM = 1000.0
#: Seed of :func:`clean_cloud`'s draw of at most ``max_points`` rows.
SUBSAMPLE_SEED = 0
#: Rows checked at a time: validation never copies a large cloud whole.
_CHUNK_ROWS = 1 << 16
#: A useful ``max_jump`` for ``cloud_from_depth`` on sensors with many
#: flying pixels: a pixel whose depth differs from a neighbour's by more than
#: this fraction of its depth is dropped (a depth discontinuity). It is *off*
#: by default because it measured worse on the tuning set (bench_pose.py --tune,
#: 6 training shapes × 8 views): at 1.0–1.5 m with Kinect-like noise 56 % of
#: poses correct with it against 85 % without (grazing surfaces lose their
#: pixels), and with masks spilled by 5 px 85 % against 92 % (``estimate``'s
#: own segmentation already drops flying pixels and spill).
FLYING_PIXEL_JUMP = 0.01


def as_cloud(
    cloud: object, max_points: int | None = None, seed: int = 0, *, min_points: int = MIN_POINTS
) -> np.ndarray:
    """(N, 3) float64 points of ``cloud`` (an array of any layout, float or
    integer, or anything with ``.points``, e.g. an Open3D point cloud), with
    rows holding NaN, inf or coordinates beyond ``MAX_COORDINATE`` dropped;
    InvalidCloudError when fewer than ``min_points`` remain.

    With ``max_points``, a larger cloud is subsampled (seeded, so the same
    input gives the same points) *before* the float64 copy: memory stays
    bounded by the chunk size and ``max_points`` whatever the input's size."""
    array = _rows_of_numbers(cloud)
    masks = [_valid_rows(array[s : s + _CHUNK_ROWS]) for s in range(0, len(array), _CHUNK_ROWS)]
    counts = [int(mask.sum()) for mask in masks]
    valid = sum(counts)
    if valid < min_points:
        raise InvalidCloudError(
            f"cloud has {valid} valid points of {len(array)} (rows with NaN, inf or coordinates beyond "
            f"{MAX_COORDINATE:g} m are dropped); at least {min_points} are needed"
        )
    if max_points is not None and valid > max_points:
        ranks = np.random.default_rng(seed).choice(valid, max_points, replace=False)
    elif valid == len(array):
        return array.astype(np.float64)
    else:
        ranks = np.arange(valid)
    return array[_rows_of_valid(masks, counts, ranks)].astype(np.float64)


def clean_cloud(cloud: object, diameter: float, max_points: int) -> np.ndarray:
    """(n, 3) float32: the points of ``cloud`` that ``estimate`` matches
    against an object ``diameter`` metres across: its valid rows (as
    :func:`as_cloud` reads them; at most ``max_points``, a seeded draw),
    without points farther than a diameter from the median (segmentation
    leaks, which would drag the centroid). Raises InvalidCloudError when what
    remains cannot be the object at this scale (millimetres, an unsegmented
    scene, or points that all coincide). Runs in the Rust core
    (``rust/src/query.rs``) without the GIL; a native float32 or float64
    cloud is never copied whole (others are converted to float64 first)."""
    array = _rows_of_numbers(cloud)
    if array.dtype not in (np.dtype(np.float32), np.dtype(np.float64)):
        with np.errstate(invalid="ignore", over="ignore"):  # what does not convert is not finite: dropped
            array = array.astype(np.float64)  # integers, float16, other byte orders: the same draw
    return _core.clean_cloud(array, diameter, _clean_settings(max_points))


def clean_depth_cloud(
    depth: np.ndarray, K: np.ndarray, depth_scale: float, mask: np.ndarray | None, diameter: float, max_points: int
) -> np.ndarray:
    """``clean_cloud(cloud_from_depth(depth, K, mask, depth_scale), diameter,
    max_points)`` of a :func:`checked_depth` image and ``K``: the same (n, 3)
    float32 points (camera frame, metres) in one call to the Rust core,
    without the whole cloud passing through numpy (a tracked frame keeps a
    thousand of an object's tens of thousands of pixels)."""
    valid = np.ones(depth.shape, bool) if mask is None else np.ascontiguousarray(checked_mask(mask, depth.shape))
    return _core.clean_depth_cloud(depth, valid, K, float(depth_scale), diameter, _clean_settings(max_points))


@lru_cache(maxsize=16)
def _clean_settings(max_points: int) -> _core.CleanSettings:
    """The limits :func:`clean_cloud` passes to the Rust core."""
    return _core.CleanSettings(
        max_points=max_points,
        seed=SUBSAMPLE_SEED,
        min_points=MIN_POINTS,
        max_coordinate=MAX_COORDINATE,
        max_extent_diameters=MAX_EXTENT_DIAMETERS,
        min_extent_diameters=MIN_EXTENT_DIAMETERS,
    )


def _rows_of_numbers(cloud: object) -> np.ndarray:
    """``cloud`` (or its ``.points``) as an (N, 3) array of real numbers,
    not copied; InvalidCloudError naming what else it is."""
    try:
        array = np.asarray(getattr(cloud, "points", cloud))
    except Exception as e:  # ragged lists, objects with a broken __array__, ...
        raise InvalidCloudError(f"cloud is not array-like ({type(cloud).__name__}: {e})") from None
    if array.dtype == np.bool_ or not (
        np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)
    ):
        raise InvalidCloudError(f"cloud must hold real numbers (float or integer), got dtype {array.dtype}")
    if array.ndim != 2 or array.shape[1] != 3:
        hint = (
            "; an organised (H, W, 3) cloud needs .reshape(-1, 3)" if array.ndim == 3 and array.shape[-1] == 3 else ""
        )
        raise InvalidCloudError(f"cloud must have shape (N, 3), got {array.shape}{hint}")
    return array


def _valid_rows(chunk: np.ndarray) -> np.ndarray:
    """(n,) bool: rows whose three coordinates are finite and within MAX_COORDINATE."""
    if chunk.dtype not in (np.float32, np.float64):
        # Integers (abs(INT_MIN) overflows) and float16 (MAX_COORDINATE would round to inf).
        chunk = chunk.astype(np.float64)
    within = np.abs(chunk) <= MAX_COORDINATE  # False for NaN too
    return within[:, 0] & within[:, 1] & within[:, 2]  # 5× sooner than .all(axis=1)


def _rows_of_valid(masks: list[np.ndarray], counts: list[int], ranks: np.ndarray) -> np.ndarray:
    """Row indices of the valid rows numbered ``ranks`` (in that order), from
    each chunk's validity ``masks`` and ``counts``, chunk by chunk, so no index
    array of the whole cloud is ever made."""
    if len(masks) == 1:
        return np.flatnonzero(masks[0])[ranks]
    rows = np.empty(len(ranks), dtype=np.intp)
    first_rank = np.cumsum([0, *counts])
    chunk_of = np.searchsorted(first_rank, ranks, side="right") - 1
    for c in np.unique(chunk_of):
        start = int(c) * _CHUNK_ROWS
        valid_here = np.flatnonzero(masks[c])
        picked = chunk_of == c
        rows[picked] = start + valid_here[ranks[picked] - first_rank[c]]
    return rows


def median_depth(points: np.ndarray) -> float:
    """Median z of (N ≥ 1, 3) finite camera-frame points, metres: the value
    ``np.median`` gives (the mean of the two middle values for an even
    count) through one partition, a fraction of ``np.median``'s overhead
    on the few thousand points of an estimate."""
    z = points[:, 2]
    middle = len(z) // 2
    if len(z) % 2:
        return float(np.partition(z, middle)[middle])
    low, high = np.partition(z, [middle - 1, middle])[middle - 1 : middle + 1]
    return float((low + high) / 2)


def is_number(value: object) -> bool:
    """Whether ``value`` is one real number (not a bool, an array or ``None``)."""
    return isinstance(value, (numbers.Real, np.number)) and not isinstance(value, (bool, np.bool_))


def pinhole_matrix(K: object) -> np.ndarray:
    """``K`` as a (3, 3) float64 pinhole camera matrix, checked: finite,
    fx, fy > 0 and last row (0, 0, 1); otherwise InvalidCloudError."""
    try:
        matrix = np.asarray(K, dtype=np.float64).reshape(3, 3)
    except (TypeError, ValueError):
        raise InvalidCloudError(f"K must be 9 numbers (a 3×3 matrix), got {K!r}") from None
    last_row = matrix[2].tolist()  # as np.allclose(matrix[2], (0, 0, 1)), without its cost on every frame
    on_the_image_plane = abs(last_row[0]) <= 1e-8 and abs(last_row[1]) <= 1e-8 and abs(last_row[2] - 1.0) <= 1e-8 + 1e-5
    if not (np.isfinite(matrix).all() and matrix[0, 0] > 0 and matrix[1, 1] > 0 and on_the_image_plane):
        raise InvalidCloudError(f"K is not a pinhole camera matrix (fx, fy > 0, last row 0 0 1): {matrix.tolist()}")
    return matrix


def cloud_from_depth(
    depth: np.ndarray,
    K: np.ndarray,
    mask: np.ndarray | None = None,
    depth_scale: float = DEPTH_SCALE_MM,
    *,
    max_jump: float | None = None,
    erode_px: int = 0,
) -> np.ndarray:
    """(N, 3) float64 camera-frame points (metres) of the pixels with a valid
    depth (and ``mask`` true, when given), in row-major order.

    ``K`` is the 3×3 pinhole matrix; a pixel (row v, column u) has its centre
    at (u, v) (OpenCV). ``depth / depth_scale`` is metres, as in Open3D:
    1000 for uint16 millimetre images, 1 for float metres.

    With ``max_jump`` (e.g. :data:`FLYING_PIXEL_JUMP`), pixels at a depth
    discontinuity (a neighbour's depth differs by more than ``max_jump`` ×
    their depth) are dropped: flying pixels and the first pixels of a
    surface behind. Off by default: ``estimate`` drops flying pixels and a
    spilled mask's background itself, and the filter costs grazing
    surfaces (see :data:`FLYING_PIXEL_JUMP`). ``erode_px`` shrinks the mask
    by that many pixels first (a mask known to spill far)."""
    depth, K = checked_depth(depth, K, depth_scale)
    if max_jump is not None and not (is_number(max_jump) and np.isfinite(max_jump) and max_jump > 0):
        raise InvalidCloudError(f"max_jump must be a positive fraction of the depth or None, got {max_jump}")
    if not (isinstance(erode_px, (int, np.integer)) and erode_px >= 0):
        raise InvalidCloudError(f"erode_px must be a non-negative whole number of pixels, got {erode_px!r}")
    valid = np.ones(depth.shape, dtype=bool)
    if mask is not None:
        mask = checked_mask(mask, depth.shape)
        valid = erode(mask, erode_px) if erode_px else mask
    if max_jump is not None:
        z = depth / depth_scale
        measured = np.isfinite(z) & (z > 0)
        valid = valid & ~depth_discontinuities(z, measured, valid & measured, max_jump)
    return back_project(depth, K, valid, depth_scale)


def checked_depth(depth: object, K: object, depth_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """A depth image and its camera checked: ``(depth (H, W) C-contiguous,
    uint16, float32 or float64 (other number types converted to float64),
    K (3, 3) float64)``; InvalidCloudError for a non-image, a bad ``K`` or
    ``depth_scale``. The image is not converted to metres: that is
    :func:`back_project`'s work, per pixel it keeps."""
    depth = np.asarray(depth)
    K = pinhole_matrix(K)
    if depth.ndim != 2:
        raise InvalidCloudError(f"depth must be a 2-D image, got shape {depth.shape}")
    if not (np.issubdtype(depth.dtype, np.integer) or np.issubdtype(depth.dtype, np.floating)):
        raise InvalidCloudError(f"depth must hold numbers, got dtype {depth.dtype}")
    if not (is_number(depth_scale) and np.isfinite(depth_scale) and depth_scale > 0):
        raise InvalidCloudError(
            f"depth_scale must be a positive number (depth units per metre), got {depth_scale!r:.40}"
        )
    if depth.dtype not in (np.dtype(np.uint16), np.dtype(np.float32), np.dtype(np.float64)):
        with np.errstate(invalid="ignore", over="ignore"):  # what does not convert is not finite: no depth
            depth = depth.astype(np.float64)
    return np.ascontiguousarray(depth), K


def checked_frame(
    depth: object | None, K: object | None, depth_scale: float
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The depth frame a cloud was cut from, as ``estimate`` and the
    ``Tracker`` take it: ``(depth, K, depth_scale)`` checked by
    :func:`checked_depth`, or None when neither ``depth`` nor ``K`` is
    given; InvalidCloudError when only one is."""
    if (depth is None) != (K is None):
        raise InvalidCloudError("depth and K go together: give both (the frame the cloud came from) or neither")
    return None if depth is None else (*checked_depth(depth, K, depth_scale), depth_scale)


def checked_mask(mask: object, shape: tuple[int, ...]) -> np.ndarray:
    """``mask`` (bool, or integers: non-zero is the object) as a bool image of
    ``shape``; InvalidCloudError if its shape differs or it holds anything
    else (a float map of probabilities must be thresholded by the caller)."""
    mask = np.asarray(mask)
    if not (mask.dtype == np.bool_ or np.issubdtype(mask.dtype, np.integer)):
        raise InvalidCloudError(
            f"mask must be bool or integer (non-zero: the object), got dtype {mask.dtype}; threshold a float map first"
        )
    mask = mask.astype(bool, copy=False)
    if mask.shape != shape:
        raise InvalidCloudError(f"mask shape {mask.shape} differs from depth shape {shape}")
    return mask


def back_project(depth: np.ndarray, K: np.ndarray, valid: np.ndarray, depth_scale: float) -> np.ndarray:
    """(N, 3) float64 camera-frame points (metres) of the ``valid`` pixels
    with a measured depth (``depth / depth_scale`` finite and positive) of a
    :func:`checked_depth` image, in row-major order (pixel centres, OpenCV).
    Runs in the Rust core without the GIL, on the valid pixels' bounding
    box only (its principal point shifted by the box corner)."""
    return _core.back_project(depth, np.ascontiguousarray(valid, dtype=bool), K, float(depth_scale))


def depth_discontinuities(z: np.ndarray, measured: np.ndarray, where: np.ndarray, max_jump: float) -> np.ndarray:
    """(H, W) bool: pixels of ``where`` with a ``measured`` 8-neighbour whose
    depth differs from theirs by more than ``max_jump`` × their depth ``z``.
    Only the bounding box of ``where`` is examined (fast for one object's mask)."""
    edges = np.zeros(z.shape, dtype=bool)
    rows, cols = np.nonzero(where)
    if len(rows) == 0:
        return edges
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    box_z = np.where(measured, z, np.nan)[max(r0 - 1, 0) : r1 + 1, max(c0 - 1, 0) : c1 + 1]
    padded = np.pad(box_z, 1, constant_values=np.nan)
    centre = padded[1:-1, 1:-1]
    jump = np.zeros(centre.shape, dtype=bool)
    h, w = centre.shape
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                neighbour = padded[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
                with np.errstate(invalid="ignore"):
                    jump |= np.abs(neighbour - centre) > max_jump * centre  # NaN compares False
    top, left = r0 - max(r0 - 1, 0), c0 - max(c0 - 1, 0)
    edges[r0:r1, c0:c1] = jump[top : top + (r1 - r0), left : left + (c1 - c0)] & where[r0:r1, c0:c1]
    return edges


def dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """``mask`` grown by a Euclidean disk of ``radius`` pixels (numpy shifts)."""
    mask = np.asarray(mask, dtype=bool)
    if radius <= 0:
        return mask.copy()
    h, w = mask.shape
    padded = np.pad(mask, radius)
    out = np.zeros_like(mask)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dy * dy + dx * dx <= radius * radius:
                out |= padded[radius + dy : radius + dy + h, radius + dx : radius + dx + w]
    return out


def erode(mask: np.ndarray, radius: int) -> np.ndarray:
    """``mask`` shrunk by a Euclidean disk of ``radius`` pixels (outside the image counts as outside)."""
    mask = np.asarray(mask, dtype=bool)
    if radius <= 0:
        return mask.copy()
    return ~dilate(~np.pad(mask, radius), radius)[radius:-radius, radius:-radius] & mask
