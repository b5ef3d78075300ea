"""Training and export of the networks (needs the `export` extra: torch, onnx)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
ort = pytest.importorskip("onnxruntime")

from edgepose.encoder import Encoder  # noqa: E402
from edgepose.views import rotation_about_z  # noqa: E402

from export import data, network, shapes, train  # noqa: E402


def turn(maps: torch.Tensor, theta: float) -> torch.Tensor:
    c, s = math.cos(theta), math.sin(theta)
    r = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return maps @ r.T


def test_code_is_invariant_and_spectrum_turns_with_the_map():
    torch.manual_seed(0)
    encoder, irr = network.Encoder().eval(), network.InPlaneRotation().eval()
    maps = torch.randn(3, network.MAP_POINTS, 3) * 0.4
    with torch.no_grad():
        code, spectrum = encoder.encode(maps, network.neighbour_groups(maps))
        for theta in (0.3, 2.0, -2.9):
            turned = turn(maps, theta)
            turned_code, turned_spectrum = encoder.encode(turned, network.neighbour_groups(turned))
            assert torch.allclose(code, turned_code, atol=1e-5)
            # Harmonic m of every channel picks up a phase of m·θ.
            s = spectrum.reshape(3, network.CHANNELS, network.HARMONICS, 2)
            t = turned_spectrum.reshape(3, network.CHANNELS, network.HARMONICS, 2)
            m = torch.arange(1, network.HARMONICS + 1)
            phase = torch.complex(torch.cos(m * theta), torch.sin(m * theta))
            expected = torch.view_as_complex(s.contiguous()) * phase
            assert torch.allclose(torch.view_as_complex(t.contiguous()), expected, atol=1e-5)
            # Even untrained, phase correlation finds an exact turn.
            cos_sin = irr(turned_spectrum, spectrum)
            found = torch.atan2(cos_sin[:, 1], cos_sin[:, 0])
            assert torch.allclose(found, torch.full_like(found, theta), atol=math.radians(0.5))


def test_rust_map_features_equal_training_features():
    # Run time features come from the Rust core, training's from torch: the
    # same groups and the same numbers (the core's order of f32 operations
    # is the exported graph's, which torch need not keep to the last bit).
    from edgepose import _core

    maps = torch.randn(6, network.MAP_POINTS, 3) * 0.4
    rust = _core.map_features(maps.numpy(), network.CENTRES, network.NEIGHBOURS, network.HARMONICS)
    ours = [f.numpy() for f in network.map_features(maps, network.neighbour_groups(maps))]
    shapes = [(6, network.CENTRES, network.NEIGHBOURS, 6), *[(6, network.CENTRES, w) for w in (2, 8, 8)]]
    assert [r.shape for r in rust] == [o.shape for o in ours] == shapes
    # Groups are sets: sort each group's rows the same way before comparing.
    order = lambda edge: np.take_along_axis(edge, np.argsort(edge[..., 3], axis=-1)[..., None], axis=2)  # noqa: E731
    np.testing.assert_allclose(order(rust[0]), order(ours[0]), rtol=1e-5, atol=1e-6)
    for r, o in zip(rust[1:], ours[1:]):
        np.testing.assert_allclose(r, o, rtol=1e-5, atol=1e-6)
    # Each centre is its own nearest neighbour: a zero offset comes first.
    assert np.abs(rust[0][:, :, 0, :3]).max() == 0


def test_reexport_keeps_the_shipped_networks_arithmetic(tmp_path):
    # Weights read back out of the shipped ONNX files and exported again give
    # the same codes, spectra and angles as the shipped files.
    from export import reexport

    assert reexport.main(["--out", str(tmp_path)]) == 0
    shipped, again = Encoder(), Encoder(tmp_path)
    maps = (np.random.default_rng(2).normal(size=(8, 512, 3)) * 0.4).astype(np.float32)
    for a, b in zip(shipped.encode(maps), again.encode(maps)):
        np.testing.assert_allclose(a, b, atol=1e-5)
    spectra = shipped.encode(maps)[1]
    np.testing.assert_allclose(
        shipped.in_plane_angles(spectra[0], spectra), again.in_plane_angles(spectra[0], spectra), atol=1e-5
    )
    # The same codes bit for bit (the re-export only changes the graph's
    # layout): the fingerprint stays, and so do the codebooks built before.
    assert again.fingerprint == shipped.fingerprint


def test_a_reexport_whose_codes_differ_gets_its_own_fingerprint(tmp_path, monkeypatch):
    from export import reexport

    real = reexport.parity_codes
    calls = iter([0, 1])

    def nudged(models_dir):
        codes, spectra = real(models_dir)
        return codes + np.float32(next(calls) * 1e-6), spectra

    monkeypatch.setattr(reexport, "parity_codes", nudged)
    assert reexport.main(["--out", str(tmp_path)]) == 0
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert Encoder(tmp_path).fingerprint == manifest["files"]["encoder.onnx"] != Encoder().fingerprint


@pytest.mark.usefixtures("train_shapes_dir")
def test_training_pairs_carry_the_true_in_plane_angle(monkeypatch):
    # The label is what is checked here: without the occlusion and spill
    # augmentations, which move the observed map away from the codebook's.
    monkeypatch.setattr(data, "OCCLUSION_PROBABILITY", 0.0)
    monkeypatch.setattr(data, "SPILL_PROBABILITY", 0.0)
    models = shapes.build_models(0, seed=0, limit=2)
    batch = data.sample_batch(models, np.random.default_rng(0), shapes=2, views_per_shape=3)
    assert batch.observed.shape == batch.codebook.shape == (6, 512, 3)
    assert np.all(np.abs(batch.angles) <= np.pi)
    # The observed map, turned back by the angle, lines up with the codebook map.
    for obs, book, theta in zip(batch.observed, batch.codebook, batch.angles):
        back = obs @ rotation_about_z(-theta).T
        err_back = np.mean(np.min(np.linalg.norm(back[:, None] - book[None], axis=2), axis=1))
        err_raw = np.mean(np.min(np.linalg.norm(obs[:, None] - book[None], axis=2), axis=1))
        assert err_back < 0.1 and err_back < 0.5 * err_raw, (err_back, err_raw)


def test_occlusion_augmentation_hides_the_asked_fraction():
    points = np.random.default_rng(1).normal(size=(4000, 3))
    for seed in range(20):
        hidden = np.random.default_rng(seed).uniform(0.0, data.MAX_HIDDEN)
        mask = data.occluded(points, hidden, np.random.default_rng(seed))
        assert abs(mask.mean() - hidden) < 0.01
    spilled = data.spill(points, 0.1, np.random.default_rng(0))
    assert len(spilled) == 400 and (spilled[:, 2] > points[:, 2].max()).all()


@pytest.mark.usefixtures("train_shapes_dir")
def test_tiny_training_exports_onnx_that_matches_torch(tmp_path):
    out = tmp_path / "models"
    assert train.main(["--tiny", "--out", str(out), "--cache", str(tmp_path / "cache")]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["parameters"]["total"] <= 1_000_000
    assert set(manifest["files"]) == {"encoder.onnx", "irr.onnx"}
    assert not list(out.glob("*.data")), "ONNX files must be self-contained"
    # The runtime wrapper loads them, checks hashes and gives unit codes.
    encoder = Encoder(out)
    maps = np.random.default_rng(0).normal(size=(5, 512, 3)).astype(np.float32) * 0.4
    codes, spectra = encoder.encode(maps, batch=2)
    assert codes.shape == (5, 64) and spectra.shape == (5, network.SPECTRUM_SIZE)
    np.testing.assert_allclose(np.linalg.norm(codes, axis=1), 1.0, atol=1e-5)
    # Resuming from the checkpoint continues rather than restarting.
    assert train.main(["--tiny", "--resume", "--out", str(out), "--cache", str(tmp_path / "cache")]) == 0


def test_confidence_data_include_a_mislabelled_detection_and_the_fit_ranks_it_low():
    """``export.confidence`` on one object: its own view, judged by ADD(-S),
    and a view of another shape through its codebook, always wrong; the
    model fitted on evidence rows puts the wrong ones below the right ones."""
    import trimesh
    from edgepose.confidence import FEATURES

    from export import confidence

    block = trimesh.creation.box([0.05, 0.08, 0.12])
    rows = confidence.collect_object((0, "block", block, 2, ["clean"], 2, False))
    assert rows["level"] == ["clean", "clean", confidence.OTHER_OBJECT, confidence.OTHER_OBJECT]
    assert rows["correct"][2:] == [False, False] and all(np.isnan(rows["error"][2:]))
    assert all(rows["correct"][:2]) and max(rows["error"][:2]) < 0.1 and max(rows["error_s"][:2]) < 0.1
    assert all(len(e) == len(confidence.CLOUD_FEATURES) for e in rows["evidence"])
    # Given the depth frames too, the evidence holds the scene terms as well.
    framed = confidence.collect_object((0, "block", block, 1, ["visible70"], 0, True))
    assert [len(e) for e in framed["evidence"]] == [len(FEATURES)] and "scene_violation" in FEATURES
    # A fit on these rows (repeated, lightly jittered) ranks the right ones first.
    rng = np.random.default_rng(0)
    evidence = np.repeat(np.array(rows["evidence"]), 20, axis=0)
    evidence *= 1 + 0.01 * rng.standard_normal(evidence.shape)
    correct = np.repeat(np.array(rows["correct"]), 20)
    model = confidence.fit_model(evidence, correct)
    p = [model.probability(dict(zip(confidence.CLOUD_FEATURES, row))) for row in rows["evidence"]]
    assert min(p[:2]) > 0.5 > max(p[2:])
