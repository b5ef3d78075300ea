"""File readers (clouds, PCD, PNG, intrinsics, poses) and the result picture."""

from __future__ import annotations

import json

import numpy as np
import pytest
from edgepose import io
from edgepose.viz import MODEL, OBSERVED, Frame, NullRecorder, draw_result, recorder, save_result_png
from test_cli import write_pcd


def test_pcd_ascii_and_binary_give_back_the_points(tmp_path, rng):
    points = rng.normal(size=(100, 3))
    for binary in (False, True):
        write_pcd(tmp_path / "c.pcd", points, binary=binary)
        np.testing.assert_allclose(io.read_pcd(tmp_path / "c.pcd"), points.astype(np.float32), rtol=0, atol=1e-6)


def test_pcd_with_multi_count_fields_before_xyz(tmp_path, rng):
    points = rng.normal(size=(10, 3)).astype(np.float32)
    table = np.zeros(10, dtype=[("normal", "<f8", (3,)), ("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    table["normal"], table["x"], table["y"], table["z"] = 7.0, points[:, 0], points[:, 1], points[:, 2]
    header = (
        "VERSION 0.7\nFIELDS normal x y z\nSIZE 8 4 4 4\nTYPE F F F F\nCOUNT 3 1 1 1\n"
        "WIDTH 10\nHEIGHT 1\nPOINTS 10\nDATA binary\n"
    )
    (tmp_path / "n.pcd").write_bytes(header.encode() + table.tobytes())
    np.testing.assert_array_equal(io.read_pcd(tmp_path / "n.pcd"), points)
    ascii_rows = "".join(f"7 7 7 {x!r} {y!r} {z!r}\n" for x, y, z in points.tolist())
    (tmp_path / "a.pcd").write_text(header.replace("binary", "ascii") + ascii_rows)
    np.testing.assert_array_equal(io.read_pcd(tmp_path / "a.pcd"), points)


def test_pcd_truncated_data_is_an_error(tmp_path, rng):
    write_pcd(tmp_path / "c.pcd", rng.normal(size=(50, 3)), binary=True)
    blob = (tmp_path / "c.pcd").read_bytes()
    (tmp_path / "c.pcd").write_bytes(blob[:-20])
    with pytest.raises(io.FileFormatError, match="fewer than the 50 points"):
        io.read_pcd(tmp_path / "c.pcd")


def test_unknown_cloud_suffix_is_an_error(tmp_path):
    (tmp_path / "c.xyz").write_text("0 0 0\n")
    with pytest.raises(io.FileFormatError, match="unsupported cloud file type"):
        io.read_cloud(tmp_path / "c.xyz")


def test_a_damaged_png_is_a_file_format_error(tmp_path, rng):
    # Found by benches/fuzz.py: a flipped bit in a chunk's header made Pillow
    # raise SyntaxError ("broken PNG file"), which escaped as itself.
    depth = rng.integers(0, 65535, size=(48, 64)).astype(np.uint16)
    io.write_png(tmp_path / "d.png", depth)
    blob = bytearray((tmp_path / "d.png").read_bytes())
    damaged = []
    for i in range(8, 64):  # every bit of the header and the first chunks flipped
        for bit in range(8):
            flipped = bytearray(blob)
            flipped[i] ^= 1 << bit
            damaged.append(bytes(flipped))
    damaged += [bytes(blob[:n]) for n in (10, 40, len(blob) // 2, len(blob) - 5)]  # cut short
    outcomes = set()
    for data in damaged:
        (tmp_path / "x.png").write_bytes(data)
        try:
            io.read_depth_png(tmp_path / "x.png")
            outcomes.add("read")
        except io.FileFormatError as e:
            outcomes.add(str(e).split("(")[1].split(":")[0])
    assert "SyntaxError" in outcomes, outcomes


def test_sixteen_bit_png_round_trip(tmp_path, rng):
    depth = rng.integers(0, 65535, size=(48, 64)).astype(np.uint16)
    io.write_png(tmp_path / "d.png", depth)
    back = io.read_depth_png(tmp_path / "d.png")
    assert back.dtype == np.uint16
    np.testing.assert_array_equal(back, depth)
    mask = depth > 30000
    io.write_png(tmp_path / "m.png", mask)
    np.testing.assert_array_equal(io.read_mask_png(tmp_path / "m.png"), mask)


def test_masks_with_alpha_or_a_palette_mark_only_the_object(tmp_path):
    from PIL import Image

    mask = np.zeros((20, 30), bool)
    mask[5:12, 8:20] = True
    grey = (mask * 255).astype(np.uint8)
    rgba = np.dstack([grey, grey, grey, np.full_like(grey, 255)])  # opaque everywhere
    Image.fromarray(rgba, "RGBA").save(tmp_path / "rgba.png")
    Image.fromarray(np.dstack([grey, np.full_like(grey, 255)]), "LA").save(tmp_path / "la.png")
    palette = Image.fromarray(mask.astype(np.uint8), "P")
    palette.putpalette([0, 0, 0, 255, 255, 255])  # index 0 black background, 1 white object
    palette.save(tmp_path / "palette.png")
    for name in ("rgba.png", "la.png", "palette.png"):
        np.testing.assert_array_equal(io.read_mask_png(tmp_path / name), mask, err_msg=name)


def test_intrinsics_from_numbers_and_json(tmp_path):
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1]])
    np.testing.assert_array_equal(io.parse_intrinsics("572.4 0 325.3 0 573.6 242 0 0 1"), K)
    np.testing.assert_array_equal(io.parse_intrinsics("572.4,0,325.3,0,573.6,242,0,0,1"), K)
    for content in (K.tolist(), {"K": K.ravel().tolist()}, {"fx": 572.4, "fy": 573.6, "cx": 325.3, "cy": 242.0}):
        (tmp_path / "k.json").write_text(json.dumps(content))
        np.testing.assert_array_equal(io.parse_intrinsics(str(tmp_path / "k.json")), K)
    with pytest.raises(io.FileFormatError, match="9 numbers"):
        io.parse_intrinsics("1 2 3")
    with pytest.raises(io.FileFormatError, match="not a pinhole"):
        io.parse_intrinsics("1 0 0 0 1 0 0 0 2")


def test_pose_from_json_bop_and_npy(tmp_path):
    T = np.eye(4)
    T[:3, 3] = (0.1, -0.2, 0.7)
    (tmp_path / "a.json").write_text(json.dumps(T.tolist()))
    (tmp_path / "b.json").write_text(
        json.dumps({"cam_R_m2c": np.eye(3).ravel().tolist(), "cam_t_m2c": [100, -200, 700]})
    )
    np.save(tmp_path / "c.npy", T)
    for name in ("a.json", "b.json", "c.npy"):
        np.testing.assert_allclose(io.read_pose(tmp_path / name), T)
    (tmp_path / "d.json").write_text("[1, 2, 3]")
    with pytest.raises(io.FileFormatError, match="not a 4×4 pose"):
        io.read_pose(tmp_path / "d.json")


def _cube_surface(n: int, rng) -> np.ndarray:
    points = rng.uniform(-0.05, 0.05, size=(n, 3))
    axis = rng.integers(0, 3, size=n)
    points[np.arange(n), axis] = np.sign(rng.normal(size=n)) * 0.05
    return points


def test_picture_overlays_cloud_and_model_where_they_are(tmp_path, rng):
    model = _cube_surface(4000, rng)
    T = np.eye(4)
    T[:3, 3] = (0.0, 0.0, 0.6)
    posed = model @ T[:3, :3].T + T[:3, 3]
    cloud = posed[posed[:, 2] < 0.6 - 0.049]  # the face towards the camera
    K = np.array([[570.0, 0, 320], [0, 570, 240], [0, 0, 1]])
    image = draw_result(Frame(cloud, model, T, K=K), ["a line of text"])
    assert image.dtype == np.uint8 and image.ndim == 3

    def count(colour, region):
        return int((np.abs(region.astype(int) - colour).sum(axis=2) < 60).sum())

    panels = image[64:]
    camera, above = panels[:, :300], panels[:, 302:602]
    assert count(OBSERVED, camera) > 2000 and count(MODEL, camera) > 300
    assert count(MODEL, above) > 3000 and count(OBSERVED, above) > 300
    # A pose 10 cm off to the right puts the model's outline right of the cloud.
    T_off = T.copy()
    T_off[0, 3] += 0.1
    shifted = draw_result(Frame(cloud, model, T_off, K=K))[64:, :300]
    cols_model = np.nonzero((np.abs(shifted.astype(int) - MODEL).sum(axis=2) < 60).any(axis=0))[0]
    cols_cloud = np.nonzero((np.abs(shifted.astype(int) - OBSERVED).sum(axis=2) < 60).any(axis=0))[0]
    assert np.median(cols_model) > np.median(cols_cloud) + 50

    path = save_result_png(tmp_path / "sub" / "r.png", Frame(cloud, model, T), ["no K: a virtual camera"])
    from PIL import Image

    assert Image.open(path).size == (image.shape[1], image.shape[0])


def test_recorder_is_a_no_op_unless_asked_for(tmp_path, capsys):
    assert isinstance(recorder(), NullRecorder)
    try:
        import rerun  # noqa: F401
    except ImportError:
        chosen = recorder(save=tmp_path / "x.rrd")
        assert isinstance(chosen, NullRecorder)
        assert "viz extra" in capsys.readouterr().err
    else:
        chosen = recorder(save=tmp_path / "x.rrd")
        chosen.log("cube", Frame(np.zeros((40, 3)) + (0, 0, 1), np.zeros((40, 3)), np.eye(4)))
        assert not isinstance(chosen, NullRecorder)
