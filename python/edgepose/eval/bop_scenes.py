"""Synthetic datasets in the BOP-scenewise layout: several objects resting
in front of a tilted support plane, rendered with the numpy z-buffer, with a
noisy 16-bit depth image, visible masks and ground truth written exactly as
BOP writes them (millimetres, ``depth_scale``, ``visib_fract``, a targets
file). The tests and the benchmark make their datasets with it; real BOP
datasets are read the same way (:class:`edgepose.eval.bop.BopDataset`).

Meshes are given in metres and written in millimetres; camera frame OpenCV.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from edgepose.eval.bop import MIN_VISIBLE_FRACTION, MM
from edgepose.eval.render import LINEMOD_CAMERA, Camera, _rotation_from_quaternion, rasterize_depth
from edgepose.io import write_png
from edgepose.symmetry import NO_SYMMETRY, Symmetry

if TYPE_CHECKING:
    import trimesh


def write_bop_dataset(
    root: str | os.PathLike,
    meshes: Mapping[int, trimesh.Trimesh],
    *,
    scenes: int = 2,
    images: int = 3,
    objects_per_image: int = 3,
    seed: int = 0,
    camera: Camera = LINEMOD_CAMERA,
    symmetries: Mapping[int, Symmetry] | None = None,
    depth_scales: Sequence[float] = (1.0, 0.1),
    distance: tuple[float, float] = (0.6, 0.9),
    spread: tuple[float, float] = (0.18, 0.3),
    depth_noise: float = 0.001,
) -> Path:
    """Write a dataset of ``scenes`` × ``images`` frames to ``root``: models
    (``meshes`` by BOP object id, metres, written as mm PLYs, with their
    ``symmetries`` in ``models_info.json``), ``test/SCENE/`` folders and
    ``test_targets_bop19.json``. Each frame shows ``objects_per_image``
    instances (object ids cycled, so a frame may hold one object twice) at
    random rotations and ``distance`` metres, on a ring around the image
    centre of radius ``spread`` (fractions of the image's width and height;
    smaller: more crowded); they may hide one another. Scene ``s`` stores depth with BOP ``depth_scale``
    ``depth_scales[s % len(depth_scales)]`` (mm per unit). Returns ``root``."""
    root = Path(root)
    rng = np.random.default_rng(seed)
    symmetries = symmetries or {}
    _write_models(root / "models", meshes, symmetries)
    ids = sorted(meshes)
    targets = []
    for scene_id in range(1, scenes + 1):
        scene_dir = root / "test" / f"{scene_id:06d}"
        depth_scale = float(depth_scales[(scene_id - 1) % len(depth_scales)])
        scene_camera: dict[str, dict] = {}
        scene_gt: dict[str, list] = {}
        scene_gt_info: dict[str, list] = {}
        for im_id in range(images):
            obj_ids = [ids[(im_id + k + scene_id) % len(ids)] for k in range(objects_per_image)]
            poses = _spread_poses(rng, camera, [meshes[o] for o in obj_ids], distance, spread)
            depth, visible, alone = _render_frame(rng, camera, [meshes[o] for o in obj_ids], poses, depth_noise)
            write_png(scene_dir / "depth" / f"{im_id:06d}.png", np.round(depth / MM / depth_scale).astype(np.uint16))
            scene_camera[str(im_id)] = {"cam_K": camera.K.ravel().tolist(), "depth_scale": depth_scale}
            scene_gt[str(im_id)], scene_gt_info[str(im_id)] = [], []
            counts: dict[int, int] = {}
            for gt_id, (obj_id, T) in enumerate(zip(obj_ids, poses)):
                write_png(scene_dir / "mask_visib" / f"{im_id:06d}_{gt_id:06d}.png", visible[gt_id])
                write_png(scene_dir / "mask" / f"{im_id:06d}_{gt_id:06d}.png", alone[gt_id])
                fraction = float(visible[gt_id].sum()) / max(int(alone[gt_id].sum()), 1)
                scene_gt[str(im_id)].append(
                    {
                        "cam_R_m2c": T[:3, :3].ravel().tolist(),
                        "cam_t_m2c": (T[:3, 3] / MM).tolist(),
                        "obj_id": obj_id,
                    }
                )
                rows, cols = np.nonzero(visible[gt_id])
                box = (
                    [int(cols.min()), int(rows.min()), int(np.ptp(cols)) + 1, int(np.ptp(rows)) + 1]
                    if len(rows)
                    else [-1] * 4
                )
                scene_gt_info[str(im_id)].append(
                    {"bbox_visib": box, "px_count_all": int(alone[gt_id].sum()), "visib_fract": fraction}
                )
                if fraction >= MIN_VISIBLE_FRACTION:
                    counts[obj_id] = counts.get(obj_id, 0) + 1
            targets += [
                {"im_id": im_id, "inst_count": n, "obj_id": o, "scene_id": scene_id} for o, n in sorted(counts.items())
            ]
        for name, content in (
            ("scene_camera", scene_camera),
            ("scene_gt", scene_gt),
            ("scene_gt_info", scene_gt_info),
        ):
            (scene_dir / f"{name}.json").write_text(json.dumps(content, indent=1))
    (root / "test_targets_bop19.json").write_text(json.dumps(targets, indent=1))
    return root


def _write_models(folder: Path, meshes: Mapping[int, trimesh.Trimesh], symmetries: Mapping[int, Symmetry]) -> None:
    """``obj_OBJID.ply`` (mm) and ``models_info.json`` (mm, BOP's keys)."""
    folder.mkdir(parents=True, exist_ok=True)
    info = {}
    for obj_id, mesh in sorted(meshes.items()):
        scaled = mesh.copy()
        scaled.apply_scale(1.0 / MM)
        scaled.export(folder / f"obj_{obj_id:06d}.ply")
        vertices = np.asarray(scaled.vertices)
        lo, size = vertices.min(0), np.ptp(vertices, axis=0)
        hull = np.asarray(scaled.convex_hull.vertices)
        # The largest distance between two vertices (they lie on the hull), a few hull rows at a time.
        diameter = max(
            float(np.linalg.norm(hull[i : i + 256, None] - hull[None], axis=2).max()) for i in range(0, len(hull), 256)
        )
        entry: dict[str, object] = {
            "diameter": diameter,
            **{f"min_{a}": float(v) for a, v in zip("xyz", lo)},
            **{f"size_{a}": float(v) for a, v in zip("xyz", size)},
        }
        symmetry = symmetries.get(obj_id, NO_SYMMETRY)
        if len(symmetry.discrete):
            discrete = symmetry.discrete.copy()
            discrete[:, :3, 3] /= MM
            entry["symmetries_discrete"] = discrete.reshape(-1, 16).tolist()
        if len(symmetry.continuous):
            entry["symmetries_continuous"] = [
                {"axis": row[:3].tolist(), "offset": (row[3:] / MM).tolist()} for row in symmetry.continuous
            ]
        info[str(obj_id)] = entry
    (folder / "models_info.json").write_text(json.dumps(info, indent=1))


def _spread_poses(
    rng: np.random.Generator,
    camera: Camera,
    meshes: Sequence[trimesh.Trimesh],
    distance: tuple[float, float],
    spread: tuple[float, float],
) -> list[np.ndarray]:
    """A random ``T_cam_obj`` per mesh: uniformly random rotation, the
    bounding-box centre on its own ray, the rays spread evenly around the
    image centre (a ring of radius drawn from ``spread`` × the image's size,
    jittered), at a depth drawn from ``distance``."""
    poses = []
    start = rng.uniform(0, 2 * np.pi)
    for k, mesh in enumerate(meshes):
        vertices = np.asarray(mesh.vertices)
        centre = vertices.min(0) / 2 + vertices.max(0) / 2
        q = rng.normal(size=4)
        R = _rotation_from_quaternion(q / np.linalg.norm(q))
        angle = start + 2 * np.pi * k / len(meshes) + rng.uniform(-0.3, 0.3)
        radius = 0.0 if len(meshes) == 1 else rng.uniform(*spread)
        u = camera.cx + radius * camera.width * np.cos(angle)
        v = camera.cy + radius * camera.height * np.sin(angle)
        z = rng.uniform(*distance)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = np.array([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z]) - R @ centre
        poses.append(T)
    return poses


def _render_frame(
    rng: np.random.Generator,
    camera: Camera,
    meshes: Sequence[trimesh.Trimesh],
    poses: Sequence[np.ndarray],
    depth_noise: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(depth (H, W) metres with 1 mm steps and noise, 0: none; visible
    (O, H, W) bool; alone (O, H, W) bool: each object's full silhouette)``.
    A support plane 3–8 cm behind the farthest object, tilted ≤ 25°, fills
    the background."""
    z_objects = np.stack(
        [
            rasterize_depth(np.asarray(m.vertices) @ T[:3, :3].T + T[:3, 3], np.asarray(m.faces), camera)
            for m, T in zip(meshes, poses)
        ]
    )
    alone = np.isfinite(z_objects)
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    rays = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(u.shape)], axis=-1)
    tilt = np.radians(rng.uniform(0, 25))
    normal = np.array([0.0, -np.sin(tilt), -np.cos(tilt)])  # faces the camera, leaning back
    farthest = float(z_objects[alone].max()) if alone.any() else 1.0
    offset = normal @ np.array([0.0, 0.0, farthest + rng.uniform(0.03, 0.08)])
    with np.errstate(divide="ignore", invalid="ignore"):
        z_plane = offset / (rays @ normal)
    z_plane[~(z_plane > 0)] = np.inf
    z_all = np.concatenate([z_objects, z_plane[None]])
    nearest = np.argmin(z_all, axis=0)
    z = np.take_along_axis(z_all, nearest[None], axis=0)[0]
    measured = np.isfinite(z) & (rng.random(z.shape) >= 0.01)
    depth = np.where(measured, z + rng.normal(0.0, depth_noise, z.shape), 0.0)
    depth = np.clip(np.round(depth / MM) * MM, 0.0, None)
    visible = np.stack([(nearest == i) & alone[i] for i in range(len(meshes))])
    return depth, visible, alone
