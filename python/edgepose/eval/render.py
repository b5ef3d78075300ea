"""Synthetic depth views of a mesh: a numpy z-buffer rasterizer, a pinhole
camera and simple depth-sensor effects (noise, quantisation, dropout,
occluders), giving segmented object clouds with known poses.

Units are metres; the camera frame is OpenCV's (x right, y down, z forward).
Pixel convention (OpenCV): the pixel in row ``v`` and column ``u`` has its
centre at image coordinates ``(u, v)``; a camera point ``p`` projects to
``u = fx·x/z + cx``, ``v = fy·y/z + cy``, and back-projection inverts exactly
that: ``x = (u − cx)·z/fx``, ``y = (v − cy)·z/fy``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from edgepose.cloud import cloud_from_depth

if TYPE_CHECKING:
    import trimesh

#: Triangles with a vertex closer to the camera than this (metres) are skipped.
NEAR_PLANE = 0.01
#: Candidate (triangle, pixel) pairs rasterized at once: bounds memory to ~0.5 GB.
_CANDIDATES_PER_BATCH = 2_000_000


@dataclass(frozen=True)
class Camera:
    """Pinhole camera intrinsics: focal lengths and principal point in pixels,
    image size in pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


#: The LINEMOD / Occlusion-LINEMOD Kinect camera (640 × 480).
LINEMOD_CAMERA = Camera(572.4, 573.6, 325.3, 242.0, 640, 480)


@dataclass(frozen=True, eq=False)
class RenderedView:
    """One synthetic depth frame of an object with its true pose."""

    cloud: np.ndarray
    """(N, 3) float64 camera-frame points, metres: the object's visible pixels
    (``mask``) back-projected from ``depth``."""
    T_cam_obj: np.ndarray
    """(4, 4) float64 true pose, object (mesh) frame → camera frame."""
    depth: np.ndarray
    """(H, W) float32 depth (z, metres) of the scene (object and occluders)
    with sensor effects; 0 where there is no measurement."""
    mask: np.ndarray
    """(H, W) bool: pixels where the object is visible and has a depth
    measurement (a perfect segmentation of the object)."""
    camera: Camera


def random_pose(
    rng: np.random.Generator,
    camera: Camera = LINEMOD_CAMERA,
    distance: tuple[float, float] = (0.45, 0.9),
    centre: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> np.ndarray:
    """Random ``T_cam_obj`` (4, 4): uniformly random rotation, and the object
    point ``centre`` (object frame, metres; e.g. the bounding-box centre) at a
    depth drawn uniformly from ``distance`` (metres), projecting to a pixel
    drawn uniformly from the central 50 % of the image (the middle half of
    each axis), so objects up to ~30 cm stay mostly or wholly in view."""
    quaternion = rng.normal(size=4)  # an isotropic 4-vector: a uniform unit quaternion
    R = _rotation_from_quaternion(quaternion / np.linalg.norm(quaternion))
    z = rng.uniform(*distance)
    u = rng.uniform(0.25, 0.75) * camera.width
    v = rng.uniform(0.25, 0.75) * camera.height
    centre_cam = np.array([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre_cam - R @ np.asarray(centre, dtype=np.float64)
    return T


def render_view(
    mesh: trimesh.Trimesh,
    *,
    T_cam_obj: np.ndarray | None = None,
    seed: int = 0,
    camera: Camera = LINEMOD_CAMERA,
    distance: tuple[float, float] = (0.45, 0.9),
    depth_noise: float = 0.001,
    quantization: float = 0.001,
    dropout: float = 0.02,
    occluders: int = 0,
) -> RenderedView:
    """Depth view of ``mesh`` (metres) posed by ``T_cam_obj`` (a
    :func:`random_pose` about the bounding-box centre when ``None``).

    Sensor effects, in this order and all drawn from
    ``np.random.default_rng(seed)``: ``occluders`` flat rectangles facing the
    camera, in front of the object, each hiding 20–50 % of the object's
    extent around one of its pixels; Gaussian depth noise of std
    ``depth_noise`` metres; rounding to multiples of ``quantization`` metres;
    loss of each measurement with probability ``dropout``. Zero turns an
    effect off."""
    rng = np.random.default_rng(seed)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if T_cam_obj is None:
        T_cam_obj = random_pose(rng, camera, distance, centre=vertices.min(0) / 2 + vertices.max(0) / 2)
    T_cam_obj = np.asarray(T_cam_obj, dtype=np.float64)
    if T_cam_obj.shape != (4, 4):
        raise ValueError(f"T_cam_obj must have shape (4, 4), got {T_cam_obj.shape}")

    depth = rasterize_depth(vertices @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3], faces, camera)
    visible = np.isfinite(depth)
    for _ in range(occluders):
        _add_occluder(depth, visible, rng)
    measured = np.isfinite(depth)
    if depth_noise > 0:
        depth[measured] += rng.normal(0.0, depth_noise, size=int(measured.sum()))
    if quantization > 0:
        depth[measured] = np.round(depth[measured] / quantization) * quantization
    if dropout > 0:
        measured &= rng.random(depth.shape) >= dropout
    measured &= depth > 0
    depth = np.where(measured, depth, 0.0).astype(np.float32)
    mask = visible & measured
    return RenderedView(depth_to_cloud(depth, camera, mask), T_cam_obj, depth, mask, camera)


def rasterize_depth(vertices_cam: np.ndarray, faces: np.ndarray, camera: Camera) -> np.ndarray:
    """(H, W) float64 z-buffer of triangles given by camera-frame vertices
    ((V, 3), metres) and ``faces`` ((F, 3) indices): the nearest surface's
    depth at each pixel centre, ``inf`` where no triangle covers it.

    Both faces of every triangle are drawn (no back-face culling). Depth is
    perspective-correct: 1/z is interpolated with screen-space barycentric
    weights, which is exact for planar triangles."""
    height, width = camera.height, camera.width
    tri = vertices_cam[faces]  # (F, 3 corners, 3)
    z = tri[:, :, 2]
    tri = tri[(z > NEAR_PLANE).all(axis=1)]
    z = tri[:, :, 2]
    u = camera.fx * tri[:, :, 0] / z + camera.cx
    v = camera.fy * tri[:, :, 1] / z + camera.cy
    # Pixel centres (integer coordinates) inside each clipped bounding box.
    u_lo = np.maximum(np.ceil(u.min(1)), 0).astype(np.int64)
    u_hi = np.minimum(np.floor(u.max(1)), width - 1).astype(np.int64)
    v_lo = np.maximum(np.ceil(v.min(1)), 0).astype(np.int64)
    v_hi = np.minimum(np.floor(v.max(1)), height - 1).astype(np.int64)
    area = (u[:, 1] - u[:, 0]) * (v[:, 2] - v[:, 0]) - (u[:, 2] - u[:, 0]) * (v[:, 1] - v[:, 0])
    keep = (u_lo <= u_hi) & (v_lo <= v_hi) & (np.abs(area) > 1e-12)
    u, v, inv_z, area = u[keep], v[keep], 1.0 / z[keep], area[keep]
    u_lo, u_hi, v_lo, v_hi = u_lo[keep], u_hi[keep], v_lo[keep], v_hi[keep]
    box_width = u_hi - u_lo + 1
    counts = box_width * (v_hi - v_lo + 1)

    zbuffer = np.full(height * width, np.inf)
    ends = np.cumsum(counts)
    start = 0
    while start < len(counts):
        # The next batch of triangles: at most _CANDIDATES_PER_BATCH pixels (at least one triangle).
        base = ends[start - 1] if start else 0
        stop = max(int(np.searchsorted(ends, base + _CANDIDATES_PER_BATCH, side="right")), start + 1)
        batch = np.arange(start, stop)
        t = np.repeat(batch, counts[batch])
        offset = np.arange(len(t)) - np.repeat(ends[batch] - counts[batch] - base, counts[batch])
        pu = (u_lo[t] + offset % box_width[t]).astype(np.float64)
        pv = (v_lo[t] + offset // box_width[t]).astype(np.float64)
        du, dv = pu - u[t, 0], pv - v[t, 0]
        w1 = (du * (v[t, 2] - v[t, 0]) - (u[t, 2] - u[t, 0]) * dv) / area[t]
        w2 = ((u[t, 1] - u[t, 0]) * dv - du * (v[t, 1] - v[t, 0])) / area[t]
        w0 = 1.0 - w1 - w2
        inside = (w0 >= -1e-9) & (w1 >= -1e-9) & (w2 >= -1e-9)
        t, w0, w1, w2 = t[inside], w0[inside], w1[inside], w2[inside]
        depth = 1.0 / (w0 * inv_z[t, 0] + w1 * inv_z[t, 1] + w2 * inv_z[t, 2])
        pixel = pv[inside].astype(np.int64) * width + pu[inside].astype(np.int64)
        np.minimum.at(zbuffer, pixel, depth)
        start = stop
    return zbuffer.reshape(height, width)


def depth_to_cloud(
    depth: np.ndarray,
    camera: Camera,
    mask: np.ndarray | None = None,
    depth_scale: float = 1.0,
) -> np.ndarray:
    """(N, 3) float64 camera-frame points (metres) of the pixels with a
    positive, finite depth (and ``mask`` true, when given), in row-major
    pixel order. ``depth / depth_scale`` is metres (``depth_scale=1000`` for
    uint16 millimetre images, as in Open3D)."""
    depth = np.asarray(depth)
    if depth.shape != (camera.height, camera.width):
        raise ValueError(f"depth must have shape {(camera.height, camera.width)}, got {depth.shape}")
    return cloud_from_depth(depth, camera.K, mask, depth_scale)


def _add_occluder(depth: np.ndarray, visible: np.ndarray, rng: np.random.Generator) -> None:
    """Put a flat rectangle facing the camera in front of the object, hiding
    20–50 % of the object's pixel extent (per axis) around one of its
    visible pixels. Updates ``depth`` (inf where empty) and ``visible`` in place."""
    rows, cols = np.nonzero(visible)
    if len(rows) == 0:
        return
    pick = rng.integers(len(rows))
    half_h = rng.uniform(0.1, 0.25) * (np.ptp(rows) + 1)
    half_w = rng.uniform(0.1, 0.25) * (np.ptp(cols) + 1)
    z = rng.uniform(0.5, 0.95) * float(depth[visible].min())
    r0, r1 = max(int(rows[pick] - half_h), 0), int(rows[pick] + half_h) + 1
    c0, c1 = max(int(cols[pick] - half_w), 0), int(cols[pick] + half_w) + 1
    depth[r0:r1, c0:c1] = np.minimum(depth[r0:r1, c0:c1], z)
    visible[r0:r1, c0:c1] = False


def _rotation_from_quaternion(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of a unit quaternion ``(w, x, y, z)``."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
