"""The BOP score of a results file: Average Recall (AR) of VSD, MSSD and
MSPD, as the BOP toolkit computes it for the 6D localisation task (BOP19),
with ADD(-S) at 0.1 × diameter alongside.

Per image and object, the ``inst_count`` best-scored estimates are
greedily matched, best score first, to the ``inst_count`` most visible
annotated instances (each to the unmatched one it fits best, if its error is
under the threshold). A matched instance is a true positive; recall is true
positives over targets, per threshold. AR_VSD averages recall over the 10
τ × 10 θ pairs, AR_MSSD and AR_MSPD over their 10 thresholds, and AR is the
mean of the three. Errors are computed on the ``models_eval`` meshes with
the dataset's own symmetries (``models_info.json``).

Units are metres (MSPD in pixels); poses are ``T_cam_obj``.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass, field

import numpy as np

from edgepose.eval.bop import MM, BopDataset, BopGt, BopObject, BopRow, BopTarget
from edgepose.eval.bop_metrics import (
    BOP_MSPD_THRESHOLDS,
    BOP_MSSD_THRESHOLDS,
    BOP_VSD_DELTA,
    BOP_VSD_DELTAS,
    BOP_VSD_TAUS,
    BOP_VSD_THRESHOLDS,
    bop_mspd_thresholds,
    bop_symmetry_transforms,
    mspd,
    mssd,
    vsd,
)
from edgepose.eval.metrics import CORRECT_FRACTION, add_or_s


@dataclass(frozen=True)
class BopScore:
    """Recalls of a set of targets (one object, or the whole dataset), 0–1."""

    targets: int
    """Annotated instances to find."""
    estimates: int
    """Estimates evaluated (at most ``inst_count`` per image and object)."""
    ar: float
    """Mean of ``ar_vsd``, ``ar_mssd`` and ``ar_mspd``: the BOP score."""
    ar_vsd: float
    ar_mssd: float
    ar_mspd: float
    add_s: float
    """Recall of ADD(-S) < 0.1 × diameter (ADD-S for symmetric objects)."""


@dataclass(frozen=True)
class BopScores:
    """The score of a results file on a dataset split."""

    dataset: str
    split: str
    overall: BopScore
    objects: dict[int, BopScore]
    """By BOP object id."""
    images: int
    """Images with at least one target."""
    time: float
    """Mean seconds per image over the images with estimates (the results'
    ``time``), as the BOP toolkit reports it; NaN when an image's time is
    unknown (negative)."""

    def to_json(self) -> dict:
        """Plain types, object ids as strings (JSON keys)."""
        return {
            "dataset": self.dataset,
            "split": self.split,
            "images": self.images,
            "time_per_image_s": self.time,
            "overall": asdict(self.overall),
            "objects": {str(k): asdict(v) for k, v in sorted(self.objects.items())},
        }

    def markdown(self) -> str:
        """The table: one row per object, then all objects, percentages."""
        lines = [
            f"BOP score of edgepose on {self.dataset}-{self.split}: {self.images} images, "
            f"{self.time * 1000:.1f} ms per image (mean)",
            "",
            "| object | targets | AR | AR_VSD | AR_MSSD | AR_MSPD | ADD(-S) |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
        ]
        rows = [(f"obj_{k:06d}", v) for k, v in sorted(self.objects.items())] + [("**all**", self.overall)]
        for name, s in rows:
            lines.append(
                f"| {name} | {s.targets} | {100 * s.ar:.1f} | {100 * s.ar_vsd:.1f} | {100 * s.ar_mssd:.1f} "
                f"| {100 * s.ar_mspd:.1f} | {100 * s.add_s:.1f} |"
            )
        return "\n".join(lines) + "\n"


@dataclass
class _Counts:
    """True positives per threshold of one object, and its targets."""

    targets: int = 0
    estimates: int = 0
    vsd: np.ndarray = field(default_factory=lambda: np.zeros((len(BOP_VSD_TAUS), len(BOP_VSD_THRESHOLDS))))
    mssd: np.ndarray = field(default_factory=lambda: np.zeros(len(BOP_MSSD_THRESHOLDS)))
    mspd: np.ndarray = field(default_factory=lambda: np.zeros(len(BOP_MSPD_THRESHOLDS)))
    add_s: float = 0.0

    def add(self, other: _Counts) -> None:
        self.targets += other.targets
        self.estimates += other.estimates
        self.vsd += other.vsd
        self.mssd += other.mssd
        self.mspd += other.mspd
        self.add_s += other.add_s

    def score(self) -> BopScore:
        n = max(self.targets, 1)
        vsd, mssd, mspd = (float(x.mean()) / n for x in (self.vsd, self.mssd, self.mspd))
        return BopScore(self.targets, self.estimates, (vsd + mssd + mspd) / 3, vsd, mssd, mspd, self.add_s / n)


def score_bop(
    dataset: BopDataset,
    rows: Iterable[BopRow],
    targets: Iterable[BopTarget],
    *,
    vsd_delta: float | None = None,
) -> BopScores:
    """Score ``rows`` (estimates, any order) against ``targets``.
    ``vsd_delta``: the VSD visibility tolerance, metres (default: BOP's for
    the dataset's name, else 15 mm). ``ValueError`` when one image's rows
    disagree on its time (by more than 1 ms, as the toolkit checks)."""
    delta = vsd_delta if vsd_delta is not None else BOP_VSD_DELTAS.get(dataset.name, BOP_VSD_DELTA)
    by_image: dict[tuple[int, int], dict[int, int]] = {}
    for target in targets:
        by_image.setdefault((target.scene_id, target.im_id), {})[target.obj_id] = target.inst_count
    estimates: dict[tuple[int, int, int], list[BopRow]] = {}
    image_times: dict[tuple[int, int], float] = {}
    for row in rows:
        estimates.setdefault((row.scene_id, row.im_id, row.obj_id), []).append(row)
        known = image_times.setdefault((row.scene_id, row.im_id), row.time)
        if abs(known - row.time) > 0.001:  # the toolkit refuses such a file too
            raise ValueError(
                f"scene {row.scene_id} image {row.im_id}: estimates with different times ({known} and {row.time} s); "
                "BOP needs one time per image"
            )
    models = _EvalModels(dataset)
    counts: dict[int, _Counts] = {}
    for (scene_id, im_id), wanted in sorted(by_image.items()):
        image = dataset.image(scene_id, im_id)
        depth = None
        for obj_id, inst_count in sorted(wanted.items()):
            obj_counts = counts.setdefault(obj_id, _Counts())
            gts = [g for g in image.gts if g.obj_id == obj_id]
            valid = {g.gt_id for g in sorted(gts, key=lambda g: -g.visib_fract)[:inst_count]}
            obj_counts.targets += len(valid)
            ests = sorted(estimates.get((scene_id, im_id, obj_id), []), key=lambda r: -r.score)[:inst_count]
            obj_counts.estimates += len(ests)
            if not ests or not gts:
                continue
            if depth is None:
                depth = image.depth()
            errors = [_errors(e, gts, image.K, depth, models, obj_id, delta) for e in ests]
            _count_matches(obj_counts, errors, [g.gt_id for g in gts], valid, depth.shape[1])
    overall = _Counts()
    for c in counts.values():
        overall.add(c)
    times = list(image_times.values())
    return BopScores(
        dataset.name,
        dataset.split,
        overall.score(),
        {k: c.score() for k, c in counts.items()},
        len(by_image),
        float(np.mean(times)) if times and min(times) >= 0 else float("nan"),
    )


class _EvalModels:
    """Per object, loaded once: eval-mesh vertices and faces (metres), its
    BOP symmetry transforms and whether ADD-S judges it."""

    def __init__(self, dataset: BopDataset) -> None:
        self.dataset = dataset
        self._cache: dict[int, tuple[BopObject, np.ndarray, np.ndarray, np.ndarray]] = {}

    def __getitem__(self, obj_id: int) -> tuple[BopObject, np.ndarray, np.ndarray, np.ndarray]:
        if obj_id not in self._cache:
            from edgepose.model import read_mesh  # trimesh: imported when scoring starts

            obj = self.dataset.objects[obj_id]
            mesh = read_mesh(obj.eval_mesh, scale=MM)
            vertices = np.asarray(mesh.vertices, dtype=np.float64)
            self._cache[obj_id] = (obj, vertices, np.asarray(mesh.faces), bop_symmetry_transforms(obj.symmetry))
        return self._cache[obj_id]


@dataclass(frozen=True)
class _PairErrors:
    """Errors of one estimate against one annotated instance."""

    vsd: np.ndarray
    """(taus,) VSD per τ, 0–1."""
    mssd: float
    """Metres / diameter."""
    mspd: float
    """Pixels."""
    add_s: float
    """Metres / diameter."""


def _errors(
    row: BopRow,
    gts: list[BopGt],
    K: np.ndarray,
    depth: np.ndarray,
    models: _EvalModels,
    obj_id: int,
    delta: float,
) -> dict[int, _PairErrors]:
    """One estimate's errors against each instance of its object, by gt_id."""
    obj, vertices, faces, transforms = models[obj_id]
    d = obj.diameter
    T_est = np.eye(4)
    T_est[:3, :3], T_est[:3, 3] = row.R, row.t
    out = {}
    for g in gts:
        out[g.gt_id] = _PairErrors(
            np.asarray(vsd(row.R, row.t, g.R, g.t, depth, K, vertices, faces, delta, BOP_VSD_TAUS, d)),
            mssd(row.R, row.t, g.R, g.t, vertices, transforms) / d,
            mspd(row.R, row.t, g.R, g.t, vertices, transforms, K),
            add_or_s(vertices, T_est, g.matrix, obj.symmetry.symmetric) / d,
        )
    return out


def _count_matches(
    counts: _Counts, errors: list[dict[int, _PairErrors]], gt_ids: list[int], valid: set[int], width: int
) -> None:
    """Add the true positives of each threshold: estimates (``errors``, best
    score first) greedily matched to the valid instances (BOP's matching)."""

    def matched(error_of: list[dict[int, float]], threshold: float) -> int:
        taken: set[int] = set()
        for errs in error_of:
            best, best_error = -1, threshold
            for gt_id in gt_ids:
                if gt_id in valid and gt_id not in taken and errs[gt_id] < best_error:
                    best, best_error = gt_id, errs[gt_id]
            if best >= 0:
                taken.add(best)
        return len(taken)

    mssd_of = [{g: e[g].mssd for g in gt_ids} for e in errors]
    mspd_of = [{g: e[g].mspd for g in gt_ids} for e in errors]
    for i, th in enumerate(BOP_MSSD_THRESHOLDS):
        counts.mssd[i] += matched(mssd_of, th)
    for i, th in enumerate(bop_mspd_thresholds(width)):
        counts.mspd[i] += matched(mspd_of, th)
    for j in range(len(BOP_VSD_TAUS)):
        vsd_of = [{g: float(e[g].vsd[j]) for g in gt_ids} for e in errors]
        for i, th in enumerate(BOP_VSD_THRESHOLDS):
            counts.vsd[j, i] += matched(vsd_of, th)
    counts.add_s += matched([{g: e[g].add_s for g in gt_ids} for e in errors], CORRECT_FRACTION)
