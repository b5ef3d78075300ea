"""Running edgepose on a BOP dataset: a codebook per object model, then every
image's targets in one :func:`edgepose.estimate_many` call, with the
annotated visible masks or a detector's masks (the BOP default-detections
JSON), giving :class:`edgepose.eval.bop.BopRow` estimates.

Units are metres; poses are ``T_cam_obj``; the row time is seconds.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from edgepose.catalog import BuildSettings, LocalExecutor, ObjectResult, RayExecutor, build_catalog
from edgepose.codebook import Codebook
from edgepose.encoder import Encoder, default_encoder
from edgepose.eval.bop import MM, BopDataset, BopDatasetError, BopImage, BopRow, BopTarget
from edgepose.frame import estimate_many
from edgepose.settings import DEFAULT_SETTINGS, EstimateSettings


@dataclass(frozen=True, eq=False)
class Detection:
    """One detector output of the BOP default-detections format."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    rle: dict
    """Its mask as an uncompressed COCO RLE (``counts``: run lengths,
    ``size``: [H, W]): decoded only when used (:meth:`mask`), since a
    detections file holds many more masks than are estimated."""
    time: float
    """Seconds the detector spent on the image (-1 when unknown)."""

    def mask(self) -> np.ndarray:
        """(H, W) bool."""
        return decode_rle(self.rle)


def bop_codebooks(
    dataset: BopDataset,
    obj_ids: Iterable[int],
    out_dir: str | os.PathLike,
    *,
    executor: LocalExecutor | RayExecutor | None = None,
    on_result: Callable[[ObjectResult], None] | None = None,
) -> dict[int, Codebook]:
    """The codebook of each object, built from its ``models/`` mesh (mm) into
    ``out_dir`` as the catalogue builds them (:func:`edgepose.catalog.build_catalog`:
    up-to-date ones are skipped, so reruns cost nothing; ``executor`` may be
    Ray's). ``BopDatasetError`` naming the objects that fail."""
    ids = sorted(set(obj_ids))
    missing = [i for i in ids if i not in dataset.objects]
    if missing:
        raise BopDatasetError(f"{dataset.root}: objects {missing} have targets but no entry in models_info.json")
    meshes = [dataset.objects[i].mesh for i in ids]
    results = build_catalog(meshes, out_dir, BuildSettings(scale=MM), executor=executor, on_result=on_result)
    failed = [f"object {i}: {r.error}" for i, r in zip(ids, results) if r.failed]
    if failed:
        raise BopDatasetError("codebooks could not be built: " + "; ".join(failed))
    encoder = default_encoder()
    return {i: Codebook.load(r.codebook, encoder) for i, r in zip(ids, results)}


def run_bop(
    dataset: BopDataset,
    targets: Iterable[BopTarget],
    codebooks: dict[int, Codebook],
    *,
    detections: dict[tuple[int, int], list[Detection]] | None = None,
    encoder: Encoder | None = None,
    settings: EstimateSettings = DEFAULT_SETTINGS,
    on_image: Callable[[BopImage, list[BopRow]], None] | None = None,
) -> list[BopRow]:
    """Estimate every target: per image, ``inst_count`` poses per object,
    from the annotated visible masks of its most visible instances, or with
    ``detections`` (by (scene_id, im_id)) from its best-scored detections.
    Every row of an image has the image's time (seconds from the depth image
    to its poses, plus the detector's own time when the detections give it).
    Score: the pose's confidence (times the detection's score)."""
    by_image: dict[tuple[int, int], dict[int, int]] = {}
    for t in targets:
        by_image.setdefault((t.scene_id, t.im_id), {})[t.obj_id] = t.inst_count
    encoder = encoder or default_encoder(threads=os.cpu_count() or 1)  # loaded before any image is timed
    rows: list[BopRow] = []
    for (scene_id, im_id), wanted in sorted(by_image.items()):
        image = dataset.image(scene_id, im_id)
        objects, obj_ids, det_scores, det_time = [], [], [], 0.0
        for obj_id, inst_count in sorted(wanted.items()):
            if detections is None:
                gts = sorted((g for g in image.gts if g.obj_id == obj_id), key=lambda g: -g.visib_fract)
                masks = [image.mask(g.gt_id) for g in gts[:inst_count]]
                scores = [1.0] * len(masks)
            else:
                found = [d for d in detections.get((scene_id, im_id), []) if d.obj_id == obj_id]
                found = sorted(found, key=lambda d: -d.score)[:inst_count]
                masks, scores = [d.mask() for d in found], [d.score for d in found]
                det_time = max([det_time] + [d.time for d in found])
            objects += [(mask, codebooks[obj_id]) for mask in masks]
            obj_ids += [obj_id] * len(masks)
            det_scores += scores
        if not objects:
            continue
        frame = estimate_many(image.depth(), image.K, objects, depth_scale=1.0, encoder=encoder, settings=settings)
        seconds = frame.seconds + det_time
        image_rows = [
            BopRow(
                scene_id, im_id, obj_id, _row_score(pose.confidence, pose.inlier_fraction) * s, pose.R, pose.t, seconds
            )
            for obj_id, s, pose in zip(obj_ids, det_scores, frame.poses)
            if pose is not None
        ]
        rows += image_rows
        if on_image:
            on_image(image, image_rows)
    return rows


def _row_score(confidence: float, inlier_fraction: float) -> float:
    """The pose's calibrated confidence, or (networks without one) its inlier fraction."""
    return confidence if math.isfinite(confidence) else inlier_fraction


def read_detections(path: str | os.PathLike) -> dict[tuple[int, int], list[Detection]]:
    """A BOP default-detections JSON (a list of ``scene_id``, ``image_id``,
    ``category_id``, ``score``, ``segmentation`` (COCO RLE, compressed or
    not), ``time``), by (scene_id, im_id). ``BopDatasetError`` when malformed."""
    path = Path(path)
    try:
        entries = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise BopDatasetError(f"{path}: not a readable detections JSON ({e})") from None
    if not isinstance(entries, list):
        raise BopDatasetError(f"{path}: expected a list of detections")
    out: dict[tuple[int, int], list[Detection]] = {}
    for n, entry in enumerate(entries):
        try:
            det = Detection(
                int(entry["scene_id"]),
                int(entry["image_id"]),
                int(entry["category_id"]),
                float(entry["score"]),
                _checked_rle(entry["segmentation"]),
                float(entry.get("time", -1.0)),
            )
        except (KeyError, TypeError, ValueError, OverflowError) as e:
            raise BopDatasetError(f"{path}: detection {n} malformed ({type(e).__name__}: {e})") from None
        out.setdefault((det.scene_id, det.im_id), []).append(det)
    return out


def decode_rle(segmentation: dict) -> np.ndarray:
    """(H, W) bool mask of a COCO run-length encoding ``{"counts", "size": [H,
    W]}``: runs alternate background and mask, starting with background, in
    column-major pixel order; ``counts`` a list of run lengths, or COCO's
    compressed string (pycocotools' ``mask.encode``). ``ValueError`` if the
    runs do not cover the image exactly."""
    rle = _checked_rle(segmentation)
    height, width = rle["size"]
    values = np.zeros(len(rle["counts"]), dtype=bool)
    values[1::2] = True
    flat = np.repeat(values, rle["counts"])
    return flat.reshape(width, height).T.copy()


def encode_rle(mask: np.ndarray) -> dict:
    """The uncompressed COCO RLE of an (H, W) bool ``mask`` (the inverse of
    :func:`decode_rle`): for writing detections in BOP's format."""
    mask = np.asarray(mask, dtype=bool)
    flat = mask.T.ravel()
    bounds = np.concatenate([[0], np.flatnonzero(flat[1:] != flat[:-1]) + 1, [flat.size]])
    runs = np.diff(bounds).tolist()
    return {"counts": [0, *runs] if flat.size and flat[0] else runs, "size": list(mask.shape)}


def _checked_rle(segmentation: dict) -> dict:
    """``segmentation`` as ``{"counts": [run lengths], "size": [H, W]}``,
    compressed counts expanded; ``ValueError`` if the runs do not cover the
    image exactly."""
    height, width = (int(v) for v in segmentation["size"])
    counts = segmentation["counts"]
    runs = _rle_string_counts(counts) if isinstance(counts, (str, bytes)) else [int(c) for c in counts]
    if any(r < 0 for r in runs) or sum(runs) != height * width:
        raise ValueError(f"RLE runs cover {sum(runs)} pixels, not {height}×{width}, or are negative")
    return {"counts": runs, "size": [height, width]}


def _rle_string_counts(text: str | bytes) -> list[int]:
    """Run lengths of COCO's compressed RLE string: each run is a
    variable-length signed number in 5-bit groups (characters from 48),
    and from the fourth on, a difference to the run two before."""
    data = text.encode() if isinstance(text, str) else text
    runs: list[int] = []
    p = 0
    while p < len(data):
        value, shift, more = 0, 0, True
        while more:
            if p >= len(data):
                raise ValueError("compressed RLE ends inside a number")
            c = data[p] - 48
            value |= (c & 0x1F) << shift
            more = bool(c & 0x20)
            p += 1
            shift += 5
            if not more and c & 0x10:
                value |= -1 << shift
        if len(runs) > 2:
            value += runs[-2]
        runs.append(value)
    return runs
