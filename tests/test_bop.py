"""BOP datasets end to end: a small BOP-format dataset written here (2 scenes
× 3 images, 3 models: the asymmetric drill, a box with three half-turn
symmetries, a can with a continuous one), read back, estimated with
``estimate_many`` and scored; the results CSV and the ``edgepose bop``
command. The metrics themselves are checked by hand in test_bop_metrics.py."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import edgepose
import numpy as np
import pytest
import trimesh
from conftest import SHIPPED
from edgepose.errors import InvalidCloudError
from edgepose.eval.bop import BopDataset, BopDatasetError, BopRow, read_bop_csv
from edgepose.eval.bop_run import bop_codebooks, decode_rle, encode_rle, read_detections, run_bop
from edgepose.eval.bop_scenes import write_bop_dataset
from edgepose.eval.bop_score import score_bop
from edgepose.io import read_mask_png
from edgepose.symmetry import Symmetry
from test_cli import fails_cleanly, run

BOX_SIDES = (0.12, 0.08, 0.05)


def half_turn(axis: int) -> np.ndarray:
    return np.diag([1.0 if i == axis else -1.0 for i in range(3)] + [1.0])


BOX_SYMMETRY = Symmetry(np.stack([half_turn(0), half_turn(1), half_turn(2)]), np.zeros((0, 6)))
CAN_SYMMETRY = Symmetry(half_turn(0)[None], np.array([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0]]))


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory) -> Path:
    from edgepose.model import read_mesh

    meshes = {
        1: read_mesh(SHIPPED / "power_drill.ply"),
        2: trimesh.creation.box(BOX_SIDES),
        5: trimesh.creation.cylinder(radius=0.035, height=0.11, sections=48),
    }
    root = tmp_path_factory.mktemp("bop") / "tinyset"
    return write_bop_dataset(root, meshes, symmetries={2: BOX_SYMMETRY, 5: CAN_SYMMETRY}, seed=3)


@pytest.fixture(scope="module")
def dataset(dataset_dir) -> BopDataset:
    return BopDataset(dataset_dir)


@pytest.fixture(scope="module")
def codebooks(dataset, tmp_path_factory):
    return bop_codebooks(dataset, dataset.objects, tmp_path_factory.mktemp("codebooks"))


def truth_rows(dataset: BopDataset, transform=None) -> list[BopRow]:
    """A row per target instance at its annotated pose (``transform(obj_id, T)`` applied)."""
    rows = []
    for t in dataset.targets():
        image = dataset.image(t.scene_id, t.im_id)
        for g in sorted((g for g in image.gts if g.obj_id == t.obj_id), key=lambda g: -g.visib_fract)[: t.inst_count]:
            T = g.matrix if transform is None else transform(t.obj_id, g.matrix)
            rows.append(BopRow(t.scene_id, t.im_id, t.obj_id, 1.0, T[:3, :3], T[:3, 3], 0.01))
    return rows


# ----------------------------------------------------------------- the reader


def test_reader_converts_bop_millimetres_to_metres(dataset):
    assert dataset.name == "tinyset" and dataset.split_dir.name == "test"
    assert set(dataset.objects) == {1, 2, 5}
    assert dataset.objects[2].diameter == pytest.approx(float(np.linalg.norm(BOX_SIDES)), rel=1e-6)
    assert np.allclose(dataset.objects[2].symmetry.discrete, BOX_SYMMETRY.discrete)
    assert np.allclose(dataset.objects[5].symmetry.continuous, CAN_SYMMETRY.continuous)
    assert not dataset.objects[1].symmetry.symmetric
    assert dataset.scene_ids() == [1, 2] and dataset.image_ids(2) == [0, 1, 2]
    for scene_id in (1, 2):  # depth_scale 1.0 and 0.1 (mm per unit): the same metres
        image = dataset.image(scene_id, 0)
        depth = image.depth()
        assert 0.5 < np.median(depth[depth > 0]) < 1.2
        for g in image.gts:
            assert 0.55 < g.t[2] < 0.95  # metres, as written (0.6-0.9 m to the box centre)
            mask = image.mask(g.gt_id)
            on = depth[mask & (depth > 0)]
            # The object's own surface, in metres, near where its pose puts it.
            assert abs(np.median(on) - g.t[2]) < dataset.objects[g.obj_id].diameter


def test_targets_follow_the_file_and_the_visibility_rule(dataset, dataset_dir, tmp_path):
    targets = dataset.targets()
    listed = json.loads((dataset_dir / "test_targets_bop19.json").read_text())
    assert [(t.scene_id, t.im_id, t.obj_id, t.inst_count) for t in targets] == [
        (e["scene_id"], e["im_id"], e["obj_id"], e["inst_count"]) for e in listed
    ]
    assert {t.scene_id for t in dataset.targets(scenes=[2])} == {2}
    # Without a targets file: every instance at least 10 % visible, the same here.
    copy = tmp_path / "copy"
    shutil.copytree(dataset_dir, copy, ignore=shutil.ignore_patterns("*targets*"))
    derived = BopDataset(copy).targets()
    assert [(t.scene_id, t.im_id, t.obj_id, t.inst_count) for t in derived] == [
        (t.scene_id, t.im_id, t.obj_id, t.inst_count) for t in targets
    ]
    # A BOP24-style file lists images only: their visible instances become targets.
    bop24 = tmp_path / "images.json"
    bop24.write_text(json.dumps([{"scene_id": 1, "im_id": 2}]))
    assert {(t.scene_id, t.im_id) for t in dataset.targets(bop24)} == {(1, 2)}


def test_a_typed_split_folder_is_found_and_missing_files_are_named(dataset_dir, tmp_path):
    copy = tmp_path / "tless"
    shutil.copytree(dataset_dir, copy)
    (copy / "test").rename(copy / "test_primesense")
    (copy / "models").rename(copy / "models_cad")
    assert BopDataset(copy).split_dir.name == "test_primesense"
    assert BopDataset(copy, "test_primesense").split == "test"  # results: tless-test
    (copy / "test_kinect").mkdir()  # two sensors (HB): the split must be named
    with pytest.raises(BopDatasetError, match=r"no test/ split folder \(found: .*test_kinect, test_primesense\)"):
        BopDataset(copy)
    assert BopDataset(copy, "test_kinect").split_dir.name == "test_kinect"
    (copy / "test_kinect").rmdir()
    assert BopDataset(copy).objects[2].mesh.parent.name == "models_cad"
    with pytest.raises(BopDatasetError, match="no val/ split folder"):
        BopDataset(copy, "val")
    (copy / "test_primesense" / "000001" / "scene_camera.json").unlink()
    with pytest.raises(BopDatasetError, match="scene_camera.json: missing"):
        BopDataset(copy).image(1, 0)
    (copy / "models_cad" / "models_info.json").write_text("{not json")
    with pytest.raises(BopDatasetError, match="models_info.json: not readable JSON"):
        _ = BopDataset(copy).objects
    with pytest.raises(BopDatasetError, match="no such dataset folder"):
        BopDataset(tmp_path / "nowhere")


# ----------------------------------------------------------------- scoring


def test_the_annotated_poses_score_full_marks(dataset):
    scores = score_bop(dataset, truth_rows(dataset), dataset.targets())
    assert scores.overall.targets == sum(t.inst_count for t in dataset.targets())
    assert (scores.overall.ar, scores.overall.ar_vsd, scores.overall.ar_mssd, scores.overall.ar_mspd) == (1, 1, 1, 1)
    assert scores.overall.add_s == 1.0


def test_a_symmetric_object_turned_by_its_symmetry_is_correct(dataset):
    turned = truth_rows(dataset, lambda obj_id, T: T @ half_turn(2) if obj_id == 2 else T)
    scores = score_bop(dataset, turned, dataset.targets())
    assert scores.objects[2].ar == 1.0 and scores.objects[2].add_s == 1.0
    # The asymmetric drill turned the same way is wrong by every measure.
    wrong = score_bop(dataset, truth_rows(dataset, lambda o, T: T @ half_turn(2) if o == 1 else T), dataset.targets())
    assert wrong.objects[1].ar_mssd == 0.0 and wrong.objects[1].add_s == 0.0
    assert wrong.objects[2].ar == 1.0


def test_a_known_offset_gives_the_expected_mssd_recall(dataset):
    # 30 mm off along the camera's x axis: MSSD = 30 mm exactly (a translation
    # moves every point alike; a symmetry cannot undo it), 0.197 of the box's
    # diameter: correct at the thresholds 0.2, 0.25 … 0.5, 7 of 10.
    def shifted(obj_id, T):
        T = T.copy()
        if obj_id == 2:
            T[0, 3] += 0.03
        return T

    scores = score_bop(dataset, truth_rows(dataset, shifted), dataset.targets())
    assert 0.03 / dataset.objects[2].diameter == pytest.approx(0.1966, abs=1e-3)
    assert scores.objects[2].ar_mssd == pytest.approx(0.7)
    assert scores.objects[2].add_s == 0.0  # 0.197 d > 0.1 d
    assert scores.objects[1].ar == 1.0


def test_missing_and_extra_estimates_count_as_bop_counts_them(dataset):
    rows = truth_rows(dataset)
    targets = dataset.targets()
    half = score_bop(dataset, [r for r in rows if r.scene_id == 1], targets)
    assert half.overall.ar == pytest.approx(
        sum(t.inst_count for t in targets if t.scene_id == 1) / half.overall.targets
    )
    # A worse-scored duplicate beyond inst_count is not evaluated; a better-scored wrong one displaces the right one.
    far = [BopRow(r.scene_id, r.im_id, r.obj_id, 0.5, r.R, r.t + 1.0, r.time) for r in rows]
    assert score_bop(dataset, rows + far, targets).overall.ar == 1.0
    first = [BopRow(r.scene_id, r.im_id, r.obj_id, 2.0, r.R, r.t + 1.0, r.time) for r in rows]
    assert score_bop(dataset, rows + first, targets).overall.ar == 0.0


# ----------------------------------------------------------------- estimating


def test_estimate_many_matches_estimate_and_reports_a_bad_mask(dataset, codebooks):
    image = dataset.image(1, 1)
    depth = image.depth()
    objects = [(image.mask(g.gt_id), codebooks[g.obj_id]) for g in image.gts]
    empty = np.zeros_like(objects[0][0])
    frame = edgepose.estimate_many(depth, image.K, [*objects, (empty, codebooks[1])], depth_scale=1.0)
    assert len(frame) == len(objects) + 1
    assert frame.poses[-1] is None and isinstance(frame.errors[-1], InvalidCloudError)
    assert {"prepare_query", "retrieve", "refine_hypotheses"} <= set(frame.timings)
    assert frame.timings["total"] == frame.seconds > 0
    for (mask, book), pose, error in zip(objects, frame.poses, frame.errors):
        assert error is None and pose is not None
        cloud = edgepose.cloud_from_depth(depth, image.K, mask, 1.0)
        alone = edgepose.estimate(cloud, book, depth=depth, K=image.K, depth_scale=1.0)
        assert np.array_equal(pose.matrix, alone.matrix) and pose.confidence == alone.confidence
        assert pose.evidence == alone.evidence
    with pytest.raises(InvalidCloudError, match="mask shape"):
        edgepose.estimate_many(depth, image.K, [(empty[:-1], codebooks[1])], depth_scale=1.0)
    assert len(edgepose.estimate_many(depth, image.K, [], depth_scale=1.0)) == 0


def test_a_full_round_trip_scores_edgepose_well(dataset, codebooks, tmp_path):
    targets = dataset.targets()
    rows = run_bop(dataset, targets, codebooks)
    assert len(rows) == sum(t.inst_count for t in targets)
    csv = tmp_path / "edgepose_tinyset-test.csv"
    from edgepose.eval.bop import write_bop_csv

    write_bop_csv(csv, rows)
    back = read_bop_csv(csv)
    scores = score_bop(dataset, back, targets)
    # Clean synthetic views with exact masks: edgepose finds every object.
    assert scores.overall.ar >= 0.9 and scores.overall.add_s >= 0.9, scores.markdown()
    for image_rows in _by_image(back).values():
        assert len({r.time for r in image_rows}) == 1


def _by_image(rows):
    out: dict = {}
    for r in rows:
        out.setdefault((r.scene_id, r.im_id), []).append(r)
    return out


# ----------------------------------------------------------------- detections


def rle_counts(mask: np.ndarray) -> list[int]:
    """Uncompressed COCO RLE run lengths of ``mask``."""
    return encode_rle(mask)["counts"]


def rle_string(counts: list[int]) -> str:
    """COCO's compressed form of ``counts`` (the inverse of the decoder)."""
    out = []
    for i, value in enumerate(counts):
        x = value - counts[i - 2] if i > 2 else value
        more = True
        while more:
            c = x & 0x1F
            x >>= 5
            more = (x != -1) if c & 0x10 else (x != 0)
            if more:
                c |= 0x20
            out.append(chr(c + 48))
    return "".join(out)


def test_rle_decoding_by_hand():
    # Runs 1 background, 2 mask, 3 background; 3 rows × 2 columns, column-major.
    expected = np.array([[False, False], [True, False], [True, False]])
    assert (decode_rle({"counts": [1, 2, 3], "size": [3, 2]}) == expected).all()
    assert (decode_rle({"counts": "123", "size": [3, 2]}) == expected).all()
    assert encode_rle(expected) == {"counts": [1, 2, 3], "size": [3, 2]}
    assert encode_rle(~expected)["counts"] == [0, 1, 2, 3]  # a mask pixel first: an empty first run
    # Runs 1, 2, 1, 2: both columns background, mask, mask. Compressed, the
    # fourth run is stored as its difference to the second (0: "0").
    assert rle_string([1, 2, 1, 2]) == "1210"
    assert (decode_rle({"counts": "1210", "size": [3, 2]}) == [[False, False], [True, True], [True, True]]).all()
    with pytest.raises(ValueError, match="cover"):
        decode_rle({"counts": [1, 2], "size": [3, 2]})


def test_detections_file_gives_the_same_estimates_as_the_masks(dataset, codebooks, tmp_path):
    targets = dataset.targets(scenes=[2])
    entries = []
    for t in targets:
        image = dataset.image(t.scene_id, t.im_id)
        for n, g in enumerate(g for g in image.gts if g.obj_id == t.obj_id):
            mask = image.mask(g.gt_id)
            counts = rle_counts(mask)
            assert (decode_rle({"counts": counts, "size": list(mask.shape)}) == mask).all()
            entries.append(
                {
                    "scene_id": t.scene_id,
                    "image_id": t.im_id,
                    "category_id": t.obj_id,
                    "score": 0.9 - 0.1 * n,
                    "bbox": [0, 0, 1, 1],
                    "segmentation": {"counts": rle_string(counts) if n % 2 == 0 else counts, "size": list(mask.shape)},
                    "time": 0.05,
                }
            )
    path = tmp_path / "detections.json"
    path.write_text(json.dumps(entries))
    with_masks = run_bop(dataset, targets, codebooks)
    with_detections = run_bop(dataset, targets, codebooks, detections=read_detections(path))
    assert len(with_detections) == len(with_masks)
    for a, b in zip(with_masks, with_detections):
        assert (a.obj_id, a.im_id) == (b.obj_id, b.im_id)
        assert np.allclose(a.t, b.t, atol=1e-3)
        assert b.time >= 0.05  # the detector's time counts
    path.write_text(json.dumps([{"scene_id": 1}]))
    with pytest.raises(BopDatasetError, match="detection 0 malformed"):
        read_detections(path)


# ----------------------------------------------------------------- the command


def test_edgepose_bop_command(dataset_dir, tmp_path):
    out = tmp_path / "results"
    result = run("bop", str(dataset_dir), "--scenes", "2", "-o", str(out))
    assert result.returncode == 0, result.stderr
    csv = out / "edgepose_tinyset-test.csv"
    lines = csv.read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time"
    rows = read_bop_csv(csv)
    assert len(rows) == len(lines) - 1 == 9 and {r.scene_id for r in rows} == {2}
    scores = json.loads((out / "edgepose_tinyset-test_scores.json").read_text())
    assert scores["overall"]["targets"] == 9 and scores["overall"]["ar"] >= 0.9
    assert set(scores["objects"]) == {"1", "2", "5"}
    assert "| **all** | 9 |" in result.stdout and "AR_MSSD" in result.stdout
    assert (out / "edgepose_tinyset-test_scores.md").read_text() in result.stdout + "\n"
    # A rerun reuses the codebooks.
    again = run("bop", str(dataset_dir), "--scenes", "2", "-o", str(out))
    assert again.returncode == 0 and read_bop_csv(csv)[0].obj_id == rows[0].obj_id


def test_edgepose_bop_command_errors(dataset_dir, tmp_path):
    fails_cleanly(run("bop", str(tmp_path / "missing")), "no such dataset folder")
    fails_cleanly(run("bop", str(dataset_dir), "--scenes", "x"), "--scenes must be comma-separated")
    fails_cleanly(run("bop", str(dataset_dir), "--scenes", "9", "-o", str(tmp_path)), "no targets")
    bad = tmp_path / "bad.json"
    bad.write_text("[1]")
    fails_cleanly(run("bop", str(dataset_dir), "--masks", str(bad), "-o", str(tmp_path)), "detection 0 malformed")


def test_a_split_without_published_ground_truth_gives_the_csv_alone(dataset_dir, tmp_path):
    # As ITODD's test split: cameras, depth and targets, but no poses or masks.
    copy = tmp_path / "itodd_like"
    shutil.copytree(dataset_dir, copy)
    scene = copy / "test" / "000002"
    masks = {p.name: read_mask_png(p) for p in sorted((scene / "mask_visib").glob("*.png"))}
    gt = json.loads((scene / "scene_gt.json").read_text())
    for name in ("scene_gt.json", "scene_gt_info.json"):
        (scene / name).unlink()
    shutil.rmtree(scene / "mask_visib")
    entries = []
    for im_id, instances in gt.items():
        for gt_id, a in enumerate(instances):
            mask = masks[f"{int(im_id):06d}_{gt_id:06d}.png"]
            entries.append(
                {
                    "scene_id": 2,
                    "image_id": int(im_id),
                    "category_id": a["obj_id"],
                    "score": 0.9,
                    "segmentation": {"counts": rle_counts(mask), "size": list(mask.shape)},
                }
            )
    detections = tmp_path / "detections.json"
    detections.write_text(json.dumps(entries))
    assert not BopDataset(copy).has_ground_truth(2) and BopDataset(copy).image_ids(2) == [0, 1, 2]
    fails_cleanly(run("bop", str(copy), "--scenes", "2", "-o", str(tmp_path / "a")), "not published")
    result = run("bop", str(copy), "--scenes", "2", "--masks", str(detections), "-o", str(tmp_path / "b"))
    assert result.returncode == 0, result.stderr
    assert "no ground truth published" in result.stdout
    assert len(read_bop_csv(tmp_path / "b" / "edgepose_itodd_like-test.csv")) == 9
    assert not (tmp_path / "b" / "edgepose_itodd_like-test_scores.json").exists()


def test_scoring_reads_models_eval_and_other_splits_keep_their_own_targets(dataset_dir, tmp_path):
    copy = tmp_path / "withval"
    shutil.copytree(dataset_dir, copy)
    # models_eval/models_info.json, when there, gives the diameters and symmetries the scores use.
    (copy / "models_eval").mkdir()
    info = json.loads((copy / "models" / "models_info.json").read_text())
    info["2"]["diameter"] = 200.0
    (copy / "models_eval" / "models_info.json").write_text(json.dumps(info))
    objects = BopDataset(copy).objects
    assert objects[2].diameter == pytest.approx(0.2) and objects[2].mesh.parent.name == "models"
    # The test split's targets file never stands in for another split's.
    (copy / "test").rename(copy / "val")
    (copy / "test_targets_bop19.json").write_text(
        json.dumps([{"scene_id": 1, "im_id": 0, "obj_id": 1, "inst_count": 1}])
    )
    val = BopDataset(copy, "val").targets()
    assert len(val) == len(BopDataset(dataset_dir).targets()) > 1


def test_one_image_with_two_times_is_refused(dataset):
    rows = truth_rows(dataset)
    first = rows[0]
    odd = BopRow(first.scene_id, first.im_id, first.obj_id, 0.1, first.R, first.t, first.time + 0.5)
    with pytest.raises(ValueError, match="one time per image"):
        score_bop(dataset, [*rows, odd], dataset.targets())
    assert score_bop(dataset, rows, dataset.targets()).time == pytest.approx(0.01)
