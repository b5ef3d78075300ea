"""estimate(): end-to-end pose recovery on rendered views of real meshes."""

from __future__ import annotations

import os
import threading
import time

import edgepose
import numpy as np
import pytest
import trimesh
from edgepose.encoder import default_encoder
from edgepose.eval import pose_errors, render_view
from edgepose.model import read_mesh
from edgepose.stages import free_space_tolerance, prepare_query, retrieve


def errors(pose, view, codebook):
    model_points = codebook.model.mesh_points
    return pose_errors(model_points, pose.matrix, view.T_cam_obj, codebook.model.diameter, symmetric=False)


def net(pose):
    """What a second search must beat to replace a pose: its inlier fraction minus free-space violation."""
    return pose.inlier_fraction - pose.free_space_violation


def test_recovers_rendered_poses_of_an_unseen_object(drill):
    mesh, codebook = drill
    correct, rotation_deg, translation_mm = 0, [], []
    for seed in range(12):
        view = render_view(mesh, seed=seed)
        pose = edgepose.estimate(view.cloud, codebook)
        e = errors(pose, view, codebook)
        correct += e.correct_add_or_s
        rotation_deg.append(e.rotation_deg)
        translation_mm.append(e.translation_mm)
        assert pose.matrix.shape == (4, 4) and np.allclose(pose.matrix[3], [0, 0, 0, 1])
        np.testing.assert_allclose(pose.R @ pose.R.T, np.eye(3), atol=1e-9)
    assert correct >= 10, f"ADD < 0.1 d on {correct}/12 views"
    assert np.median(rotation_deg) < 5.0 and np.median(translation_mm) < 5.0


def test_refinement_improves_the_fit(drill):
    mesh, codebook = drill
    view = render_view(mesh, seed=100)
    coarse = edgepose.estimate(view.cloud, codebook, refine=False)
    fine = edgepose.estimate(view.cloud, codebook)
    assert not coarse.refined and fine.refined
    assert errors(fine, view, codebook).add <= errors(coarse, view, codebook).add + 1e-4
    assert set(fine.timings) == {
        "prepare_query",
        "retrieve",
        "candidate_poses",
        "score_poses",
        "refine_hypotheses",
        "confidence",
        "total",
    }
    assert len(fine.candidates) == 16 and fine.view in fine.candidates


def test_turned_over_poses_of_a_near_symmetric_object_are_told_apart(ycb_dir):
    # The mustard bottle seen in depth alone is nearly the same turned 180° about
    # its axis: the best-verified candidate is often the turned-over pose (a
    # 66 mm ADD error). Refining several distinct hypotheses and keeping the
    # best fit must recover the true one.
    mesh = read_mesh(ycb_dir / "mustard_bottle.ply")
    codebook = edgepose.build_codebook(mesh)
    seeds = range(500, 512)
    refined = [
        errors(edgepose.estimate(render_view(mesh, seed=s).cloud, codebook), render_view(mesh, seed=s), codebook)
        for s in seeds
    ]
    unrefined = [
        errors(
            edgepose.estimate(render_view(mesh, seed=s).cloud, codebook, refine=False),
            render_view(mesh, seed=s),
            codebook,
        )
        for s in seeds
    ]
    assert sum(e.correct_add_or_s for e in refined) >= 11, [round(e.rotation_deg) for e in refined]
    assert sum(e.rotation_deg > 150 for e in unrefined) >= 3, "these views should include turned-over candidates"


def tabbed_box() -> trimesh.Trimesh:
    """A 12 × 6 × 4 cm box with a 2 cm cube on its top face near one end: seen
    from below, the box turned a half turn about its z axis looks the same."""
    tab = trimesh.creation.box(extents=(0.02, 0.02, 0.02))
    tab.apply_translation((0.04, 0.0, 0.03))
    return trimesh.util.concatenate([trimesh.creation.box(extents=(0.12, 0.06, 0.04)), tab])


def looking_at(side: float, seed: int) -> np.ndarray:
    """T_cam_obj of a camera 0.6 m away looking at an object's top (``side``
    1) or bottom (−1) face, tilted up to ~15° and turned about its axis (seeded)."""
    rng = np.random.default_rng(seed)
    towards_camera = np.array([0.0, 0.0, side]) + rng.normal(size=3) * 0.25
    z = -towards_camera / np.linalg.norm(towards_camera)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    a = rng.uniform(0, 2 * np.pi)
    spin = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = (np.stack([x, np.cross(z, x), z], axis=1) @ spin).T
    T[:3, 3] = [0.0, 0.0, 0.6]
    return T


def test_a_view_that_cannot_tell_a_pose_from_its_turn_offers_the_turn_as_an_alternative():
    mesh = tabbed_box()
    codebook = edgepose.build_codebook(mesh)
    assert not codebook.symmetry.symmetric  # the tab breaks the box's symmetry
    points, d = codebook.model.mesh_points, codebook.model.diameter
    half_turn = np.diag([-1.0, -1.0, 1.0, 1.0])

    def right(T, truth):
        return pose_errors(points, T, truth, d, symmetric=False).correct_add_or_s

    for seed in range(4):
        # From below the tab is hidden: the pose is the truth or its turn, and the other is offered.
        truth = looking_at(-1.0, seed)
        pose = edgepose.estimate(render_view(mesh, T_cam_obj=truth, seed=seed).cloud, codebook)
        found = [pose.matrix, *(a.matrix for a in pose.alternatives)]
        assert any(right(T, truth) for T in found) and any(right(T, truth @ half_turn) for T in found), seed
        margins = [a.margin for a in pose.alternatives]
        assert margins == sorted(margins) and all(m <= edgepose.EstimateSettings().alternatives.within for m in margins)
        # The confidence reads them: how many, and how close the best comes.
        assert pose.evidence["alternatives"] == len(margins) and pose.evidence["alternative_margin"] == margins[0]
        for i, T in enumerate(found):  # distinct from the pose and from each other
            assert all(pose_errors(points, T, other, d, symmetric=False).add >= 0.1 * d for other in found[i + 1 :]), (
                seed
            )
        # From above the tab tells them apart: the turn is no alternative.
        truth = looking_at(1.0, seed)
        pose = edgepose.estimate(render_view(mesh, T_cam_obj=truth, seed=seed).cloud, codebook)
        assert right(pose.matrix, truth), seed
        assert not any(right(a.matrix, truth @ half_turn) for a in pose.alternatives), seed
        if not pose.alternatives:
            assert pose.evidence["alternatives"] == 0 and pose.evidence["alternative_margin"] == 1.0
    none = edgepose.estimate(
        render_view(mesh, T_cam_obj=looking_at(-1.0, 0), seed=0).cloud,
        codebook,
        settings=edgepose.EstimateSettings(alternatives=edgepose.AlternativeSettings(max_count=0)),
    )
    assert none.alternatives == ()


def test_distinct_hypotheses_skip_near_duplicates():
    from edgepose.stages import distinct_hypotheses

    def rz(deg):
        a = np.radians(deg)
        return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])

    rotations = np.stack([rz(0), rz(5), rz(180), rz(30), rz(182), rz(90)])
    order = np.arange(6)
    assert distinct_hypotheses(rotations, order, 3, 20.0).tolist() == [0, 2, 3]
    assert distinct_hypotheses(rotations, order[::-1], 2, 20.0).tolist() == [5, 4]
    assert distinct_hypotheses(rotations, order, 10, 20.0).tolist() == [0, 2, 3, 5]


def test_a_near_tie_between_rival_hypotheses_goes_to_the_lower_polished_rmse():
    """A block with a post on top, seen with the post in view: the true pose
    and its half turn (the post on the wrong end), both competing, the
    turn's coarse RMSE a hair lower, so the turn is picked. Polishing both
    (the real ICP, asked for the pick first) tells them apart: the true
    pose wins, and its polish is handed on, the same as polishing it
    alone. No tie (the turn's RMSE well below), no polish
    (``refine.icp_iterations=0``) or ``refine.tie_polish_within=0``: the pick
    stands, unpolished. No usable ICP result: no pick."""
    from edgepose.settings import DEFAULT_SETTINGS
    from edgepose.stages import pick_hypothesis, polish
    from edgepose.views import rotation_about

    block = trimesh.creation.box([0.16, 0.06, 0.03])
    post = trimesh.creation.box([0.04, 0.04, 0.04])
    post.apply_translation([0.06, 0.0, 0.035])
    mesh = trimesh.util.concatenate([block, post])
    codebook = edgepose.build_codebook(mesh)
    T = np.eye(4)
    T[:3, :3] = rotation_about(np.array([1.0, 0.0, 0.0]), np.radians(160))  # looking at the post's side
    T[:3, 3] = [0.0, 0.0, 0.6]
    query = prepare_query(render_view(mesh, T_cam_obj=T, seed=1).cloud, codebook)
    half_turn = rotation_about(np.array([0.0, 0.0, 1.0]), np.pi)
    R = np.stack([T[:3, :3], T[:3, :3] @ half_turn])
    t = np.stack([T[:3, 3] + r @ codebook.model.centre for r in R])  # model frame -> camera
    # Every usable hypothesis competes, whatever it explains.
    S = DEFAULT_SETTINGS.with_(**{"refine.hypothesis_inlier_ratio": 0.0, "refine.hypothesis_free_space_margin": 1.0})
    coarse = query.sample(S.refine.hypothesis_points, S.subsample_seed)
    asked = []

    def polish_tie(tie):
        asked.append(tie)
        return polish(query, codebook, R[tie], t[tie], S)

    def pick(rmse, settings=S, inliers=(200, 200)):
        asked.clear()
        return pick_hypothesis(query, codebook, coarse, R, t, np.array(inliers), np.array(rmse), settings, polish_tie)

    found = pick([1e-3, 0.99e-3])
    assert asked == [[1, 0]] and found.pick == 0 and len(found.tie_polish) == 1
    alone = polish(query, codebook, R[:1], t[:1], S)
    for name in ("rotations", "translations", "inliers", "rmse"):
        np.testing.assert_array_equal(getattr(found.tie_polish, name), getattr(alone, name))
    assert found.rmse_ratio == 1e-3 / 0.99e-3  # the winner's coarse RMSE over its competing rival's
    assert found.margin == found.scores.net[0] - found.scores.net[1]
    for rmse, settings in [
        ([1e-3, 0.5e-3], S),
        ([1e-3, 0.99e-3], S.with_(**{"refine.tie_polish_within": 0.0})),
        ([1e-3, 0.99e-3], S.with_(**{"refine.icp_iterations": 0})),
    ]:
        found = pick(rmse, settings)
        assert (found.pick, found.tie_polish, asked) == (1, None, []), (rmse, settings.refine)
    assert pick([1e-3, 0.99e-3], inliers=(3, 3)) is None


def test_same_input_same_pose_and_saved_codebook_same_pose(drill, tmp_path):
    mesh, codebook = drill
    view = render_view(mesh, seed=5)
    a = edgepose.estimate(view.cloud, codebook)
    b = edgepose.estimate(view.cloud.astype(np.float32).astype(np.float64), codebook)
    assert np.array_equal(a.matrix, edgepose.estimate(view.cloud, codebook).matrix)
    path = tmp_path / "drill.codebook"
    codebook.save(path)
    loaded = edgepose.Codebook.load(path)
    assert np.array_equal(edgepose.estimate(view.cloud, loaded).matrix, a.matrix)
    assert np.allclose(b.matrix, a.matrix, atol=1e-3)


def test_accepts_open3d_like_clouds_and_depth_images(drill):
    mesh, codebook = drill
    view = render_view(mesh, seed=9)

    class PointCloud:  # the shape of open3d.geometry.PointCloud that edgepose reads
        points = view.cloud

    cloud = edgepose.cloud_from_depth(view.depth, view.camera.K, view.mask, depth_scale=1.0)
    np.testing.assert_allclose(cloud, view.cloud)
    depth_mm = np.round(view.depth * 1000).astype(np.uint16)
    cloud_mm = edgepose.cloud_from_depth(depth_mm, view.camera.K, view.mask)
    np.testing.assert_allclose(cloud_mm, view.cloud, atol=1e-3)
    assert np.array_equal(
        edgepose.estimate(PointCloud(), codebook).matrix, edgepose.estimate(view.cloud, codebook).matrix
    )


def test_threads_give_the_serial_poses(drill):
    mesh, codebook = drill
    clouds = [render_view(mesh, seed=s).cloud for s in range(8)]
    serial = [edgepose.estimate(c, codebook).matrix for c in clouds]
    results: dict[int, np.ndarray] = {}

    def work(i: int) -> None:
        results[i] = edgepose.estimate(clouds[i], codebook).matrix

    threads = [threading.Thread(target=work, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert all(np.array_equal(results[i], serial[i]) for i in range(8))


def test_bad_clouds_raise_clear_errors(drill):
    _, codebook = drill
    with pytest.raises(edgepose.InvalidCloudError, match=r"shape \(N, 3\)"):
        edgepose.estimate(np.zeros((100, 2)), codebook)
    with pytest.raises(edgepose.InvalidCloudError, match="0 valid points"):
        edgepose.estimate(np.zeros((0, 3)), codebook)
    with pytest.raises(edgepose.InvalidCloudError, match="valid points"):
        edgepose.estimate(np.full((500, 3), np.nan), codebook)
    with pytest.raises(edgepose.InvalidCloudError, match="dtype"):
        edgepose.estimate(np.array([["a", "b", "c"]] * 100), codebook)


def test_search_and_refinement_settings_are_bounded(drill):
    mesh, codebook = drill
    cloud = render_view(mesh, seed=4).cloud
    for bad in ({"k": 0}, {"k": len(codebook) + 1}, {"icp_iterations": -1}, {"icp_iterations": 10**9}):
        with pytest.raises(ValueError, match="between"):
            edgepose.estimate(cloud, codebook, **bad)
    everything = edgepose.estimate(cloud, codebook, k=len(codebook))
    assert len(everything.candidates) == len(codebook)
    coarse_only = edgepose.estimate(cloud, codebook, icp_iterations=0)
    assert coarse_only.refined and np.isfinite(coarse_only.fit) and coarse_only.fit < 0.01


def test_an_encoder_other_than_the_codebooks_is_refused(drill, tmp_path):
    import hashlib
    import json
    import shutil

    onnx = pytest.importorskip("onnx")
    from edgepose.encoder import MODELS_DIR, Encoder

    mesh, codebook = drill
    shutil.copytree(MODELS_DIR, tmp_path / "models")
    graph = onnx.load(str(tmp_path / "models" / "encoder.onnx"))
    graph.doc_string = "another encoder"
    onnx.save(graph, str(tmp_path / "models" / "encoder.onnx"))
    manifest = json.loads((tmp_path / "models" / "manifest.json").read_text())
    digest = hashlib.sha256((tmp_path / "models" / "encoder.onnx").read_bytes()).hexdigest()
    manifest["files"]["encoder.onnx"] = manifest["fingerprint"] = digest  # as an export writes it
    (tmp_path / "models" / "manifest.json").write_text(json.dumps(manifest))
    other = Encoder(tmp_path / "models")
    with pytest.raises(edgepose.CodebookError, match="different encoder"):
        edgepose.estimate(render_view(mesh, seed=2).cloud, codebook, encoder=other)


def test_a_millimetre_cloud_is_reported(drill):
    mesh, codebook = drill
    cloud_mm = render_view(mesh, seed=3).cloud * 1000.0
    with pytest.raises(edgepose.InvalidCloudError, match="millimetres"):
        edgepose.estimate(cloud_mm, codebook)


def test_a_doubtful_pose_gets_a_second_wider_search_that_never_does_worse(drill):
    mesh, codebook = drill
    settings = edgepose.EstimateSettings()
    for seed in (3, 100):
        view = render_view(mesh, seed=seed)
        first = edgepose.estimate(view.cloud, codebook, settings=settings.with_(**{"second_search.pair_poses": 0}))
        # A bar no pose clears: every estimate is doubtful and searched again.
        doubting = settings.with_(**{"second_search.retry_below_inlier_fraction": 1.01})
        both = edgepose.estimate(view.cloud, codebook, settings=doubting)
        assert first.searches == 1 and len(first.candidates) == 16
        assert both.searches == 2 and 16 < len(both.candidates) <= 16 + settings.second_search.pair_poses
        assert "pair_poses" in both.timings and "pair_poses" not in first.timings
        np.testing.assert_array_equal(both.candidates[:16], first.candidates)  # the same ranking, extended
        wider = edgepose.estimate(view.cloud, codebook, settings=doubting.with_(**{"second_search.retry_k": 48}))
        ranking = retrieve(prepare_query(view.cloud, codebook), codebook, default_encoder(), 48).views
        np.testing.assert_array_equal(wider.candidates[:48], ranking)  # 32 more views down the cosine ranking
        assert len(wider.candidates) == len(both.candidates) + 32
        assert net(both) >= net(first) - 1e-12
        assert errors(both, view, codebook).add < 0.1 * codebook.model.diameter


def test_a_pose_below_the_retry_confidence_is_searched_again(drill):
    # A clean view's pose is neither unrefined nor short of points nor in
    # free space: only its confidence can send it to the second search.
    mesh, codebook = drill
    view = render_view(mesh, seed=3)
    settings = edgepose.EstimateSettings()
    trusted = edgepose.estimate(
        view.cloud, codebook, settings=settings.with_(**{"second_search.retry_below_confidence": 0.0})
    )
    assert trusted.searches == 1 and 0.0 < trusted.confidence < 1.0
    retried = edgepose.estimate(
        view.cloud,
        codebook,
        settings=settings.with_(**{"second_search.retry_below_confidence": trusted.confidence + 1e-9}),
    )
    assert retried.searches == 2 and "pair_poses" in retried.timings
    # The wider search keeps the first pose unless it explains more.
    assert net(retried) >= net(trusted) - 1e-12
    assert errors(retried, view, codebook).add < 0.1 * codebook.model.diameter
    default = edgepose.estimate(view.cloud, codebook)
    assert default.searches == (2 if trusted.confidence < settings.second_search.retry_below_confidence else 1)


def test_doubt_is_a_pose_that_explains_too_few_points_or_violates_free_space(drill):
    from edgepose.search import doubtful, explains_more
    from edgepose.stages import PoseScores, Refined, prepare_query

    mesh, codebook = drill
    view = render_view(mesh, seed=3)
    query = prepare_query(view.cloud, codebook)
    R, t = view.T_cam_obj[:3, :3], view.T_cam_obj[:3, 3] + view.T_cam_obj[:3, :3] @ codebook.model.centre
    one = lambda v: np.array([v])  # noqa: E731
    unused = PoseScores(
        one(0.0), one(1.0), one(0.0), one(0.0), one(0.0), one(0.1), one(0.0)
    )  # doubt scores the pose itself
    flip = np.diag([1.0, -1.0, -1.0])  # turned over about the model's x axis, same centre
    assert not doubtful(query, codebook, Refined(0, R, t, unused, True))
    assert doubtful(query, codebook, Refined(0, R @ flip, t, unused, True))
    assert doubtful(query, codebook, Refined(0, R, t + [0, 0, 0.05], unused, True))  # 5 cm too far
    assert doubtful(query, codebook, Refined(0, R, t, unused, False))  # not refined

    def refined(inliers: float, violation: float, was_refined: bool = True, scene: float = 0.0) -> Refined:
        scores = PoseScores(one(0.001), one(inliers), one(violation), one(0.1), one(0.0), one(0.1), one(scene))
        return Refined(0, R, t, scores, was_refined)

    assert explains_more(refined(0.97, 0.0), refined(0.99, 0.05))
    assert explains_more(refined(0.97, 0.0), refined(0.99, 0.0, scene=0.05))  # scene violations count too
    assert not explains_more(refined(0.90, 0.0), refined(0.95, 0.01))
    assert explains_more(refined(0.5, 0.2), refined(0.99, 0.0, False))  # refined beats unrefined


def test_the_depth_frame_exposes_a_pose_out_of_the_occluders_shadow(drill):
    """Given the whole depth frame, a pose whose unseen part would stand in
    front of background the camera saw beside the mask is a contradiction;
    the true pose, whose unseen part is behind the occluder, is not."""
    from edgepose.cloud import checked_depth
    from edgepose.eval.scenes import render_scene
    from edgepose.stages import score_poses

    mesh, codebook = drill
    d = codebook.model.diameter
    view = render_scene(mesh, "visible40", seed=4)
    frame = (*checked_depth(view.depth, view.K, 1.0), 1.0)
    seen, blind = prepare_query(view.cloud, codebook, frame=frame), prepare_query(view.cloud, codebook)
    R = view.T_cam_obj[:3, :3]
    t = view.T_cam_obj[:3, 3] + R @ codebook.model.centre  # model frame → camera
    slid = [t + 0.4 * d * np.array(step) for step in ([1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0])]
    rotations, translations = np.stack([R] * 5), np.stack([t, *slid])
    scores = score_poses(seen, codebook, seen.points, rotations, translations, 0.02 * d, 0.0)
    assert scores.scene_violation[0] < 0.05
    assert scores.scene_violation[1:].max() > 0.2, scores.scene_violation
    assert (
        score_poses(blind, codebook, blind.points, rotations, translations, 0.02 * d, 0.0).scene_violation == 0
    ).all()

    pose = edgepose.estimate(view.cloud, codebook, depth=view.depth, K=view.K, depth_scale=1.0)
    assert errors(pose, view, codebook).correct_add_or_s
    assert pose.evidence["scene_violation"] < 0.05 and 0.5 <= pose.confidence <= 1.0
    assert edgepose.estimate(view.cloud, codebook).evidence["scene_violation"] == 0.0
    with pytest.raises(edgepose.InvalidCloudError, match="depth and K go together"):
        edgepose.estimate(view.cloud, codebook, depth=view.depth)
    with pytest.raises(edgepose.InvalidCloudError, match="2-D image"):
        edgepose.estimate(view.cloud, codebook, depth=view.depth[0], K=view.K)


def test_the_flip_rival_found_beside_the_polish_is_the_one_found_after_it(drill, monkeypatch):
    """The confidence's turned rival is handed to one of the Rust core's
    threads before the polish (``refine.flip_rival_beside_polish``, the default)
    or found after the polish in the caller's thread: the same poses,
    confidences and evidence, on whole and partly hidden views. The
    confidence uses stage 5's rival: it never looks for one of the refined
    pose itself."""
    from edgepose import search as search_module
    from edgepose import stages

    mesh, codebook = drill
    searches: list[bool] = []
    real = stages.RivalSearch.__init__

    def recorded(self, *args, beside, **kwargs):
        searches.append(beside)
        real(self, *args, beside=beside, **kwargs)

    monkeypatch.setattr(stages.RivalSearch, "__init__", recorded)

    def not_wanted(*args, **kwargs):
        raise AssertionError("the confidence looked for the refined pose's rival itself")

    monkeypatch.setattr(search_module, "flip_rival", not_wanted)
    settings = edgepose.EstimateSettings()
    for seed, occluders in [(3, 0), (11, 2), (21, 3)]:
        view = render_view(mesh, seed=seed, occluders=occluders)
        searches.clear()
        beside = edgepose.estimate(view.cloud, codebook, settings=settings)
        assert searches and all(searches), searches
        searches.clear()
        after = edgepose.estimate(
            view.cloud, codebook, settings=settings.with_(**{"refine.flip_rival_beside_polish": False})
        )
        assert searches and not any(searches), searches
        np.testing.assert_array_equal(beside.matrix, after.matrix)
        assert beside.confidence == after.confidence and beside.evidence == after.evidence


def test_work_shared_with_a_core_thread_gives_the_same_poses(drill):
    """The candidates' alignment and scores (``retrieve.candidates_on_two_cores``)
    and the first search's few coarse ICPs (``refine.coarse_icp_on_two_cores``),
    shared between the caller's thread
    and one of the core's (the defaults) or run on one: the same candidates,
    poses, confidences and evidence."""
    mesh, codebook = drill
    settings = edgepose.EstimateSettings()
    one_core = settings.with_(**{"refine.coarse_icp_on_two_cores": False, "retrieve.candidates_on_two_cores": False})
    for seed, occluders in [(4, 0), (12, 2), (22, 3)]:
        view = render_view(mesh, seed=seed, occluders=occluders)
        shared = edgepose.estimate(view.cloud, codebook, settings=settings)
        serial = edgepose.estimate(view.cloud, codebook, settings=one_core)
        np.testing.assert_array_equal(shared.candidate_fit, serial.candidate_fit)
        np.testing.assert_array_equal(shared.matrix, serial.matrix)
        assert shared.confidence == serial.confidence and shared.evidence == serial.evidence


def test_a_flip_rival_handed_to_a_core_thread_is_the_one_found_in_the_caller(drill):
    """The rival search handed to one of the core's threads gives what the
    caller's own search gives, bit for bit: asked for at once (the caller
    may take it back before a thread starts it), after the thread is done,
    or while the caller polishes; and again when asked twice."""
    from edgepose import stages

    mesh, codebook = drill
    settings = edgepose.EstimateSettings()
    for seed in (5, 6):
        view = render_view(mesh, seed=seed, occluders=2)
        query = prepare_query(view.cloud, codebook, settings=settings)
        # The true pose in the model frame (the mesh frame shifted by its
        # centre), 4 mm off, as a search leaves it before the polish.
        R = np.ascontiguousarray(view.T_cam_obj[:3, :3])
        t = view.T_cam_obj[:3, 3] + R @ codebook.model.centre + 0.004
        found = stages.RivalSearch(query, codebook, R, t, settings, beside=False).get()
        assert len(found.rotations) == 1
        at_once = stages.RivalSearch(query, codebook, R, t, settings, beside=True).get()
        later = stages.RivalSearch(query, codebook, R, t, settings, beside=True)
        time.sleep(0.05)
        icp, polished_beside = stages.polished(query, codebook, R, t, settings)
        alone = stages.polish(query, codebook, R[None], t[None], settings)
        for name in ("rotations", "translations", "inliers", "rmse"):
            np.testing.assert_array_equal(getattr(icp, name), getattr(alone, name))
        for rival in (at_once, later.get(), polished_beside.get(), later.get()):
            np.testing.assert_array_equal(rival.rotations, found.rotations)
            np.testing.assert_array_equal(rival.translations, found.translations)
            np.testing.assert_array_equal(rival.fits, found.fits)
            assert rival.net == found.net


#: What a forked child estimates: set in the parent before it forks.
_FORKED: dict = {}


def test_a_forked_child_estimates_and_builds_codebooks():
    """A process forked after the parent used the core's worker threads
    (Python's multiprocessing on Linux, a robot stack's workers) has none of
    them: the core starts its own there (``rust/src/threads.rs``) instead of
    waiting forever on threads that are not there, as rayon's global pool
    would. The child's pose is the parent's, bit for bit."""
    import multiprocessing

    import trimesh

    if "fork" not in multiprocessing.get_all_start_methods():
        pytest.skip("no fork on this platform")
    mesh = trimesh.creation.box((0.12, 0.07, 0.03))
    codebook = edgepose.build_codebook(mesh)
    view = render_view(mesh, seed=4)
    pose = edgepose.estimate(view.cloud, codebook)  # the parent's threads run
    _FORKED.update(mesh=mesh, cloud=view.cloud, codebook=codebook)
    with multiprocessing.get_context("fork").Pool(1) as pool:
        matrix, confidence, rebuilt = pool.apply_async(_estimate_in_child).get(timeout=120)
    np.testing.assert_array_equal(matrix, pose.matrix)
    assert confidence == pose.confidence
    assert rebuilt == codebook.model.diameter


def _estimate_in_child() -> tuple[np.ndarray, float, float]:
    """In a forked child: ``_FORKED``'s pose matrix and confidence, and the
    diameter of its mesh's codebook built afresh."""
    pose = edgepose.estimate(_FORKED["cloud"], _FORKED["codebook"])
    rebuilt = edgepose.build_codebook(_FORKED["mesh"])
    return pose.matrix, pose.confidence, rebuilt.model.diameter


def test_parallel_work_counts_the_cores_this_process_may_use():
    """In a process pinned to one core (``taskset``, a robot stack's CPU
    sets) edgepose counts one usable core (how many encoder threads and
    ``estimate_many`` workers it starts by default), not the machine's."""
    import subprocess
    import sys

    if not hasattr(os, "sched_setaffinity"):
        pytest.skip("no CPU affinity on this platform")
    script = (
        "import os; os.sched_setaffinity(0, {min(os.sched_getaffinity(0))});"
        "from edgepose.settings import usable_cores;"
        "print(usable_cores(), os.cpu_count())"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout.split()
    assert int(out[0]) == 1 and int(out[1]) >= 1


def test_the_free_space_tolerance_grows_with_the_sensor_noise_at_the_object_depth(drill):
    _, codebook = drill
    d = codebook.model.diameter
    settings = edgepose.EstimateSettings()
    a, b, c = settings.score.depth_noise
    near, far = (np.random.default_rng(0).normal(size=(500, 3)) * 0.03 + (0, 0, z) for z in (0.5, 1.5))
    q_near = prepare_query(near, codebook, settings)
    q_far = prepare_query(far, codebook, settings)
    # Close by, the fraction of the diameter rules; far away, three noise stds.
    assert free_space_tolerance(q_near.median_depth, d, settings) == pytest.approx(
        settings.score.free_space_tolerance * d
    )
    sigma_far = a + b * (q_far.median_depth - c) ** 2
    assert free_space_tolerance(q_far.median_depth, d, settings) == pytest.approx(3.0 * sigma_far)
    assert 3.0 * sigma_far > settings.score.free_space_tolerance * d
    quiet = settings.with_(**{"score.free_space_noise_sigmas": 0.0})
    assert free_space_tolerance(q_far.median_depth, d, quiet) == pytest.approx(settings.score.free_space_tolerance * d)
