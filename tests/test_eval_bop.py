"""BOP results CSV: round trip, millimetres in the file, readable errors."""

from __future__ import annotations

import numpy as np
import pytest
from edgepose.eval import BopRow, read_bop_csv, write_bop_csv
from scipy.spatial.transform import Rotation


def rows(rng: np.random.Generator, n: int = 20) -> list[BopRow]:
    rotations = Rotation.random(n, random_state=rng).as_matrix()
    return [
        BopRow(
            scene_id=48 + i // 10,
            im_id=i,
            obj_id=int(rng.integers(1, 22)),
            score=float(rng.random()),
            R=R,
            t=rng.normal(0, 0.1, 3) + [0, 0, 0.8],
            time=float(rng.uniform(0.001, 0.5)),
        )
        for i, R in enumerate(rotations)
    ]


def test_round_trip_keeps_every_value(tmp_path, rng):
    written = rows(rng)
    path = tmp_path / "edgepose_ycbv-test.csv"
    write_bop_csv(path, written)
    read = read_bop_csv(path)
    assert len(read) == len(written)
    for a, b in zip(written, read):
        assert (a.scene_id, a.im_id, a.obj_id) == (b.scene_id, b.im_id, b.obj_id)
        assert (a.score, a.time) == (b.score, b.time)
        np.testing.assert_array_equal(a.R, b.R)
        np.testing.assert_allclose(b.t, a.t, rtol=1e-12)
        assert b.R.dtype == np.float64 and b.t.shape == (3,)


def test_file_holds_the_bop_header_and_millimetres(tmp_path):
    row = BopRow(scene_id=1, im_id=2, obj_id=5, score=0.5, R=np.eye(3), t=np.array([0.1, -0.025, 0.75]), time=0.02)
    path = tmp_path / "results.csv"
    write_bop_csv(path, [row])
    header, line = path.read_text().splitlines()
    assert header == "scene_id,im_id,obj_id,score,R,t,time"
    scene_id, im_id, obj_id, score, R, t, time = line.split(",")
    assert (scene_id, im_id, obj_id) == ("1", "2", "5")
    assert float(score) == 0.5 and float(time) == 0.02
    assert [float(x) for x in R.split(" ")] == [1, 0, 0, 0, 1, 0, 0, 0, 1]
    np.testing.assert_allclose([float(x) for x in t.split(" ")], [100.0, -25.0, 750.0], rtol=1e-12)


def test_malformed_lines_are_named_by_number(tmp_path):
    path = tmp_path / "bad.csv"
    good = "1,2,5,0.5,1 0 0 0 1 0 0 0 1,100 -25 750,0.02"
    path.write_text(f"scene_id,im_id,obj_id,score,R,t,time\n{good}\n\n1,3,5,0.5,1 0 0 0 1 0 0 0,100 -25 750,0.02\n")
    with pytest.raises(ValueError, match=r"bad\.csv:4: .*R needs 9 values"):
        read_bop_csv(path)
    path.write_text(f"scene_id,im_id,obj_id,score,R,t,time\n{good}\n1,x,5,0.5\n")
    with pytest.raises(ValueError, match=r"bad\.csv:3: .*7 comma-separated fields"):
        read_bop_csv(path)
    path.write_text("scene_id,im_id,obj_id,score,R,t,time\n1,two,5,0.5,1 0 0 0 1 0 0 0 1,100 -25 750,0.02\n")
    with pytest.raises(ValueError, match=r"bad\.csv:2: "):
        read_bop_csv(path)
    path.write_text(f"scene_id,im_id,obj_id,score,R,t\n{good}\n")
    with pytest.raises(ValueError, match=r"bad\.csv:1: expected header"):
        read_bop_csv(path)
    # Blank lines are fine.
    path.write_text(f"scene_id,im_id,obj_id,score,R,t,time\n\n{good}\n\n")
    assert len(read_bop_csv(path)) == 1


def test_rows_check_their_shapes():
    with pytest.raises(ValueError, match=r"\(3, 3\)"):
        BopRow(scene_id=1, im_id=1, obj_id=1, score=1.0, R=np.eye(4), t=np.zeros(3), time=0.0)
