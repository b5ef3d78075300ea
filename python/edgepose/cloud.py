"""Observed point clouds: validation, cleaning and back-projection from depth.

Clouds are (N, 3) arrays in metres, camera frame (OpenCV: x right, y down,
z forward), already segmented to one object.
"""

from __future__ import annotations

import numpy as np

from edgepose.errors import InvalidCloudError

#: Fewer valid points than this cannot give a pose.
MIN_POINTS = 32


def as_cloud(cloud: object) -> np.ndarray:
    """(N, 3) float64 copy of ``cloud`` (an array or anything with ``.points``,
    e.g. an Open3D point cloud) with NaN/inf rows dropped."""
    points = getattr(cloud, "points", cloud)
    try:
        array = np.asarray(points)
    except Exception as e:
        raise InvalidCloudError(f"cloud is not array-like ({type(cloud).__name__}: {e})") from None
    if array.ndim != 2 or array.shape[1] != 3:
        raise InvalidCloudError(f"cloud must have shape (N, 3), got {array.shape}")
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise InvalidCloudError(f"cloud must hold numbers, got dtype {array.dtype}")
    array = array.astype(np.float64)
    finite = np.isfinite(array).all(axis=1)
    if finite.sum() < MIN_POINTS:
        raise InvalidCloudError(
            f"cloud has {int(finite.sum())} finite points of {len(array)}; at least {MIN_POINTS} are needed"
        )
    return array[finite]


def cloud_from_depth(
    depth: np.ndarray,
    K: np.ndarray,
    mask: np.ndarray | None = None,
    depth_scale: float = 1000.0,
) -> np.ndarray:
    """(N, 3) float64 camera-frame points (metres) of the pixels with a valid
    depth (and ``mask`` true, when given), in row-major order.

    ``K`` is the 3×3 pinhole matrix; a pixel (row v, column u) has its centre
    at (u, v) (OpenCV). ``depth / depth_scale`` is metres, as in Open3D:
    1000 for uint16 millimetre images, 1 for float metres."""
    depth = np.asarray(depth)
    K = np.asarray(K, dtype=np.float64)
    if depth.ndim != 2:
        raise InvalidCloudError(f"depth must be a 2-D image, got shape {depth.shape}")
    if K.shape != (3, 3):
        raise InvalidCloudError(f"K must be 3×3, got {K.shape}")
    z = depth.astype(np.float64) / depth_scale
    valid = np.isfinite(z) & (z > 0)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != depth.shape:
            raise InvalidCloudError(f"mask shape {mask.shape} differs from depth shape {depth.shape}")
        valid &= mask
    v, u = np.nonzero(valid)
    z = z[v, u]
    x = (u - K[0, 2]) * z / K[0, 0]
    y = (v - K[1, 2]) * z / K[1, 1]
    return np.stack([x, y, z], axis=1)
