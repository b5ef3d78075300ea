"""Stressed synthetic scenes: the object in front of a support plane (or
resting on it, a table) beside other objects, occluded by solid shapes,
seen by a noisy sensor and cut out by an imperfect detector mask.

:func:`render_scene` renders one view of a mesh at one stress level
(:data:`edgepose.eval.stress.STRESS_LEVELS`, re-exported here). Units are
metres; the camera frame is OpenCV's (x right, y down, z forward); poses are
``T_cam_obj``. Every random choice comes from ``np.random.default_rng(seed)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from edgepose.cloud import cloud_from_depth
from edgepose.eval.render import LINEMOD_CAMERA, Camera, random_pose, rasterize_depth, render_view
from edgepose.eval.sensor import detector_mask, mix_spill_ring, recorded, sensed
from edgepose.eval.stress import STRESS_LEVELS, TABLE_ELEVATION_DEG, Stress, noise_sigma

if TYPE_CHECKING:
    import trimesh

__all__ = ["MAX_RANGE", "STRESS_LEVELS", "SceneView", "Stress", "noise_sigma", "render_scene"]

#: Background farther than this (metres) is out of the sensor's range: no measurement.
MAX_RANGE = 8.0
#: Occluder bisection stops within this distance of the target visible fraction.
_BISECT_TOLERANCE = 0.01


@dataclass(frozen=True, eq=False)
class SceneView:
    """One stressed depth frame of an object with its true pose."""

    cloud: np.ndarray
    """(N, 3) float64 camera-frame points, metres: ``edgepose.cloud_from_depth`` of the depth image
    (as uint16 millimetres, the library defaults) under the detector ``mask``."""
    depth: np.ndarray
    """(H, W) float32 depth of the whole scene with sensor effects, metres; 0: no measurement."""
    K: np.ndarray
    """(3, 3) float64 intrinsics."""
    mask: np.ndarray
    """(H, W) bool detector mask (what the pose method is given)."""
    true_mask: np.ndarray
    """(H, W) bool pixels where the object is truly visible (in front of everything else)."""
    T_cam_obj: np.ndarray
    """(4, 4) float64 true pose."""
    visible_fraction: float
    """Achieved visible pixels / the object's pixels when rendered alone."""
    spill_fraction: float
    """Cloud points off the object (mask outside ``true_mask``) / cloud points on it."""
    ideal_depth: np.ndarray
    """(H, W) float32 noise-free scene z-buffer, metres; inf where empty."""
    flying_mask: np.ndarray
    """(H, W) bool mixed pixels (depth between the object's and the background's)."""
    stress: str
    camera: Camera
    support: tuple[np.ndarray, float] | None = None
    """The support plane n·x = offset (camera frame, metres; unit n towards
    the camera): the table under a resting object, else the wall behind it;
    None without a background."""


def render_scene(
    mesh: trimesh.Trimesh,
    stress: Stress | str = "clean",
    seed: int = 0,
    *,
    T_cam_obj: np.ndarray | None = None,
    camera: Camera = LINEMOD_CAMERA,
    neighbours: Sequence[trimesh.Trimesh] = (),
    occluders: Sequence[trimesh.Trimesh] = (),
) -> SceneView:
    """A view of ``mesh`` (metres) at ``stress`` (a :class:`Stress` or a
    :data:`STRESS_LEVELS` name). The pose is ``T_cam_obj`` or, when ``None``,
    :func:`random_pose` drawn first from the seed's generator, as
    :func:`render_view` draws it (same seed and distance → same pose).

    Scene: a support plane 2–6 cm behind the object's farthest point, facing
    the camera tilted by up to 30° (when ``stress.resting``: a table under the
    object, touching it, seen from ``TABLE_ELEVATION_DEG`` above, the object
    drawn in one of its stable poses on it); 1–3 neighbours (boxes, cylinders or
    ``neighbours`` meshes) beside the object, never in front of it; when
    ``stress.visible < 1`` an occluder (box, cylinder or one of
    ``occluders``, scaled to span the object) between camera and object, slid
    in from a random side by bisection until the visible fraction is within
    1 % of the target (or as close as its shape allows). Then lateral jitter
    and depth noise, mixed pixels in the spill ring, 1 mm quantisation and
    dropout; the detector mask is the true visible mask dilated, eroded
    and/or cut."""
    stress = STRESS_LEVELS[stress] if isinstance(stress, str) else stress
    if not stress.background:
        return _plain_view(mesh, stress, seed, T_cam_obj, camera)
    rng = np.random.default_rng(seed)  # every draw below, in this order: a seed is one scene
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    box_centre = vertices.min(0) / 2 + vertices.max(0) / 2
    T_cam_obj, up = _scene_pose(mesh, stress, rng, camera, T_cam_obj, box_centre)
    posed = vertices @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    centre = T_cam_obj[:3, :3] @ box_centre + T_cam_obj[:3, 3]
    z_obj = rasterize_depth(posed, np.asarray(mesh.faces), camera)
    alone = np.isfinite(z_obj)
    normal, offset = _support_plane(stress, posed, centre, up, rng)
    rays, z_rest = _plane_depth(camera, normal, offset)
    z_rest = _with_neighbours(z_rest, z_obj, centre, camera, rng, neighbours)

    visible = alone & (z_obj < z_rest)
    z_scene = np.minimum(z_obj, z_rest)
    if stress.visible < 1.0 and visible.any():
        z_occ = _occlude(stress.visible, z_obj, visible, centre, camera, rng, occluders)
        visible &= z_obj < z_occ
        z_scene = np.minimum(z_scene, z_occ)
    visible_fraction = float(visible.sum()) / max(int(alone.sum()), 1)
    ideal = z_scene.astype(np.float32)

    depth, measured = sensed(z_scene, stress, camera, rng)
    mask = detector_mask(visible, stress, camera, rng)
    flying = mix_spill_ring(depth, mask, visible, measured, z_obj, stress, rng)
    depth, measured = recorded(depth, measured, ideal, rays, visible, stress, rng)
    depth_mm = np.round(depth.astype(np.float64) * 1000.0).astype(np.uint16)
    on_object = int((mask & visible & measured).sum())
    spilled = int((mask & ~visible & measured).sum())
    return SceneView(
        cloud=cloud_from_depth(depth_mm, camera.K, mask),
        depth=depth,
        K=camera.K,
        mask=mask,
        true_mask=visible,
        T_cam_obj=T_cam_obj,
        visible_fraction=visible_fraction,
        spill_fraction=spilled / max(on_object, 1),
        ideal_depth=ideal,
        flying_mask=flying & measured,
        stress=stress.name,
        camera=camera,
        support=(normal, offset),
    )


def _scene_pose(
    mesh: trimesh.Trimesh,
    stress: Stress,
    rng: np.random.Generator,
    camera: Camera,
    T_cam_obj: np.ndarray | None,
    box_centre: np.ndarray,
) -> tuple[np.ndarray, np.ndarray | None]:
    """The object's pose (``T_cam_obj`` or drawn as :func:`render_view` draws
    it; resting on the table when ``stress.resting``) and, for a table, its
    upward normal in the camera frame (seen from the elevation drawn)."""
    up = None
    if stress.resting:
        elevation = np.radians(rng.uniform(*TABLE_ELEVATION_DEG))
        up = np.array([0.0, -np.cos(elevation), -np.sin(elevation)])
    if T_cam_obj is None:
        T_cam_obj = random_pose(rng, camera, stress.distance, centre=box_centre)
        if up is not None:  # same box centre in the camera frame, turned to rest on the table
            R = _resting_rotation(mesh, up, rng)
            T_cam_obj[:3, 3] += (T_cam_obj[:3, :3] - R) @ box_centre
            T_cam_obj[:3, :3] = R
    return np.asarray(T_cam_obj, dtype=np.float64), up


def _support_plane(
    stress: Stress, posed: np.ndarray, centre: np.ndarray, up: np.ndarray | None, rng: np.random.Generator
) -> tuple[np.ndarray, float]:
    """The support plane ``n·x = offset`` (camera frame, metres): a table
    under the object touching its lowest point (``up``), or a wall 2–6 cm
    behind it facing the camera tilted by up to 30°."""
    import trimesh.transformations as tf

    if stress.resting and up is not None:
        return up, float((posed @ up).min())
    toward = -centre / np.linalg.norm(centre)
    axis = np.cross(toward, rng.normal(size=3))
    tilt = tf.rotation_matrix(np.radians(rng.uniform(0, 30)), axis / np.linalg.norm(axis))[:3, :3]
    normal = tilt @ toward
    return normal, float((posed @ normal).min() - rng.uniform(0.02, 0.06))


def _plane_depth(camera: Camera, normal: np.ndarray, offset: float) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's ray (H, W, 3; z = 1) and the plane's depth along it
    (H, W; inf where the ray misses it or meets it beyond ``MAX_RANGE``)."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    rays = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(u.shape)], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        z_rest = offset / (rays @ normal)
    z_rest[~((z_rest > 0) & (z_rest < MAX_RANGE))] = np.inf
    return rays, z_rest


def _with_neighbours(
    z_rest: np.ndarray,
    z_obj: np.ndarray,
    centre: np.ndarray,
    camera: Camera,
    rng: np.random.Generator,
    neighbours: Sequence[trimesh.Trimesh],
) -> np.ndarray:
    """``z_rest`` with 1–3 neighbours (boxes, cylinders or ``neighbours``
    meshes) beside the object, each pushed out until it hides no object pixel."""
    import trimesh.transformations as tf

    u, v = _project(centre, camera)
    rows, cols = np.nonzero(np.isfinite(z_obj))
    count = int(rng.integers(1, 4)) if len(rows) else 0
    start = rng.uniform(0, 2 * np.pi)
    for k in range(count):
        nb = _primitive(rng, list(neighbours))
        nb_vertices = np.asarray(nb.vertices) @ tf.random_rotation_matrix(rng.random(3))[:3, :3].T
        nb_vertices -= nb_vertices.min(0) / 2 + nb_vertices.max(0) / 2
        angle = start + 2 * np.pi * k / count + rng.uniform(-0.4, 0.4)
        e = np.array([np.cos(angle), np.sin(angle), 0.0])
        r_obj = ((cols - u) * e[0] + (rows - v) * e[1]).max() * centre[2] / camera.fx
        lateral = r_obj + (nb_vertices @ e).max() + rng.uniform(-0.005, 0.02)
        depth_shift = rng.uniform(-0.01, 0.05)
        r0, c0 = rows.min(), cols.min()
        box = _crop(camera, r0, rows.max() + 1, c0, cols.max() + 1)
        for _ in range(8):
            moved = nb_vertices + centre + lateral * e + [0, 0, depth_shift]
            if not (rasterize_depth(moved, nb.faces, box) < z_obj[r0 : r0 + box.height, c0 : c0 + box.width]).any():
                z_rest = np.minimum(z_rest, rasterize_depth(moved, nb.faces, camera))
                break
            lateral += 0.01 + 0.2 * lateral
    return z_rest


def _plain_view(mesh, stress: Stress, seed: int, T_cam_obj, camera: Camera) -> SceneView:
    """``render_view``'s view as a SceneView (the ``clean`` level: identical clouds)."""
    view = render_view(
        mesh,
        T_cam_obj=T_cam_obj,
        seed=seed,
        camera=camera,
        distance=stress.distance,
        depth_noise=stress.depth_noise,
        quantization=stress.quantization,
        dropout=stress.dropout,
    )
    alone = np.isfinite(
        rasterize_depth(
            np.asarray(mesh.vertices, dtype=np.float64) @ view.T_cam_obj[:3, :3].T + view.T_cam_obj[:3, 3],
            np.asarray(mesh.faces),
            camera,
        )
    )
    ideal = np.where(alone, view.depth, np.inf).astype(np.float32)
    return SceneView(
        cloud=view.cloud,
        depth=view.depth,
        K=camera.K,
        mask=view.mask,
        true_mask=alone,
        T_cam_obj=view.T_cam_obj,
        visible_fraction=1.0,
        spill_fraction=0.0,
        ideal_depth=ideal,
        flying_mask=np.zeros_like(alone),
        stress=stress.name,
        camera=camera,
    )


def _occlude(target, z_obj, visible, centre, camera, rng, meshes) -> np.ndarray:
    """Depth image of one occluder between camera and object, slid along a
    random image direction so that ``visible`` keeps ``target`` of the
    object's unoccluded pixels (bisection on the offset)."""
    import trimesh
    import trimesh.transformations as tf

    rows, cols = np.nonzero(visible)
    u, v = _project(centre, camera)
    angle = rng.uniform(0, 2 * np.pi)
    e = np.array([np.cos(angle), np.sin(angle), 0.0])  # slide direction (camera x-y plane)
    along = (cols - u) * e[0] + (rows - v) * e[1]
    across = (rows - v) * e[0] - (cols - u) * e[1]
    front = float(z_obj[visible].min())
    gap = rng.uniform(0.02, 0.10)
    kind = int(rng.integers(0, 2 + len(meshes)))
    grow = rng.uniform(1.2, 1.6)
    # Occluder size in pixels, then metres at its depth.
    width_px = (np.ptp(along) + 8) * grow
    height_px = (np.ptp(across) + 8) * rng.uniform(1.2, 1.6)
    if kind == 0:  # a box (a panel, a carton)
        thickness = rng.uniform(0.02, 0.08)
        z_occ = max(front - gap - thickness / 2, 0.15)
        occluder = trimesh.creation.box(
            extents=[width_px * z_occ / camera.fx, height_px * z_occ / camera.fy, thickness]
        )
    elif kind == 1:  # a cylinder (a bottle, a pole) across the slide direction
        a = width_px / camera.fx
        z_occ = max((front - gap) / (1 + a / 2), 0.15)
        occluder = trimesh.creation.cylinder(radius=a * z_occ / 2, height=height_px * z_occ / camera.fy, sections=32)
        occluder.apply_transform(tf.rotation_matrix(np.pi / 2, [1, 0, 0]))  # axis along y
    else:  # a given mesh, scaled to span the object
        occluder = meshes[kind - 2].copy()
        occluder.apply_translation(-occluder.bounds.mean(0))
        ext = occluder.extents
        z_occ = front - gap
        for _ in range(2):
            scale = max(width_px * z_occ / camera.fx / ext[0], height_px * z_occ / camera.fy / ext[1])
            z_occ = max(front - gap - scale * ext[2] / 2, 0.15)
        occluder.apply_scale(scale)
    R = tf.rotation_matrix(angle, [0, 0, 1])[:3, :3]
    tilt = tf.rotation_matrix(np.radians(rng.uniform(-15, 15)), rng.normal(size=3))[:3, :3]
    local = np.asarray(occluder.vertices) @ (R @ tilt).T
    faces = np.asarray(occluder.faces)
    base = np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0]) * z_occ
    # While bisecting, rasterize only the object's bounding box, every other pixel when it is large.
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    step = 2 if (r1 - r0) * (c1 - c0) > 10_000 else 1
    crop = _crop(camera, r0, r1, c0, c1, step)
    vis_crop, z_crop = visible[r0:r1:step, c0:c1:step], z_obj[r0:r1:step, c0:c1:step]
    n_alone = max(int(np.isfinite(z_crop).sum()), 1)

    def fraction(offset_px: float) -> float:
        z = rasterize_depth(local + base + e * offset_px * z_occ / camera.fx, faces, crop)
        return int((vis_crop & (z_crop < z)).sum()) / n_alone

    lo = (along.min() + along.max()) / 2  # occluder centred on the object: all of it hidden
    hi = along.max() + width_px / 2 + 4  # leading edge past the object: nothing hidden
    for _ in range(24):
        mid = (lo + hi) / 2
        f = fraction(mid)
        if abs(f - target) <= _BISECT_TOLERANCE:
            break
        lo, hi = (mid, hi) if f < target else (lo, mid)
    return rasterize_depth(local + base + e * mid * z_occ / camera.fx, faces, camera)


def _crop(camera: Camera, r0: int, r1: int, c0: int, c1: int, step: int = 1) -> Camera:
    """The camera seeing rows r0:r1:step, columns c0:c1:step of ``camera``'s image."""
    return Camera(
        camera.fx / step,
        camera.fy / step,
        (camera.cx - c0) / step,
        (camera.cy - r0) / step,
        -(-(c1 - c0) // step),
        -(-(r1 - r0) // step),
    )


def _primitive(rng: np.random.Generator, meshes: list) -> trimesh.Trimesh:
    """A neighbour: a random box (4–15 cm sides), cylinder (2–5 cm radius, 6–20 cm
    high) or one of ``meshes``."""
    import trimesh

    kind = int(rng.integers(0, 2 + len(meshes)))
    if kind >= 2:
        return meshes[kind - 2]
    if kind == 0:
        return trimesh.creation.box(extents=rng.uniform(0.04, 0.15, size=3))
    return trimesh.creation.cylinder(radius=rng.uniform(0.02, 0.05), height=rng.uniform(0.06, 0.2), sections=24)


def _resting_rotation(mesh: trimesh.Trimesh, up: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(3, 3) rotation object → camera of ``mesh`` resting on a table whose
    normal is ``up`` (camera frame): one of its stable poses
    (:func:`_stable_poses`), drawn by how likely it lands in it, turned
    about the normal by a random angle."""
    import trimesh.transformations as tf

    rests, chances = _stable_poses(mesh)
    rest = rests[rng.choice(len(rests), p=chances)]  # object → table, z up
    spin = tf.rotation_matrix(rng.uniform(0, 2 * np.pi), [0.0, 0.0, 1.0])[:3, :3]
    across = np.array([1.0, 0.0, 0.0])  # the table's x axis: the image's rows
    table = np.column_stack([across, np.cross(up, across), up])  # table → camera
    return table @ spin @ rest


#: :func:`_stable_poses` by ``mesh.identifier_hash`` (0.1–1 s each to find).
_STABLE_POSES: dict[str, tuple[np.ndarray, np.ndarray]] = {}


def _stable_poses(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """(P, 3, 3) rotations object → table (z up) in which ``mesh`` rests on
    a face of its convex hull, and (P,) the chance it lands in each
    (``trimesh.poses.compute_stable_poses`` about its centre of mass, or the
    hull's when that lies outside the hull). A mesh without volume (a sheet)
    lies flat, its thinnest direction up."""
    import trimesh

    key = mesh.identifier_hash
    if key not in _STABLE_POSES:
        hull = mesh.convex_hull

        def inside(c: np.ndarray) -> bool:  # strictly inside every face of the hull
            behind = np.einsum("ij,ij->i", c - hull.triangles_center, hull.face_normals) < 0
            return bool(np.all(np.isfinite(c)) and np.all(behind))

        centre = np.asarray(mesh.center_mass, dtype=np.float64)
        if not inside(centre):
            centre = np.asarray(hull.center_mass, dtype=np.float64)
        if inside(centre):  # (trimesh samples centres until one is inside the hull)
            rests, chances = trimesh.poses.compute_stable_poses(hull, center_mass=centre)
            rests = np.asarray(rests)[:, :3, :3]
        else:
            vertices = np.asarray(mesh.vertices, dtype=np.float64)
            axes = np.linalg.svd(vertices - vertices.mean(0))[2]  # rows: principal directions, thinnest last
            axes[0] *= np.sign(np.linalg.det(axes))
            rests, chances = axes[None], np.ones(1)
        if len(_STABLE_POSES) >= 256:
            _STABLE_POSES.clear()
        _STABLE_POSES[key] = (rests, np.asarray(chances) / np.sum(chances))
    return _STABLE_POSES[key]


def _project(p: np.ndarray, camera: Camera) -> tuple[float, float]:  # pixel (u, v) of a camera-frame point
    return camera.fx * p[0] / p[2] + camera.cx, camera.fy * p[1] / p[2] + camera.cy
