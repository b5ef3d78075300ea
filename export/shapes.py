"""Training shapes: the shared training meshes plus procedural compositions of
primitives, each scaled to a random real-object size and turned into a
standard model. Never the YCB objects: those are the unseen test set."""

from __future__ import annotations

from pathlib import Path

import edgepose
import numpy as np
import trimesh
from edgepose.model import read_mesh

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
#: Object diameters drawn for training shapes, metres (household objects).
DIAMETER_RANGE = (0.06, 0.30)


def shared_mesh_paths(data_dir: Path = DATA) -> list[Path]:
    """Every mesh under train_shapes/ (blobs and CAD parts)."""
    root = data_dir / "train_shapes"
    paths = sorted(root.glob("blobs/*.obj")) + sorted(p for p in (root / "cad").iterdir() if p.is_file())
    if not paths:
        raise FileNotFoundError(f"no training meshes under {root}")
    return paths


def procedural_mesh(rng: np.random.Generator) -> trimesh.Trimesh:
    """A union (concatenation) of 1–4 random primitives: boxes, cylinders,
    cones, capsules, spheres and handle-like tori, at random poses."""
    parts = []
    for _ in range(int(rng.integers(1, 5))):
        kind = rng.choice(["box", "cylinder", "cone", "capsule", "sphere", "torus"])
        size = rng.uniform(0.2, 1.0, size=3)
        if kind == "box":
            part = trimesh.creation.box(extents=size)
        elif kind == "cylinder":
            part = trimesh.creation.cylinder(radius=size[0] / 2, height=size[1], sections=24)
        elif kind == "cone":
            part = trimesh.creation.cone(radius=size[0] / 2, height=size[1], sections=24)
        elif kind == "capsule":
            part = trimesh.creation.capsule(radius=size[0] / 3, height=size[1], count=[16, 16])
        elif kind == "sphere":
            part = trimesh.creation.icosphere(subdivisions=2, radius=size[0] / 2)
        else:
            part = trimesh.creation.torus(
                major_radius=size[0] / 2, minor_radius=size[0] / 8, major_sections=24, minor_sections=8
            )
        transform = trimesh.transformations.random_rotation_matrix(rng.random(3))
        transform[:3, 3] = rng.uniform(-0.35, 0.35, size=3)
        part.apply_transform(transform)
        parts.append(part)
    return trimesh.util.concatenate(parts)


def build_models(
    count_procedural: int, seed: int, n_points: int = 4096, limit: int | None = None
) -> list[edgepose.StandardModel]:
    """Standard models of all training shapes, each at a random diameter."""
    rng = np.random.default_rng(seed)
    meshes: list[trimesh.Trimesh] = []
    for path in shared_mesh_paths()[:limit]:
        try:
            meshes.append(read_mesh(path))
        except edgepose.EdgePoseError as e:
            print(f"skipping unusable training mesh: {e}")
    meshes += [procedural_mesh(rng) for _ in range(count_procedural)]
    models = []
    for mesh in meshes:
        extent = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
        scale = rng.uniform(*DIAMETER_RANGE) / extent
        try:
            models.append(edgepose.load_model(mesh, n_points=n_points, scale=scale, seed=int(rng.integers(1 << 31))))
        except edgepose.EdgePoseError:
            continue  # a degenerate training mesh: skip it
    return models


def save_models(models: list[edgepose.StandardModel], path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(
        path,
        points=np.stack([m.points for m in models]),
        normals=np.stack([m.normals for m in models]),
        scale=np.array([m.scale for m in models]),
        diameter=np.array([m.diameter for m in models]),
        spacing=np.array([m.spacing for m in models]),
    )


def load_models(path: Path) -> list[edgepose.StandardModel]:
    data = np.load(path)
    return [
        edgepose.StandardModel(p, n, np.zeros(3), float(s), float(d), float(sp))
        for p, n, s, d, sp in zip(data["points"], data["normals"], data["scale"], data["diameter"], data["spacing"])
    ]
