"""BOP benchmark files: datasets in the BOP-scenewise layout, and results
files ``scene_id,im_id,obj_id,score,R,t,time``.

A dataset folder (``lmo/``, ``tless/``, ``ycbv/``…) holds ``models/`` (or
``models_eval/``) with ``obj_OBJID.ply`` meshes and ``models_info.json``
(diameters, symmetries), and a split folder (``test/``, or e.g.
``test_primesense/``) of scenes ``SCENE/`` with ``scene_camera.json``
(``cam_K``, ``depth_scale``), ``scene_gt.json`` (``cam_R_m2c``,
``cam_t_m2c``), ``scene_gt_info.json`` (``visib_fract``), ``depth/IMID.png``
and ``mask_visib/IMID_GTID.png``; beside them the targets file
(``test_targets_bop19.json``).

BOP is in millimetres and edgepose in metres: this module converts at the
edge, once, so everything it returns is in metres (poses ``T_cam_obj``,
OpenCV camera frame). In a results file R is 9 space-separated values
(row-major), t is 3 space-separated values in millimetres and time is
seconds (the BOP toolkit's format); :class:`BopRow` keeps t in metres.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from edgepose.errors import EdgePoseError, checked_path
from edgepose.symmetry import Symmetry, transform_from

BOP_HEADER = "scene_id,im_id,obj_id,score,R,t,time"

#: BOP object ids of the YCB-Video dataset (``ycbv``), by YCB mesh name.
YCBV_OBJ_ID = {
    "master_chef_can": 1,
    "cracker_box": 2,
    "sugar_box": 3,
    "tomato_soup_can": 4,
    "mustard_bottle": 5,
    "tuna_fish_can": 6,
    "pudding_box": 7,
    "gelatin_box": 8,
    "potted_meat_can": 9,
    "banana": 10,
    "pitcher_base": 11,
    "bleach_cleanser": 12,
    "bowl": 13,
    "mug": 14,
    "power_drill": 15,
    "wood_block": 16,
    "scissors": 17,
    "large_marker": 18,
    "large_clamp": 19,
    "extra_large_clamp": 20,
    "foam_brick": 21,
}


@dataclass(frozen=True, eq=False)
class BopRow:
    """One pose estimate of one object in one image."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    """Confidence, higher is better."""
    R: np.ndarray
    """(3, 3) float64 rotation, object → camera frame."""
    t: np.ndarray
    """(3,) float64 translation, metres, camera frame."""
    time: float
    """Seconds spent on the image (BOP: the same for every estimate of one
    image; -1 when unknown)."""

    def __post_init__(self) -> None:
        R = np.asarray(self.R, dtype=np.float64)
        t = np.asarray(self.t, dtype=np.float64)
        if R.shape != (3, 3) or t.shape != (3,):
            raise ValueError(f"R must be (3, 3) and t (3,), got {R.shape} and {t.shape}")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)


def write_bop_csv(path: str | os.PathLike, rows: Iterable[BopRow]) -> None:
    """Write ``rows`` as a BOP results CSV (t converted to millimetres).
    Values are written in full precision, so reading gives them back."""
    lines = [BOP_HEADER]
    for row in rows:
        R = " ".join(repr(float(x)) for x in row.R.ravel())
        t = " ".join(repr(float(x)) for x in row.t * 1000.0)
        lines.append(
            f"{int(row.scene_id)},{int(row.im_id)},{int(row.obj_id)},{float(row.score)!r},{R},{t},{float(row.time)!r}"
        )
    Path(path).write_text("\n".join(lines) + "\n")


def read_bop_csv(path: str | os.PathLike) -> list[BopRow]:
    """Rows of a BOP results CSV (t converted to metres). Blank lines are
    skipped; a wrong header or a malformed line raises ``ValueError`` naming
    the file and line number."""
    path = Path(path)
    lines = path.read_text().splitlines()
    if not lines or lines[0].strip() != BOP_HEADER:
        found = lines[0].strip() if lines else "an empty file"
        raise ValueError(f"{path}:1: expected header {BOP_HEADER!r}, found {found!r}")
    rows = []
    for number, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        try:
            rows.append(_parse_row(line))
        except ValueError as e:
            raise ValueError(f"{path}:{number}: malformed BOP row ({e}): {line!r}") from None
    return rows


def append_bop_csv(path: str | os.PathLike, row: BopRow) -> None:
    """Add ``row`` to a BOP results CSV, created with its header when missing
    (``ValueError`` as :func:`read_bop_csv` for a malformed existing file)."""
    rows = read_bop_csv(path) if Path(path).is_file() else []
    write_bop_csv(path, [*rows, row])


def _parse_row(line: str) -> BopRow:
    fields = line.strip().split(",")
    if len(fields) != 7:
        raise ValueError(f"expected 7 comma-separated fields, found {len(fields)}")
    scene_id, im_id, obj_id, score, R, t, time = fields
    R_values = [float(x) for x in R.split()]
    t_values = [float(x) for x in t.split()]
    if len(R_values) != 9 or len(t_values) != 3:
        raise ValueError(f"R needs 9 values and t 3, found {len(R_values)} and {len(t_values)}")
    return BopRow(
        scene_id=int(scene_id),
        im_id=int(im_id),
        obj_id=int(obj_id),
        score=float(score),
        R=np.array(R_values).reshape(3, 3),
        t=np.array(t_values) / 1000.0,
        time=float(time),
    )


# ------------------------------------------------------------------ datasets

#: Millimetres (BOP's unit) → metres.
MM = 0.001
#: Targets less visible than this are not counted (BOP: 10 % of the surface).
MIN_VISIBLE_FRACTION = 0.1
#: Folders of object models looked for, in order (T-LESS has ``models_cad/``).
MODEL_FOLDERS = ("models", "models_cad", "models_eval")
#: The targets files looked for beside the split folder, in order.
TARGETS_FILES = ("{split}_targets_bop19.json", "test_targets_bop19.json", "{split}_targets_bop24.json")


class BopDatasetError(EdgePoseError):
    """A BOP dataset folder that cannot be read: a missing or malformed
    file, named with what was expected."""


@dataclass(frozen=True, eq=False)
class BopObject:
    """One object model of a dataset (``models_info.json``), metres."""

    obj_id: int
    diameter: float
    """Metres."""
    symmetry: Symmetry
    """``symmetries_discrete`` and ``symmetries_continuous``, object frame, metres."""
    mesh: Path
    """``models/obj_OBJID.ply`` (or ``models_cad/``, ``models_eval/``): the
    mesh codebooks are built from (millimetres)."""
    eval_mesh: Path
    """``models_eval/obj_OBJID.ply`` when the dataset has it (the BOP metrics
    use it), else ``mesh``."""


@dataclass(frozen=True, eq=False)
class BopGt:
    """One annotated object instance of an image."""

    gt_id: int
    """Its index in the image's ``scene_gt`` list (names its mask file)."""
    obj_id: int
    R: np.ndarray
    """(3, 3) float64 rotation, object → camera."""
    t: np.ndarray
    """(3,) float64 translation, metres."""
    visib_fract: float
    """Share of its silhouette that is visible, 0–1 (``scene_gt_info``)."""

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) float64 ``T_cam_obj``."""
        return transform_from(self.R, self.t)


@dataclass(frozen=True, eq=False)
class BopImage:
    """One test image: camera, depth and annotations."""

    scene_id: int
    im_id: int
    K: np.ndarray
    """(3, 3) float64 pinhole intrinsics, pixels."""
    depth_scale: float
    """Depth image units → metres (BOP's ``depth_scale`` is → millimetres)."""
    gts: tuple[BopGt, ...]
    scene_dir: Path

    def depth(self) -> np.ndarray:
        """(H, W) float64 depth, metres; 0 where nothing was measured (inf
        where an absurd ``depth_scale`` overflows: no measurement either)."""
        from edgepose.io import read_depth_png

        image = read_depth_png(_image_file(self.scene_dir / "depth", f"{self.im_id:06d}"))
        with np.errstate(over="ignore"):
            return image.astype(np.float64) * self.depth_scale

    def mask(self, gt_id: int) -> np.ndarray:
        """(H, W) bool: where annotated instance ``gt_id`` is visible (``mask_visib``)."""
        from edgepose.io import read_mask_png

        return read_mask_png(_image_file(self.scene_dir / "mask_visib", f"{self.im_id:06d}_{gt_id:06d}"))


@dataclass(frozen=True)
class BopTarget:
    """Object ``obj_id`` is to be found ``inst_count`` times in an image."""

    scene_id: int
    im_id: int
    obj_id: int
    inst_count: int


class BopDataset:
    """A BOP-scenewise dataset folder and one of its splits. Reads lazily:
    a scene's JSON files when one of its images is first asked for."""

    def __init__(self, root: str | os.PathLike, split: str = "test") -> None:
        self.root = checked_path(root, "root")
        if not self.root.is_dir():
            raise BopDatasetError(f"{self.root}: no such dataset folder")
        self.name = self.root.resolve().name
        """The dataset's name, from its folder (``lmo``): names the results file."""
        self.split = split.split("_")[0]
        """The split without its type (``test`` for ``test_primesense``), as
        BOP names results files and targets files."""
        self.split_dir = _split_dir(self.root, split)
        self._scenes: dict[int, tuple[dict, dict, dict]] = {}

    @cached_property
    def objects(self) -> dict[int, BopObject]:
        """Every object of ``models_info.json``, by id. Diameters and
        symmetries come from ``models_eval/models_info.json`` when the
        dataset has it (what the BOP toolkit scores with), else from the
        models' own."""
        models = next((self.root / d for d in MODEL_FOLDERS if (self.root / d).is_dir()), None)
        if models is None:
            raise BopDatasetError(f"{self.root}: no model folder ({', '.join(d + '/' for d in MODEL_FOLDERS)})")
        eval_dir = self.root / "models_eval"
        info_file = eval_dir / "models_info.json"
        if not info_file.is_file():
            info_file = models / "models_info.json"
        info = _read_json(info_file)
        if not isinstance(info, dict):
            raise BopDatasetError(f"{info_file}: expected an object of models by id")
        objects = {}
        for key, entry in info.items():
            try:
                obj_id = int(key)
                mesh = models / f"obj_{obj_id:06d}.ply"
                eval_mesh = eval_dir / mesh.name
                objects[obj_id] = BopObject(
                    obj_id,
                    float(entry["diameter"]) * MM,
                    symmetry_from_info(entry),
                    mesh,
                    eval_mesh if eval_mesh.is_file() else mesh,
                )
            except (KeyError, TypeError, ValueError, OverflowError) as e:
                raise BopDatasetError(f"{info_file}: object {key}: {type(e).__name__}: {e}") from None
        return objects

    def scene_ids(self) -> list[int]:
        """The split's scenes (folders named by a number), ascending."""
        return sorted(int(d.name) for d in self.split_dir.iterdir() if d.is_dir() and d.name.isdigit())

    def image_ids(self, scene_id: int) -> list[int]:
        """The images of a scene (``scene_camera.json``), ascending."""
        try:
            return sorted(int(k) for k in self._scene(scene_id)[0])
        except ValueError as e:
            where = self.split_dir / f"{scene_id:06d}" / "scene_camera.json"
            raise BopDatasetError(f"{where}: an image id that is not a number ({e})") from None

    def has_ground_truth(self, scene_id: int) -> bool:
        """Whether the scene's poses are published (``scene_gt.json``; some
        test splits withhold them: estimates can be made, not scored here)."""
        return (self.split_dir / f"{scene_id:06d}" / "scene_gt.json").is_file()

    def image(self, scene_id: int, im_id: int) -> BopImage:
        """Camera and annotations of one image (metres)."""
        camera, gt, gt_info = self._scene(scene_id)
        where = self.split_dir / f"{scene_id:06d}"
        try:
            cam = camera[str(im_id)]
            K = np.asarray(cam["cam_K"], dtype=np.float64).reshape(3, 3)
            depth_scale = float(cam.get("depth_scale", 1.0)) * MM
            if not (np.isfinite(depth_scale) and depth_scale > 0):
                raise ValueError(f"depth_scale must be a positive number, got {cam.get('depth_scale')!r}")
            gts = tuple(
                BopGt(
                    gt_id,
                    int(g["obj_id"]),
                    np.asarray(g["cam_R_m2c"], dtype=np.float64).reshape(3, 3),
                    np.asarray(g["cam_t_m2c"], dtype=np.float64).reshape(3) * MM,
                    float(gt_info[str(im_id)][gt_id]["visib_fract"]) if gt_info else 1.0,
                )
                for gt_id, g in enumerate(gt.get(str(im_id), []))
            )
        except (KeyError, IndexError, TypeError, ValueError, OverflowError) as e:
            raise BopDatasetError(f"{where}: image {im_id}: malformed annotation ({type(e).__name__}: {e})") from None
        return BopImage(scene_id, im_id, K, depth_scale, gts, where)

    def targets(
        self, targets_file: str | os.PathLike | None = None, scenes: Iterable[int] | None = None
    ) -> list[BopTarget]:
        """What to find, per image and object: from ``targets_file``, else the
        dataset's own (``test_targets_bop19.json``…), else every annotated
        instance at least :data:`MIN_VISIBLE_FRACTION` visible. Only
        ``scenes`` when given. A BOP24-style file listing images only gets
        each image's instances at least 10 % visible."""
        wanted = None if scenes is None else set(scenes)
        path = Path(targets_file) if targets_file is not None else self._default_targets_file()
        if path is None:
            if not all(self.has_ground_truth(s) for s in self.scene_ids()):
                raise BopDatasetError(
                    f"{self.root}: no targets file ({', '.join(p.format(split=self.split) for p in TARGETS_FILES)}) "
                    "and no scene_gt.json to find the objects in: give one with --targets"
                )
            entries = [{"scene_id": s, "im_id": i} for s in self.scene_ids() for i in self.image_ids(s)]
        else:
            entries = _read_json(path)
            if not isinstance(entries, list):
                raise BopDatasetError(f"{path}: expected a list of targets")
        targets: list[BopTarget] = []
        for entry in entries:
            try:
                scene_id, im_id = _whole_id(entry["scene_id"]), _whole_id(entry["im_id"])
                if wanted is not None and scene_id not in wanted:
                    continue
                if "obj_id" in entry:
                    targets.append(BopTarget(scene_id, im_id, _whole_id(entry["obj_id"]), int(entry["inst_count"])))
                else:
                    targets.extend(self._visible_targets(scene_id, im_id))
            except (KeyError, TypeError, ValueError, OverflowError) as e:
                raise BopDatasetError(f"{path}: malformed target {entry!r} ({type(e).__name__}: {e})") from None
        return targets

    def _visible_targets(self, scene_id: int, im_id: int) -> list[BopTarget]:
        counts: dict[int, int] = {}
        for g in self.image(scene_id, im_id).gts:
            if g.visib_fract >= MIN_VISIBLE_FRACTION:
                counts[g.obj_id] = counts.get(g.obj_id, 0) + 1
        return [BopTarget(scene_id, im_id, obj_id, n) for obj_id, n in sorted(counts.items())]

    def _default_targets_file(self) -> Path | None:
        for pattern in TARGETS_FILES:
            if pattern.startswith("test_") and not self.split.startswith("test"):
                continue  # the test split's targets never stand in for another split's
            path = self.root / pattern.format(split=self.split)
            if path.is_file():
                return path
        return None

    def _scene(self, scene_id: int) -> tuple[dict, dict, dict]:
        if scene_id not in self._scenes:
            where = self.split_dir / f"{scene_id:06d}"
            if not _is(where, Path.is_dir):
                raise BopDatasetError(f"{where}: no such scene folder")
            camera, gt, info = where / "scene_camera.json", where / "scene_gt.json", where / "scene_gt_info.json"
            scene = (
                _read_json(camera),
                _read_json(gt) if gt.is_file() else {},
                _read_json(info) if info.is_file() else {},
            )
            for path, value in zip((camera, gt, info), scene):
                if not isinstance(value, dict):
                    raise BopDatasetError(f"{path}: expected an object of images by id, got {type(value).__name__}")
            self._scenes[scene_id] = scene
        return self._scenes[scene_id]


def symmetry_from_info(entry: dict) -> Symmetry:
    """An object's symmetries from its ``models_info.json`` entry (BOP:
    flattened 4×4 turns with t in mm; continuous ones as a unit ``axis`` and a
    point ``offset`` on it, mm), in metres."""
    discrete = np.asarray(entry.get("symmetries_discrete", []), dtype=np.float64).reshape(-1, 4, 4).copy()
    discrete[:, :3, 3] *= MM
    continuous = np.asarray(
        [
            [*s["axis"], *(np.asarray(s["offset"], dtype=np.float64) * MM)]
            for s in entry.get("symmetries_continuous", [])
        ],
        dtype=np.float64,
    ).reshape(-1, 6)
    norms = np.linalg.norm(continuous[:, :3], axis=1, keepdims=True)
    continuous[:, :3] /= np.where(norms > 0, norms, 1.0)
    return Symmetry.from_json({"discrete": discrete.reshape(-1, 16).tolist(), "continuous": continuous.tolist()})


def _split_dir(root: Path, split: str) -> Path:
    """``root/split``, or the one ``root/split_TYPE`` (``test_primesense``)."""
    if (root / split).is_dir():
        return root / split
    typed = sorted(d for d in root.glob(f"{split}_*") if d.is_dir())
    if len(typed) == 1:
        return typed[0]
    found = ", ".join(d.name for d in sorted(root.iterdir()) if d.is_dir()) or "nothing"
    raise BopDatasetError(f"{root}: no {split}/ split folder (found: {found})")


def _image_file(folder: Path, stem: str) -> Path:
    """``folder/stem.png``, or the one ``folder/stem.*`` (``.tif`` depth)."""
    path = folder / f"{stem}.png"
    if _is(path, Path.is_file):
        return path
    found = sorted(folder.glob(f"{stem}.*")) if _is(folder, Path.is_dir) else []
    if not found:
        raise BopDatasetError(f"{path}: no such image")
    return found[0]


def _is(path: Path, test: Callable[[Path], bool]) -> bool:
    """``test(path)`` (``Path.is_file``, ``Path.is_dir``), False where the
    system cannot even look (a name too long: an absurd id in a JSON file)."""
    try:
        return test(path)
    except OSError:
        return False


def _whole_id(value: object) -> int:
    """A scene, image or object id of a BOP file: a whole number from 0 to
    ``MAX_ID - 1``; ValueError otherwise (BOP names folders and files by
    them, zero-padded to six digits)."""
    number = int(value)  # type: ignore[call-overload]
    if not 0 <= number < MAX_ID:
        raise ValueError(f"id {value!r} is not a whole number from 0 to {MAX_ID - 1}")
    return number


#: Ids at or above this are not a real dataset's (BOP pads ids to six digits).
MAX_ID = 10**9


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise BopDatasetError(f"{path}: missing") from None
    except (OSError, ValueError) as e:
        raise BopDatasetError(f"{path}: not readable JSON ({e})") from None
