"""Pose.confidence: the shipped calibrated model, the evidence it reads and
the metrics that judge it (AUROC, calibration, acceptance)."""

from __future__ import annotations

import json
import shutil

import edgepose
import numpy as np
import pytest
import trimesh
from edgepose import _core
from edgepose.confidence import FEATURES, TERMS, TRUST_THRESHOLD, ConfidenceModel, feature_vector
from edgepose.encoder import MODELS_DIR, Encoder
from edgepose.eval import render_view
from edgepose.eval.metrics import acceptance, auroc, calibration
from edgepose.settings import DEFAULT_SETTINGS


def test_the_observed_box_is_numpys_column_by_column():
    """The evidence's bounding box of a query's float32 points: each side
    exactly the column's ``np.ptp`` (the core's one pass); none for no points."""
    from edgepose.confidence import box_sides

    rng = np.random.default_rng(5)
    for n in (1, 2, 7, 1536):
        points = (rng.normal(size=(n, 3)) * [0.1, 0.03, 0.2] + [0.0, 0.1, 0.7]).astype(np.float32)
        assert box_sides(points) == [float(np.ptp(points[:, k])) for k in range(3)], n
    assert box_sides(np.zeros((0, 3), np.float32)) == [0.0, 0.0, 0.0]


def test_shipped_networks_carry_a_confidence_model_over_known_features():
    manifest = json.loads((MODELS_DIR / "manifest.json").read_text())
    model = ConfidenceModel.from_manifest(manifest["confidence"])
    assert set(model.features) <= set(FEATURES)
    assert manifest["confidence"]["fitted_on"]["data"].endswith("never YCB")
    assert edgepose.encoder.default_encoder().confidence is not None


def test_a_clean_view_is_trusted_and_every_pose_has_its_evidence(drill):
    mesh, codebook = drill
    for seed in (1, 2, 3):
        pose = edgepose.estimate(render_view(mesh, seed=seed).cloud, codebook)
        assert set(pose.evidence) == set(FEATURES)
        assert TRUST_THRESHOLD <= pose.confidence <= 1.0
        assert not pose.ambiguous


def test_another_objects_cloud_is_not_trusted(drill):
    _, codebook = drill
    # A box about the drill's size: the drill's codebook can only explain it badly.
    box = trimesh.creation.box([0.05, 0.15, 0.2])
    for seed in (1, 2, 3):
        pose = edgepose.estimate(render_view(box, seed=seed).cloud, codebook)
        assert 0.0 <= pose.confidence < TRUST_THRESHOLD, pose.evidence


def test_a_turned_pose_is_less_trusted_than_the_right_one(drill):
    """The same scoring terms for the estimate and for a wrong pose 90° off:
    the probability model must prefer the right one."""
    from dataclasses import replace

    from edgepose.confidence import FitEvidence, SearchEvidence, evidence_of

    model = edgepose.encoder.default_encoder().confidence
    fits = FitEvidence(1.0, 1.0, 0.3, 0.0, off_silhouette=0.1, observed_extent=1.2, translation_constraint=0.2)
    found = SearchEvidence(0.95, False, True, 1.0, 0.5, 0.0, 0.5, alternatives=0, alternative_margin=1.0)
    good = evidence_of(fits, found)
    bad = evidence_of(
        FitEvidence(0.6, 0.8, 0.8, 0.2, off_silhouette=0.4, observed_extent=1.2, translation_constraint=0.2),
        SearchEvidence(0.7, True, True, 0.0, 0.0, 0.98, 1.0, alternatives=2, alternative_margin=0.0),
    )
    assert model.probability(good) > 0.9 and model.probability(bad) < 0.2
    # Other poses that explain the view as well make the same pose less trusted.
    tied = evidence_of(fits, replace(found, alternatives=3, alternative_margin=0.0))
    assert model.probability(tied) < model.probability(good)


def test_a_pose_given_the_depth_frame_is_judged_by_the_model_that_reads_the_scene(drill):
    from edgepose.confidence import SCENE_FEATURES
    from edgepose.eval.scenes import render_scene

    mesh, codebook = drill
    encoder = edgepose.encoder.default_encoder()
    cloud_model, scene_model = encoder.confidence, encoder.scene_confidence
    assert cloud_model is not None and scene_model is not None
    assert not set(SCENE_FEATURES) & set(cloud_model.features)
    assert set(SCENE_FEATURES) <= set(scene_model.features)
    view = render_scene(mesh, "visible70", seed=5)
    framed = edgepose.estimate(view.cloud, codebook, depth=view.depth, K=view.K, depth_scale=1.0)
    alone = edgepose.estimate(view.cloud, codebook)
    assert framed.confidence == pytest.approx(scene_model.probability(framed.evidence))
    assert alone.confidence == pytest.approx(cloud_model.probability(alone.evidence))


def test_a_malformed_confidence_model_is_a_model_files_error(tmp_path):
    for name in ("encoder.onnx", "irr.onnx"):
        shutil.copy(MODELS_DIR / name, tmp_path / name)
    manifest = json.loads((MODELS_DIR / "manifest.json").read_text())
    manifest["confidence"]["features"] = {"mystery": "a term no edgepose computes"}
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(edgepose.ModelFilesError, match="mystery"):
        Encoder(tmp_path)
    manifest = json.loads((MODELS_DIR / "manifest.json").read_text())
    manifest["confidence"]["with_scene"]["weights"] = [1.0]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(edgepose.ModelFilesError, match="one per term"):
        Encoder(tmp_path)
    manifest = json.loads((MODELS_DIR / "manifest.json").read_text())
    manifest["confidence"]["knots"][0] = [0.5, 0.1]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(edgepose.ModelFilesError, match="ascending"):
        Encoder(tmp_path)
    del manifest["confidence"]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    assert Encoder(tmp_path).confidence is None  # networks without one: confidence is NaN


def test_each_term_is_a_piecewise_linear_curve_through_its_knots():
    """The model is logistic in each term plus max(0, term - knot) at its
    knots; it survives the manifest, a manifest without knots is linear in
    every term, and the fast per-pose sum equals the matrix form."""

    def logit(model: ConfidenceModel, score: float) -> float:
        p = model.probability({"score": score})
        return float(np.log(p / (1 - p)))

    one = np.ones(2)
    hinged = ConfidenceModel(("score",), ((0.5,),), 0 * one, one, np.array([1.0, 2.0]), 0.0)
    hinged = ConfidenceModel.from_manifest(hinged.to_manifest())
    assert hinged.to_manifest()["inputs"] == ["score:value", "score:value>0.5"]
    assert [logit(hinged, x) for x in (0.2, 0.4, 0.8)] == pytest.approx([0.2, 0.4, 0.8 + 2 * 0.3])
    linear = {k: v[:1] if k in ("mean", "scale", "weights") else v for k, v in hinged.to_manifest().items()}
    del linear["knots"]
    assert logit(ConfidenceModel.from_manifest(linear), 0.8) == pytest.approx(0.8)

    shipped = ConfidenceModel.from_manifest(json.loads((MODELS_DIR / "manifest.json").read_text())["confidence"])
    assert any(shipped.knots)
    rng = np.random.default_rng(0)
    # Every branch of every transform (negative margins, extents past 1.2 d,
    # fractions past 1): the Rust core's sum reads them as Python's do.
    logged = {n for n, terms in TERMS.items() if any("log" in t.__name__ or "unexplained" in t.__name__ for t in terms)}
    evidence = [
        {n: float(rng.uniform(0.0 if n in logged else -0.5, 1.5)) for n in shipped.features} for _ in range(200)
    ]
    terms = np.array([feature_vector(e, shipped.features) for e in evidence])
    z = (ConfidenceModel.inputs(terms, shipped.knots) - shipped.mean) / shipped.scale @ shipped.weights + shipped.bias
    assert [shipped.probability(e) for e in evidence] == pytest.approx(1 / (1 + np.exp(-z)), abs=1e-12)
    assert np.isnan(shipped.probability({**evidence[0], "margin": float("nan")}))


def test_a_confidence_model_that_does_not_add_up_is_refused():
    """A manifest whose knots do not match its terms, and a core model
    given an unknown transform or the wrong number of evidence values, are
    errors naming the problem, not a silent probability."""
    one = np.ones(2)
    with pytest.raises(ValueError, match="model of 2 terms has 1 lists of knots"):
        ConfidenceModel(("score", "fit"), ((0.5,),), 0 * one, one, one, 0.0)
    with pytest.raises(ValueError, match='unknown confidence term transform "softplus"'):
        _core.ConfidenceCurves([(0, "softplus", 1.0, [])], 0.0, 1)
    with pytest.raises(ValueError, match="reads evidence 1 of 1"):
        _core.ConfidenceCurves([(1, "value", 1.0, [])], 0.0, 1)
    curves = _core.ConfidenceCurves([(0, "value", 1.0, [(0.5, -1.0)])], 0.0, 1)
    assert curves.probability([0.0]) == 0.5
    with pytest.raises(ValueError, match="2 evidence values for a model of 1"):
        curves.probability([0.0, 1.0])


def test_the_fit_finds_the_lowest_threshold_that_lets_few_wrong_poses_through():
    from export.confidence import strict_thresholds

    wrong = [0.55, 0.6, 0.7, 0.8, 0.9, 0.93, 0.95, 0.96, 0.97, 0.98]
    right = [0.6, 0.9, 0.97, 0.99]
    rows = strict_thresholds(np.array(wrong + right), np.array([False] * 10 + [True] * 4))
    # ≤ 5 % of 10 wrong poses is none of them: above 0.98; ≤ 10 % is one: 0.98.
    assert [(r["wrong_accepted_at_most"], r["threshold"]) for r in rows] == [(0.05, 0.99), (0.10, 0.98)]
    assert rows[0]["wrong_accepted"] == 0.0 and rows[0]["correct_kept"] == 0.25
    assert rows[1]["wrong_accepted"] == pytest.approx(0.1) and rows[1]["correct_kept"] == 0.25


def test_the_fit_says_how_right_the_accepted_poses_would_have_to_be():
    from export.confidence import acceptance_demand

    # 40 wrong poses; 100 accepted at 0.5, of which 90 right and 10 wrong.
    p = np.array([0.9] * 100 + [0.2] * 30)
    y = np.array([True] * 90 + [False] * 10 + [False] * 30)
    row = acceptance_demand(p, y)
    assert row["accepted"] == 100 and row["right"] == pytest.approx(0.9)
    # ≤ 5 % of 40 wrong is 2 of the 100 accepted: they must be 98 % right.
    assert row["right_needed"] == pytest.approx(0.98) and row["mean_confidence"] == pytest.approx(0.9)


def test_each_pose_carries_the_strict_rule_of_the_model_that_judged_it(drill, tmp_path):
    """The fit's recorded stricter thresholds come back as the model's rules;
    every pose carries the ≤ 5 % one of its own model (clouds alone, or given
    the frame); without recorded rules the strict threshold is NaN; malformed
    ones are a model files error."""
    from edgepose.confidence import STRICT_WRONG_ACCEPTED
    from edgepose.eval.scenes import render_scene

    mesh, codebook = drill
    manifest = json.loads((MODELS_DIR / "manifest.json").read_text())
    encoder = edgepose.encoder.default_encoder()
    for model, entry in (
        (encoder.confidence, manifest["confidence"]),
        (encoder.scene_confidence, manifest["confidence"]["with_scene"]),
    ):
        assert model is not None
        recorded = {
            r["wrong_accepted_at_most"]: r["threshold"]
            for r in entry["fitted_on"]["cross_validation"]["stricter_thresholds"]
        }
        assert model.strict_threshold == recorded[STRICT_WRONG_ACCEPTED] > TRUST_THRESHOLD
        assert model.threshold_for(0.10) == recorded[0.10] <= model.strict_threshold
        assert model.threshold_for(0.07) == model.strict_threshold  # the rule of the largest share not above 0.07
        with pytest.raises(ValueError, match="at most 0.01 of wrong poses"):
            model.threshold_for(0.01)
    view = render_scene(mesh, "visible70", seed=5)
    alone = edgepose.estimate(view.cloud, codebook)
    framed = edgepose.estimate(view.cloud, codebook, depth=view.depth, K=view.K, depth_scale=1.0)
    assert alone.strict_threshold == encoder.confidence.strict_threshold
    assert framed.strict_threshold == encoder.scene_confidence.strict_threshold
    tracker = edgepose.Tracker(codebook)
    tracker.update(view.cloud)
    tracked = tracker.update(view.cloud)
    assert tracked.mode == "tracked" and tracked.strict_threshold == encoder.confidence.strict_threshold

    for name in ("encoder.onnx", "irr.onnx"):
        shutil.copy(MODELS_DIR / name, tmp_path / name)
    for entry in (manifest["confidence"], manifest["confidence"]["with_scene"]):
        del entry["fitted_on"]["cross_validation"]["stricter_thresholds"]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    unrecorded = Encoder(tmp_path)
    assert np.isnan(edgepose.estimate(view.cloud, codebook, encoder=unrecorded).strict_threshold)
    with pytest.raises(ValueError, match="recorded: none"):
        unrecorded.confidence.threshold_for(0.05)  # type: ignore[union-attr]
    manifest["confidence"]["fitted_on"]["cross_validation"]["stricter_thresholds"] = [{"threshold": 0.9}]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(edgepose.ModelFilesError, match="stricter_thresholds"):
        Encoder(tmp_path)


def test_the_benchmark_counts_what_each_poses_strict_rule_accepts():
    from edgepose.eval import pose_errors
    from edgepose.eval.benchmark import ViewResult, summarise_confidence

    points = np.random.default_rng(0).normal(size=(100, 3)) * 0.05
    right, wrong = np.eye(4), np.eye(4)
    wrong[:3, 3] = [0.1, 0.0, 0.0]

    def view(T: np.ndarray, confidence: float, strict: float) -> ViewResult:
        errors = pose_errors(points, T, np.eye(4), 0.2, False)
        return ViewResult("edgepose", "part", 0, 0, 100, 0.01, errors, 1.0, T, "", confidence, strict)

    # Judged by two models (strict at 0.9 and 0.95): a right pose at 0.92
    # passes the first only; a wrong one at 0.93 passes neither.
    views = [
        view(right, 0.99, 0.9), view(right, 0.92, 0.95), view(right, 0.92, 0.9), view(right, 0.6, 0.9),
        view(wrong, 0.93, 0.95), view(wrong, 0.7, 0.9),
    ]  # fmt: skip
    c = summarise_confidence(views)
    assert c is not None and c.strict_thresholds == (0.9, 0.95)
    assert c.strict_correct_kept == pytest.approx(50.0) and c.strict_wrong_accepted == 0.0
    assert c.correct_kept == 100.0 and c.wrong_accepted == 100.0  # the default rule, at 0.5
    unknown = summarise_confidence([view(right, 0.99, float("nan"))])
    assert unknown is not None and np.isnan(unknown.strict_correct_kept) and unknown.strict_thresholds == ()


def test_the_benchmark_counts_wrong_poses_with_the_truth_among_their_alternatives():
    from edgepose.eval.baselines import EdgePoseMethod
    from edgepose.eval.benchmark import BenchObject, run_method
    from edgepose.eval.render import render_view
    from edgepose.report import alternatives_table
    from test_pose import looking_at, tabbed_box

    # Seen from below, the tabbed box's pose and its half turn explain the view alike.
    mesh = tabbed_box()
    poses = [looking_at(-1.0, seed) for seed in range(4)]
    clouds = [render_view(mesh, T_cam_obj=T, seed=seed).cloud for seed, T in enumerate(poses)]
    points = np.asarray(mesh.sample(2000, seed=0), dtype=np.float64)
    d = float(np.linalg.norm(mesh.bounds[1] - mesh.bounds[0]))
    box = BenchObject("tabbed_box", mesh, points, d, False, list(range(4)), clouds, poses)
    views = run_method(EdgePoseMethod(), [box]).views
    assert all(v.alternatives >= 1 for v in views)
    assert all(v.errors.correct_add_or_s != v.alternative_correct for v in views)  # one of the two is the truth
    wrong = sum(not v.errors.correct_add_or_s for v in views)
    row = alternatives_table({"from below": views}).splitlines()[-1].split(" | ")
    assert row[1:4] == ["4", f"{wrong}", f"{wrong}"]


def test_auroc_counts_ordered_pairs_and_ties():
    assert auroc([0.9, 0.8, 0.2, 0.1], [True, True, False, False]) == 1.0
    assert auroc([0.1, 0.2, 0.8, 0.9], [True, True, False, False]) == 0.0
    assert auroc([0.5, 0.5], [True, False]) == 0.5
    # Pairs (correct, wrong): (0.9,0.3) (0.9,0.6) (0.4,0.3) (0.4,0.6) -> 3 of 4 ordered.
    assert auroc([0.9, 0.4, 0.3, 0.6], [True, True, False, False]) == 0.75
    assert np.isnan(auroc([0.3, 0.4], [True, True]))


def test_calibration_bins_and_expected_error():
    p = np.array([0.05, 0.05, 0.95, 0.95, 0.55, 0.55])
    y = np.array([False, False, True, False, True, True])
    c = calibration(p, y, bins=10)
    assert c.count.sum() == 6 and c.count[0] == 2 and c.count[9] == 2 and c.count[5] == 2
    # |0 - .05|·2 + |.5 - .95|·2 + |1 - .55|·2, over 6.
    assert c.ece == pytest.approx((0.1 + 0.9 + 0.9) / 6)
    assert c.accuracy[9] == 0.5 and np.isnan(c.accuracy[3])


def test_acceptance_at_a_threshold():
    a = acceptance([0.9, 0.6, 0.4, 0.7, 0.2], [True, True, True, False, False], threshold=0.5)
    assert a.correct_kept == pytest.approx(2 / 3) and a.wrong_accepted == pytest.approx(1 / 2)
    with pytest.raises(ValueError, match="finite"):
        acceptance([np.nan], [True])


def test_the_flip_margin_prefers_the_true_pose_to_its_half_turns(drill):
    """The drill (asymmetric) seen whole: its true pose explains the view
    clearly better than any half turn about a principal axis (margin > 0)
    and fits it far more closely than its best turned rival (fit ratio well
    below 1), and each half-turned pose is beaten by the true one (margin
    < 0) and fits worse than that rival, the truth (fit ratio above 1)."""
    from edgepose.settings import DEFAULT_SETTINGS as S
    from edgepose.stages import flip_margin, flip_rival, prepare_query, score_poses
    from edgepose.views import rotation_about

    mesh, codebook = drill
    view = render_view(mesh, seed=4)
    query = prepare_query(view.cloud, codebook)
    model = codebook.model

    def margin_and_fit_ratio(R: np.ndarray, t: np.ndarray) -> tuple[float, float]:
        observed = query.sample(S.refine.hypothesis_points, S.subsample_seed)
        scores = score_poses(
            query, codebook, observed, R[None], t[None], S.refine.hypothesis_inlier_distance * model.diameter, 0.0
        )
        flips = flip_margin(scores, flip_rival(query, codebook, R, t, S))
        assert flips.rival.fits.shape == (1,)
        return flips.margin, float(scores.fit[0] / flips.rival.fits[0])

    R = view.T_cam_obj[:3, :3]
    t = view.T_cam_obj[:3, 3] + R @ model.centre  # model frame -> camera
    margin, fit_ratio = margin_and_fit_ratio(R, t)
    assert margin > 0.1 and fit_ratio < 0.7
    centroid, axes = model.principal_axes
    assert np.allclose(axes.T @ axes, np.eye(3), atol=1e-9)
    for a in axes.T:
        flip = rotation_about(a, np.pi)
        margin, fit_ratio = margin_and_fit_ratio(R @ flip, t + R @ centroid - R @ flip @ centroid)
        assert margin < 0.0 and fit_ratio > 1.0


def test_a_pose_turned_onto_itself_gives_way_to_its_refined_rival(drill):
    """The drill seen whole, but the pose half turned about each principal
    axis (a near-symmetric object's usual mistake): its best turned rival,
    refined, is the truth and replaces it; the true pose keeps its place.
    With the check off (``turn.check_below`` ≤ −1) a clean estimate is the same."""
    from edgepose.settings import DEFAULT_SETTINGS as S
    from edgepose.stages import Refined, flip_margin, flip_rival, prepare_query, score_poses, turned_pose
    from edgepose.views import rotation_about

    mesh, codebook = drill
    view = render_view(mesh, seed=4)
    query = prepare_query(view.cloud, codebook)
    model = codebook.model
    observed = query.sample(S.refine.hypothesis_points, S.subsample_seed)

    def searched(R: np.ndarray, t: np.ndarray):
        """A search's refined pose (R, t) and what turned_pose makes of it."""
        scores = score_poses(
            query, codebook, observed, R[None], t[None], S.refine.hypothesis_inlier_distance * model.diameter, 0.0
        )
        result = Refined(0, R, t, scores, True)
        return turned_pose(query, codebook, result, flip_margin(scores, flip_rival(query, codebook, R, t, S)), S)

    R = view.T_cam_obj[:3, :3]
    t = view.T_cam_obj[:3, 3] + R @ model.centre  # model frame -> camera
    assert searched(R, t) is None
    centroid, axes = model.principal_axes
    for a in axes.T:
        flip = rotation_about(a, np.pi)
        turned = searched(R @ flip, t + R @ centroid - R @ flip @ centroid)
        assert turned is not None and turned.margin > S.turn.switch_gain
        both = np.stack([R, turned.R]), np.stack([t, turned.t])
        assert codebook.index.pose_distances(*both, 0, False, 64)[1] < 0.02 * model.diameter
    unchecked = edgepose.estimate(view.cloud, codebook, settings=S.with_(**{"turn.check_below": -1.0}))
    pose = edgepose.estimate(view.cloud, codebook)
    assert np.array_equal(pose.matrix, unchecked.matrix) and "turned_pose" not in unchecked.timings


def test_a_symmetric_objects_half_turns_are_no_rivals():
    """A box's half turns about its axes are its symmetries: the same pose,
    so no flip competes with the estimate (margin 1)."""
    box = trimesh.creation.box([0.06, 0.1, 0.16])
    codebook = edgepose.build_codebook(box)
    assert codebook.symmetry.symmetric
    for seed in (1, 2):
        pose = edgepose.estimate(render_view(box, seed=seed).cloud, codebook)
        assert pose.evidence["flip_margin"] == 1.0


def test_the_rmse_ratio_compares_the_pick_with_the_rivals_that_competed():
    """A block with a post on top, seen from below (the post hidden): the
    pose and its half turn about the block's vertical axis explain the view
    alike, so the turn competes and the ratio of their coarse ICP RMSEs is
    in (0, 1 + tie_polish_within] (a near tie is decided by the polished
    RMSEs, so the pick's coarse one may be the higher); with no rival the
    ratio is 0."""
    from edgepose.stages import prepare_query, refine_hypotheses
    from edgepose.views import rotation_about

    block = trimesh.creation.box([0.16, 0.06, 0.03])
    post = trimesh.creation.box([0.04, 0.04, 0.04])
    post.apply_translation([0.06, 0.0, 0.035])
    mesh = trimesh.util.concatenate([block, post])
    codebook = edgepose.build_codebook(mesh)
    assert not codebook.symmetry.symmetric
    T = np.eye(4)
    T[:3, :3] = rotation_about(np.array([1.0, 0.0, 0.0]), np.radians(20))
    T[:3, 3] = [0.0, 0.0, 0.6]
    query = prepare_query(render_view(mesh, T_cam_obj=T, seed=1).cloud, codebook)
    centre = codebook.model.centre
    half_turn = rotation_about(np.array([0.0, 0.0, 1.0]), np.pi)
    R = np.stack([T[:3, :3], T[:3, :3] @ half_turn])
    t = np.stack([T[:3, 3] + r @ centre for r in R])  # model frame -> camera
    both = refine_hypotheses(query, codebook, R, t, np.array([0.0, 1.0]))
    assert 0.0 < both.rmse_ratio <= 1.0 + DEFAULT_SETTINGS.refine.tie_polish_within, both.rmse_ratio
    untied = refine_hypotheses(
        query, codebook, R, t, np.array([0.0, 1.0]), DEFAULT_SETTINGS.with_(**{"refine.tie_polish_within": 0.0})
    )
    assert 0.0 < untied.rmse_ratio <= 1.0, untied.rmse_ratio  # the lowest coarse RMSE picked
    alone = refine_hypotheses(query, codebook, R[:1], t[:1], np.array([0.0]))
    assert alone.rmse_ratio == 0.0 and alone.margin == 1.0
