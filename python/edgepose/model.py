"""The standard model: an object's surface as evenly spread points with
outward normals, centred, with its scale to the unit sphere.

Units are metres. Mesh files in millimetres are detected from their size
(see :func:`detect_scale`) or converted with an explicit ``scale``.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Union

import numpy as np

from edgepose import _core
from edgepose.errors import InvalidArgumentError, InvalidModelError, MeshLoadError, checked_path

if TYPE_CHECKING:
    import trimesh

log = logging.getLogger(__name__)

DEFAULT_MODEL_POINTS = 4096
#: Largest extent (in file units) still read as metres; larger means millimetres.
#: A robot handles objects well under 3 m, and mm models of them exceed 3 units.
METRES_MAX_EXTENT = 3.0
#: Objects smaller or larger than this (diameter, metres, after unit conversion)
#: are a units mistake, not something a robot's depth camera can localise.
MIN_DIAMETER = 1e-3
MAX_DIAMETER = 10.0
#: A model thinner than this fraction of its diameter (along its thinnest
#: principal axis) is flat: a plane or a few coplanar triangles, with no
#: shape for a depth cloud to lock onto. A credit card is ~1 % thick.
MIN_THICKNESS = 1e-3

MeshSource = Union[str, os.PathLike, "trimesh.Trimesh"]


@dataclass(frozen=True)
class StandardModel:
    """An object's surface samples in the model frame.

    The model frame is the original mesh frame shifted by ``centre``:
    ``p_mesh = p_model + centre``. Poses (``T_cam_obj``) refer to the
    original mesh frame.
    """

    points: np.ndarray
    """(N, 3) float32 surface points, metres, model frame."""
    normals: np.ndarray
    """(N, 3) float32 unit outward normals, model frame."""
    centre: np.ndarray
    """(3,) float64 model-frame origin in the original mesh frame, metres."""
    scale: float
    """``1 / max‖p‖``: multiplies model-frame metres into the unit sphere."""
    diameter: float
    """Largest distance between two model points, metres."""
    spacing: float
    """Mean nearest-neighbour distance between model points, metres."""
    core: _core.StandardModel = field(init=False, repr=False, compare=False)
    """The same model in the Rust core, built once; passed to
    :func:`edgepose.compute_maps` and the codebook's ``ModelIndex``."""

    def __post_init__(self) -> None:
        core = _core.StandardModel(
            np.ascontiguousarray(self.points, dtype=np.float32),
            np.ascontiguousarray(self.normals, dtype=np.float32),
            np.ascontiguousarray(self.centre, dtype=np.float64),
            float(self.scale),
            float(self.diameter),
            float(self.spacing),
        )
        object.__setattr__(self, "core", core)

    @classmethod
    def from_core(cls, core: _core.StandardModel) -> StandardModel:
        """The model the core built (from a mesh or from points)."""
        return cls(core.points, core.normals, core.centre, core.scale, core.diameter, core.spacing)

    @property
    def mesh_points(self) -> np.ndarray:
        """(N, 3) float64 surface points in the original mesh frame (the frame
        of ``T_cam_obj``), metres."""
        return self.points.astype(np.float64) + self.centre

    @property
    def radius(self) -> float:
        """Distance from the centre to the farthest model point, metres."""
        return 1.0 / self.scale

    @cached_property
    def box_corners(self) -> np.ndarray:
        """(8, 3) float64 corners of the points' axis-aligned bounding box,
        model frame, metres: a posed model projects within theirs."""
        lo, hi = self.points.min(axis=0).astype(np.float64), self.points.max(axis=0).astype(np.float64)
        return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])

    @cached_property
    def principal_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """The points' centroid (3,) and their principal axes (3, 3), one per
        column, model frame: the axes an elongated or flat object is most
        easily mistaken by a half turn about."""
        points = self.points.astype(np.float64)
        centroid = points.mean(axis=0)
        _, axes = np.linalg.eigh(np.cov((points - centroid).T))
        return centroid, axes


def detect_scale(extent: float) -> float:
    """Factor from file units to metres, guessed from the largest bounding-box
    extent: 1.0 for metres, 0.001 when the mesh looks like millimetres."""
    return 0.001 if extent > METRES_MAX_EXTENT else 1.0


def load_model(
    source: MeshSource,
    *,
    n_points: int = DEFAULT_MODEL_POINTS,
    scale: float | None = None,
    seed: int = 0,
) -> StandardModel:
    """Standard model of a mesh file (obj, ply, stl, glb, off, …) or a
    ``trimesh.Trimesh``.

    ``scale`` multiplies file units into metres; when ``None`` it is detected
    (millimetre files are recognised by size and converted, with a log line).
    """
    import trimesh

    if not isinstance(source, (str, os.PathLike, trimesh.Trimesh)):
        raise InvalidArgumentError(f"source must be a mesh file path or a trimesh.Trimesh, got {source!r:.80}")
    mesh = source if isinstance(source, trimesh.Trimesh) else read_mesh(source)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces)
    if len(vertices) == 0 or len(faces) == 0:
        raise MeshLoadError(f"{_name(source)}: mesh has no triangles")
    if not np.isfinite(vertices).all():
        raise MeshLoadError(f"{_name(source)}: mesh vertices contain NaN or infinite values")
    extent = float(np.ptp(vertices, axis=0).max())
    if scale is None:
        scale = detect_scale(extent)
        if scale != 1.0:
            log.info("%s: extent %.1f units, read as millimetres", _name(source), extent)
    if not (np.isfinite(scale) and scale > 0):
        raise InvalidModelError(f"scale must be a positive number, got {scale}")
    _check_size(float(np.linalg.norm(np.ptp(vertices, axis=0))) * scale, scale, _name(source))
    vertices = vertices * scale
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise InvalidModelError(
            f"{_name(source)}: faces must be (F, 3) vertex indices, got {faces.dtype} {faces.shape}"
        )
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise InvalidModelError(f"{_name(source)}: faces refer to vertices outside 0..{len(vertices) - 1}")
    faces = np.ascontiguousarray(faces, dtype=np.uint32)
    core = _core.StandardModel.from_mesh(vertices, faces, n_points, seed, source=_name(source))
    return _checked(StandardModel.from_core(core), _name(source))


def model_from_points(
    points: np.ndarray,
    normals: np.ndarray,
    *,
    n_points: int = DEFAULT_MODEL_POINTS,
) -> StandardModel:
    """Standard model of an object given as surface points (metres, (N, 3))
    with normals ((N, 3), any length, pointing outward or all inward).
    Thinned to ``n_points`` by farthest-point sampling when larger."""
    points = _as_triples(points, "points")
    normals = _as_triples(normals, "normals")
    if len(points) and np.isfinite(points).all():
        _check_size(float(np.linalg.norm(np.ptp(points, axis=0))), 1.0, "points")
    core = _core.StandardModel.from_points(points, normals, n_points, source="points")
    return _checked(StandardModel.from_core(core), "points")


def _check_size(diameter: float, scale: float, name: str) -> None:
    """InvalidModelError unless an object ``diameter`` metres across (its
    bounding-box diagonal) is of a size a robot handles."""
    if diameter == 0.0:
        return  # all points coincide: the core reports it as degenerate
    if not MIN_DIAMETER <= diameter <= MAX_DIAMETER:
        raise InvalidModelError(
            f"{name}: the object would be {diameter:.3g} m across (file units × {scale:g}); "
            f"edgepose handles {MIN_DIAMETER:g}–{MAX_DIAMETER:g} m: pass the right `scale` "
            "(metres per file unit)"
        )


def _checked(model: StandardModel, name: str) -> StandardModel:
    """``model``, unless it is flat (see MIN_THICKNESS)."""
    centred = model.points.astype(np.float64)
    centred -= centred.mean(axis=0)
    _, _, axes = np.linalg.svd(centred, full_matrices=False)
    thickness = float(np.ptp(centred @ axes[2]))
    if thickness < MIN_THICKNESS * model.diameter:
        raise InvalidModelError(
            f"{name}: the model is flat ({thickness:.2g} m thick, {model.diameter:.3g} m across): "
            "a plane or a few coplanar triangles has no shape to estimate a pose from"
        )
    return model


def read_mesh(path: str | os.PathLike, scale: float | None = 1.0) -> trimesh.Trimesh:  # noqa: F821
    """A mesh file (obj, ply, stl, glb, off, …) as one ``trimesh.Trimesh``:
    the triangles of every geometry, in the file's frame, times ``scale``
    (1: the file's units; ``None``: metres, with millimetre files detected
    as :func:`load_model` does).

    Geometry only: materials and textures are ignored (so no image library is
    needed), and multi-part files (glb scenes) are merged with their node
    transforms applied."""
    import trimesh

    path = checked_path(path)
    if not path.is_file():
        raise MeshLoadError(f"{path}: no such file")
    try:
        # A depth method needs no texture: skip_materials keeps a missing
        # texture image (BOP's models name one) from being looked for at all.
        scene = trimesh.load_scene(path, skip_materials=True)
        parts = []
        for node in scene.graph.nodes_geometry:
            transform, geometry_name = scene.graph[node]
            geometry = scene.geometry[geometry_name]
            if isinstance(geometry, trimesh.Trimesh) and len(geometry.faces):
                vertices = trimesh.transform_points(np.asarray(geometry.vertices), transform)
                parts.append((vertices, np.asarray(geometry.faces)))
    except Exception as e:  # trimesh raises many types for bad files
        raise MeshLoadError(f"{path}: cannot read mesh ({type(e).__name__}: {e})") from None
    if not parts:
        raise MeshLoadError(f"{path}: holds no triangle mesh")
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    vertices = np.concatenate([v for v, _ in parts])
    faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets)])
    if scale is None:
        scale = detect_scale(float(np.ptp(vertices, axis=0).max()))
    if not (np.isfinite(scale) and scale > 0):
        raise InvalidModelError(f"scale must be a positive number, got {scale}")
    return trimesh.Trimesh(vertices=vertices * scale, faces=faces, process=False)


def _as_triples(array: np.ndarray, name: str) -> np.ndarray:
    array = np.asarray(array)
    if array.ndim != 2 or array.shape[1] != 3:
        raise InvalidModelError(f"{name} must have shape (N, 3), got {array.shape}")
    return np.ascontiguousarray(array, dtype=np.float32)


def _name(source: object) -> str:
    return str(source) if isinstance(source, (str, os.PathLike)) else type(source).__name__
