"""The command line through its real entry point (the ``edgepose`` console
script), on views rendered with known poses."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import edgepose
import numpy as np
import pytest
from edgepose.encoder import MODELS_DIR
from edgepose.eval import pose_errors, read_bop_csv, render_view

SHIPPED = Path(edgepose.__file__).resolve().parent / "codebooks"
DRILL_CODEBOOK = SHIPPED / "power_drill.codebook"


def run(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    beside_python = Path(sys.executable).with_name("edgepose")
    exe = str(beside_python) if beside_python.exists() else shutil.which("edgepose")
    if exe is None:
        pytest.skip("edgepose entry point not installed")
    return subprocess.run([exe, *args], capture_output=True, text=True, timeout=180, cwd=cwd)


def fails_cleanly(out: subprocess.CompletedProcess[str], message: str) -> None:
    assert out.returncode == 1, (out.stdout, out.stderr)
    assert message in out.stderr, out.stderr
    assert "Traceback" not in out.stderr
    assert out.stderr.strip().startswith("error:"), out.stderr


@pytest.fixture(scope="module")
def drill():
    """The shipped demo object: its codebook and one rendered view with its truth."""
    import trimesh

    mesh = trimesh.load(SHIPPED / "power_drill.ply", process=False)
    codebook = edgepose.Codebook.load(DRILL_CODEBOOK)
    view = render_view(mesh, seed=5)
    return codebook, view


def assert_close_to_truth(result: dict, view, codebook) -> None:
    T = np.asarray(result["matrix"])
    points = codebook.model.mesh_points
    e = pose_errors(points, T, view.T_cam_obj, codebook.model.diameter, symmetric=False)
    assert e.rotation_deg < 5.0 and e.translation_mm < 10.0, e
    assert e.correct_add_or_s


# ----------------------------------------------------------------- --version, --help


def test_version_proves_the_core_and_the_networks_load():
    out = run("--version")
    assert out.returncode == 0, out.stderr
    manifest = json.loads((MODELS_DIR / "manifest.json").read_text())
    assert out.stdout.startswith(f"edgepose {edgepose.__version__}")
    assert "compiled core loaded" in out.stdout
    assert manifest["files"]["encoder.onnx"][:12] in out.stdout
    assert manifest["files"]["irr.onnx"][:12] in out.stdout
    assert f"fingerprint {manifest.get('fingerprint', manifest['files']['encoder.onnx'])[:12]}" in out.stdout
    assert "onnxruntime 1." in out.stdout


def test_module_entry_point_matches_console_script():
    out = subprocess.run([sys.executable, "-m", "edgepose.cli", "--version"], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout == run("--version").stdout


def test_help_lists_the_commands_with_worked_examples():
    out = run("--help")
    assert out.returncode == 0
    for command in ("demo", "build", "estimate", "track", "eval"):
        assert f"edgepose {command}" in out.stdout
    assert "--K" in out.stdout and "--mask" in out.stdout


# ----------------------------------------------------------------- demo


def test_demo_works_with_only_the_installed_package(tmp_path):
    from PIL import Image

    out = run("demo", "--seed", "3", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "shipped codebook power_drill.codebook, 2100 views" in out.stdout
    assert "estimated   T_cam_obj" in out.stdout and "true        T_cam_obj" in out.stdout
    assert "(correct at 0.1 × diameter" in out.stdout
    # The two printed matrices agree (the estimate is right on this view).
    numbers = [float(x) for line in out.stdout.splitlines() if line.startswith("            ") for x in line.split()]
    estimated, true = np.reshape(numbers[:16], (4, 4)), np.reshape(numbers[16:32], (4, 4))
    assert np.abs(estimated[:3, :3] - true[:3, :3]).max() < 0.05
    assert np.linalg.norm(estimated[:3, 3] - true[:3, 3]) < 0.01

    picture = tmp_path / "edgepose_demo.png"
    assert picture.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = np.asarray(Image.open(picture).convert("RGB")).astype(int)
    assert image.shape[0] >= 300 and image.shape[1] >= 600
    blue = (np.abs(image - (70, 160, 255)).sum(axis=2) < 60).sum()
    orange = (np.abs(image - (255, 140, 30)).sum(axis=2) < 60).sum()
    assert blue > 2000 and orange > 2000, (blue, orange)


def test_demo_builds_a_codebook_for_a_given_mesh(ycb_dir, tmp_path):
    out = run(
        "demo",
        "--mesh",
        str(ycb_dir / "banana.ply"),
        "--views",
        "500",
        "--seed",
        "1",
        "--show",
        str(tmp_path / "banana.png"),
    )
    assert out.returncode == 0, out.stderr
    assert "codebook 500 views built in" in out.stdout
    assert "(correct at 0.1 × diameter" in out.stdout
    assert (tmp_path / "banana.png").stat().st_size > 10_000


def test_demo_reports_a_missing_mesh_clearly(tmp_path):
    fails_cleanly(run("demo", "--mesh", str(tmp_path / "nope.obj")), "no such file")


# ----------------------------------------------------------------- build


def test_build_makes_loadable_codebooks_for_a_folder(ycb_dir, tmp_path):
    import trimesh

    meshes = tmp_path / "meshes"
    meshes.mkdir()
    shutil.copy(ycb_dir / "banana.ply", meshes)
    trimesh.creation.box(extents=(80.0, 50.0, 30.0)).export(meshes / "block.stl")  # millimetres
    (meshes / "notes.txt").write_text("not a mesh")
    out = run("build", str(meshes), "-o", str(tmp_path / "books"), "--views", "500")
    assert out.returncode == 0, out.stderr
    assert "banana" in out.stdout and "block" in out.stdout and "500" in out.stdout
    assert sorted(p.name for p in (tmp_path / "books").iterdir()) == ["banana.codebook", "block.codebook"]
    block = edgepose.Codebook.load(tmp_path / "books" / "block.codebook")
    assert len(block) == 500
    assert block.model.diameter == pytest.approx(np.linalg.norm([0.08, 0.05, 0.03]), rel=0.03)  # mm detected


def test_build_reports_a_broken_mesh_and_still_builds_the_others(ycb_dir, tmp_path):
    (tmp_path / "broken.obj").write_text("v 0 0 0\nf 1 1 1\n")
    out = run("build", str(tmp_path / "broken.obj"), str(ycb_dir / "banana.ply"), "-o", str(tmp_path), "--views", "100")
    assert out.returncode == 1
    assert "broken.obj" in out.stderr and "Traceback" not in out.stderr
    assert (tmp_path / "banana.codebook").is_file() and not (tmp_path / "broken.codebook").exists()


def test_build_refuses_a_missing_path(tmp_path):
    fails_cleanly(run("build", str(tmp_path / "nothing"), "-o", str(tmp_path)), "no such file or folder")


# ----------------------------------------------------------------- estimate


def test_estimate_from_npy_ply_and_pcd_clouds(drill, tmp_path):
    import trimesh

    codebook, view = drill
    np.save(tmp_path / "cloud.npy", view.cloud)
    trimesh.PointCloud(view.cloud).export(tmp_path / "cloud.ply")
    write_pcd(tmp_path / "cloud.pcd", view.cloud, binary=True)
    for name in ("cloud.npy", "cloud.ply", "cloud.pcd"):
        out = run("estimate", "--codebook", str(DRILL_CODEBOOK), str(tmp_path / name))
        assert out.returncode == 0, out.stderr
        result = json.loads(out.stdout)
        assert set(result) >= {"matrix", "score", "fit", "view", "timings"}
        assert result["points"] == len(view.cloud)
        assert result["fit"] < 0.005 and result["timings"]["total"] > 0
        # The default and the strict rule both trust a clean view's pose.
        assert result["trusted"] and result["trusted_strict"]
        assert result["confidence"] >= result["strict_threshold"] > 0.5
        assert all(set(a) == {"matrix", "margin"} and len(a["matrix"]) == 4 for a in result["alternatives"])
        assert_close_to_truth(result, view, codebook)


def test_estimate_warns_of_a_stale_codebook_in_one_line(drill, tmp_path):
    from test_codebook import _resealed

    codebook, view = drill
    stale = tmp_path / "stale.codebook"
    stale.write_bytes(_resealed(DRILL_CODEBOOK.read_bytes(), lambda m: m.update(symmetry_search="0" * 16)))
    np.save(tmp_path / "cloud.npy", view.cloud)
    out = run("estimate", "--codebook", str(stale), str(tmp_path / "cloud.npy"))
    assert out.returncode == 0, out.stderr
    assert out.stderr.startswith("warning: ") and "older or unknown symmetry search" in out.stderr, out.stderr
    assert len(out.stderr.splitlines()) == 1 and "StaleCodebookWarning" not in out.stderr, out.stderr
    assert_close_to_truth(json.loads(out.stdout), view, codebook)


def test_estimate_from_a_depth_png_with_k_and_mask(drill, tmp_path):
    from PIL import Image

    codebook, view = drill
    depth_mm = np.round(view.depth * 1000).astype(np.uint16)
    Image.fromarray(depth_mm).save(tmp_path / "depth.png")
    Image.fromarray(view.mask.astype(np.uint8) * 255).save(tmp_path / "mask.png")
    (tmp_path / "camera.json").write_text(json.dumps({"cam_K": view.camera.K.ravel().tolist()}))
    (tmp_path / "truth.json").write_text(json.dumps({"matrix": view.T_cam_obj.tolist()}))
    K_numbers = " ".join(str(x) for x in view.camera.K.ravel())

    first = run(
        "estimate",
        "-c",
        str(DRILL_CODEBOOK),
        str(tmp_path / "depth.png"),
        "--K",
        str(tmp_path / "camera.json"),
        "--mask",
        str(tmp_path / "mask.png"),
        "--truth",
        str(tmp_path / "truth.json"),
        "--show",
        str(tmp_path / "shown.png"),
        "--bop-csv",
        str(tmp_path / "bop.csv"),
        "--obj-id",
        "15",
    )
    assert first.returncode == 0, first.stderr
    result = json.loads(first.stdout)
    assert result["points"] == int(view.mask.sum())
    assert_close_to_truth(result, view, codebook)
    assert result["errors"]["correct_add"] and result["errors"]["rotation_deg"] < 5
    assert (tmp_path / "shown.png").read_bytes()[:4] == b"\x89PNG"

    second = run(
        "estimate",
        "-c",
        str(DRILL_CODEBOOK),
        str(tmp_path / "depth.png"),
        "--K",
        K_numbers,
        "--mask",
        str(tmp_path / "mask.png"),
        "--bop-csv",
        str(tmp_path / "bop.csv"),
        "--im-id",
        "1",
    )
    assert second.returncode == 0, second.stderr
    assert json.loads(second.stdout)["matrix"] == result["matrix"]  # same input, same pose
    rows = read_bop_csv(tmp_path / "bop.csv")
    assert [(r.im_id, r.obj_id) for r in rows] == [(0, 15), (1, 1)]
    np.testing.assert_allclose(rows[0].R, np.asarray(result["matrix"])[:3, :3], atol=1e-12)
    np.testing.assert_allclose(rows[0].t, np.asarray(result["matrix"])[:3, 3], atol=1e-12)


def test_estimate_refuses_bad_inputs_with_one_line(drill, tmp_path):
    codebook, view = drill
    np.save(tmp_path / "mm.npy", view.cloud * 1000)
    np.save(tmp_path / "flat.npy", view.cloud[:, :2])
    (tmp_path / "depth.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    (tmp_path / "bad.codebook").write_bytes(b"\x00" * 64)
    cb = str(DRILL_CODEBOOK)
    fails_cleanly(run("estimate", "-c", cb, str(tmp_path / "missing.ply")), "no such file")
    fails_cleanly(run("estimate", "-c", cb, str(tmp_path / "mm.npy")), "millimetres")
    fails_cleanly(run("estimate", "-c", cb, str(tmp_path / "flat.npy")), "expected (N, 3)")
    fails_cleanly(run("estimate", "-c", cb, str(tmp_path / "depth.png")), "needs --K")
    fails_cleanly(
        run("estimate", "-c", cb, str(tmp_path / "depth.png"), "--K", "1 2 3", "--mask", "m.png"), "9 numbers"
    )
    fails_cleanly(run("estimate", "-c", str(tmp_path / "bad.codebook"), str(tmp_path / "mm.npy")), "codebook")
    write_pcd(tmp_path / "packed.pcd", view.cloud, binary=True, data="binary_compressed")
    fails_cleanly(run("estimate", "-c", cb, str(tmp_path / "packed.pcd")), "binary_compressed")


def test_estimate_saves_a_rerun_recording(drill, tmp_path):
    pytest.importorskip("rerun", reason="the viz extra (rerun-sdk) is not installed")
    codebook, view = drill
    np.save(tmp_path / "cloud.npy", view.cloud)
    out = run("estimate", "-c", str(DRILL_CODEBOOK), str(tmp_path / "cloud.npy"), "--rrd", str(tmp_path / "run.rrd"))
    assert out.returncode == 0, out.stderr
    recording = (tmp_path / "run.rrd").read_bytes()
    assert recording[:3] == b"RRF"
    for entity in (b"camera/power_drill/observed", b"camera/power_drill/estimate/model"):
        assert entity in recording  # entity paths are stored uncompressed


def write_pcd(path: Path, points: np.ndarray, binary: bool, data: str | None = None) -> None:
    """A PCL file with x y z (float32) and an rgb field the reader must skip."""
    rgb = np.arange(len(points), dtype=np.uint32)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\n"
        f"COUNT 1 1 1 1\nWIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\n"
        f"DATA {data or ('binary' if binary else 'ascii')}\n"
    )
    if binary:
        table = np.zeros(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
        table["x"], table["y"], table["z"], table["rgb"] = points[:, 0], points[:, 1], points[:, 2], rgb
        path.write_bytes(header.encode() + table.tobytes())
    else:
        body = "".join(f"{x!r} {y!r} {z!r} {c}\n" for (x, y, z), c in zip(points.astype(np.float32).tolist(), rgb))
        path.write_text(header + body)


# ----------------------------------------------------------------- eval


def test_eval_prints_the_accuracy_table(ycb_dir):
    out = run("eval", str(ycb_dir / "banana.ply"), "--views", "3")
    assert out.returncode == 0, out.stderr
    rows = [line for line in out.stdout.splitlines() if "banana" in line or " all " in line]
    assert len(rows) == 2, out.stdout
    cells = [c.strip() for c in rows[0].strip("│┃ ").split("│")]
    assert cells[:3] == ["banana", "no", "edgepose"]
    assert cells[3].endswith("%") and 0 <= float(cells[3].rstrip(" %")) <= 100
    assert float(cells[7]) > 0  # median ms


def test_eval_refuses_an_unknown_method(ycb_dir):
    fails_cleanly(run("eval", str(ycb_dir / "banana.ply"), "--methods", "magic"), "unknown methods")


# ----------------------------------------------------------------- track


def track_depth_frames(tmp_path: Path, frames: list, K: np.ndarray):
    """``edgepose track`` on ``frames`` ((depth metres, mask) pairs) written as
    16-bit millimetre PNGs with mask PNGs of the same names; its result."""
    from PIL import Image

    (tmp_path / "frames").mkdir()
    (tmp_path / "masks").mkdir()
    for i, (depth, mask) in enumerate(frames):
        Image.fromarray(np.round(depth * 1000).astype(np.uint16)).save(tmp_path / "frames" / f"{i:04d}.png")
        Image.fromarray(mask.astype(np.uint8) * 255).save(tmp_path / "masks" / f"{i:04d}.png")
    return run(
        "track", "-c", str(DRILL_CODEBOOK), str(tmp_path / "frames"), "--K", " ".join(str(x) for x in K.ravel()),
        "--masks", str(tmp_path / "masks"), "-o", str(tmp_path / "poses.csv"),
    )  # fmt: skip


def test_track_follows_depth_frames_and_reports_a_bad_frame(drill, tmp_path):
    import csv

    import trimesh

    codebook, view = drill
    mesh = trimesh.load(SHIPPED / "power_drill.ply", process=False)
    frames, truths = [], []
    T = view.T_cam_obj
    for i in range(6):
        T = T.copy()
        T[:3, :3] = trimesh.transformations.rotation_matrix(np.radians(3.0), [0, 1, 0])[:3, :3] @ T[:3, :3]
        frame = render_view(mesh, T_cam_obj=T, seed=i)
        mask = frame.mask if i != 3 else np.zeros_like(frame.mask)  # frame 3: the object is lost
        frames.append((frame.depth, mask))
        truths.append(T)
    out = track_depth_frames(tmp_path, frames, view.camera.K)
    assert out.returncode == 0, out.stderr
    assert "6 frames: 4 tracked, 1 initialised, 0 re-initialised, 1 without a pose" in out.stdout
    rows = list(csv.DictReader((tmp_path / "poses.csv").open()))
    assert [r["mode"] for r in rows[:3]] == ["initialised", "tracked", "tracked"]
    assert rows[3]["mode"].startswith("error: ") and rows[3]["m00"] == ""
    for row, T_true in zip(rows, truths):
        if row["m00"]:
            T_est = np.array([float(row[f"m{r}{c}"]) for r in range(4) for c in range(4)]).reshape(4, 4)
            e = pose_errors(codebook.model.mesh_points, T_est, T_true, codebook.model.diameter, False)
            assert e.correct_add_or_s and float(row["confidence"]) >= 0.5
    # A frame file that cannot be read is reported the same way; the track goes on.
    (tmp_path / "frames" / "0004.png").write_bytes(b"\x89PNG not really")
    K = " ".join(str(x) for x in view.camera.K.ravel())
    out = run(
        "track", "-c", str(DRILL_CODEBOOK), str(tmp_path / "frames"), "--K", K,
        "--masks", str(tmp_path / "masks"), "-o", str(tmp_path / "again.csv"),
    )  # fmt: skip
    assert out.returncode == 0 and "4 tracked" not in out.stdout and "2 without a pose" in out.stdout, out.stdout
    rows = list(csv.DictReader((tmp_path / "again.csv").open()))
    assert rows[4]["mode"].startswith("error: ") and rows[5]["m00"] != ""
    fails_cleanly(run("track", "-c", str(DRILL_CODEBOOK), str(tmp_path / "frames")), "need --K")


def test_track_gives_the_tracker_each_depth_frame_whole(tmp_path):
    # The drill sliding on a table, its masks spilled onto the table where
    # the two meet: given the frames, the tracker leaves the table out and
    # tracks every frame (from the clouds alone most frames fail the check).
    from edgepose.eval.scenes import render_scene
    from edgepose.model import read_mesh

    mesh = read_mesh(SHIPPED / "power_drill.ply")
    T = render_scene(mesh, "on_table", seed=0).T_cam_obj
    views = []
    for i in range(6):
        T_i = T.copy()
        T_i[0, 3] += 0.004 * i  # along the camera's x axis, which lies in the table
        views.append(render_scene(mesh, "on_table", seed=0, T_cam_obj=T_i))
    out = track_depth_frames(tmp_path, [(v.depth, v.mask) for v in views], views[0].K)
    assert out.returncode == 0, out.stderr
    assert "6 frames: 5 tracked, 1 initialised, 0 re-initialised" in out.stdout


def test_eval_at_a_stress_level_reports_confidence_and_draws_a_reliability_diagram(tmp_path):
    out = run(
        "eval", str(SHIPPED / "power_drill.ply"), "--views", "3", "--stress", "visible70",
        "--reliability", str(tmp_path / "rel.png"),
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "stress visible70" in out.stdout and "confidence at stress visible70" in out.stdout
    assert "AUROC" in out.stdout and "strict" in out.stdout and (tmp_path / "rel.png").stat().st_size > 10_000
    fails_cleanly(run("eval", str(SHIPPED / "power_drill.ply"), "--stress", "visible99"), "--stress must be one of")
