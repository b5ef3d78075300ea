"""BOP challenge results files: ``scene_id,im_id,obj_id,score,R,t,time``.

In the file R is 9 space-separated values (row-major), t is 3 space-separated
values in millimetres and time is seconds (the BOP toolkit's format). In
memory, :class:`BopRow` keeps t in metres like the rest of edgepose.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

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
