"""The evaluation loop shared by ``edgepose eval`` and ``benches/bench_pose.py``:
render views of each object with known poses, run a pose method on every
view, score each estimate and summarise.

Units are metres; poses are ``T_cam_obj``. Latency is the wall-clock time of
one ``method.estimate(cloud)`` call; one untimed warm-up estimate per object
precedes the timed ones.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from edgepose.confidence import TRUST_THRESHOLD
from edgepose.eval.baselines import NO_POSE, PoseMethod
from edgepose.eval.metrics import Acceptance, PoseErrors, acceptance, auc, auroc, calibration, pose_errors
from edgepose.eval.scenes import render_scene
from edgepose.eval.stress import STRESS_LEVELS, Stress

if TYPE_CHECKING:
    import trimesh


@dataclass
class BenchObject:
    """One benchmark object: its mesh, metric points and rendered views."""

    name: str
    mesh: trimesh.Trimesh
    points: np.ndarray
    """(N, 3) float64 model points in the original mesh frame, metres (for the metrics)."""
    diameter: float
    """Metres."""
    symmetric: bool
    """Judged with ADD-S in ADD(-S) (by default: when :func:`edgepose.symmetry.detect_symmetry` finds a symmetry)."""
    seeds: list[int]
    clouds: list[np.ndarray]
    """Per view: (N, 3) float64 camera-frame cloud, metres."""
    poses: list[np.ndarray]
    """Per view: (4, 4) true T_cam_obj."""
    stress: str = "clean"
    """Name of the :class:`edgepose.eval.stress.Stress` level the views were rendered at."""
    visible: list[float] = field(default_factory=list)
    """Per view: achieved visible fraction of the object (1 when unoccluded)."""
    spill: list[float] = field(default_factory=list)
    """Per view: spilled (off-object) points / object points in the cloud."""
    frames: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    """Per view: the whole depth frame the cloud was cut from, ((H, W)
    float32 metres, 0: no measurement; K (3, 3)), for methods that use it
    (``uses_frame``)."""


@dataclass
class ViewResult:
    method: str
    object: str
    view: int
    seed: int
    points: int
    latency_s: float
    errors: PoseErrors
    score: float
    T_est: np.ndarray
    error: str
    confidence: float = float("nan")
    """The method's probability that the pose is correct (edgepose; NaN for methods without one)."""
    strict_threshold: float = float("nan")
    """The confidence its strict rule asks for (edgepose's ``Pose.strict_threshold``; NaN: none)."""
    alternatives: int = 0
    """How many other poses the method offered (edgepose's ``Pose.alternatives``) ..."""
    alternative_correct: bool = False
    """... and whether one of them is within ADD(-S) < 0.1 × diameter of the truth."""


@dataclass
class MethodRun:
    """Every view one method estimated."""

    name: str
    prepare_s: dict[str, float]
    """Seconds of per-object preparation (codebook build, training), by object name."""
    views: list[ViewResult]


@dataclass
class Summary:
    views: int
    add_s_pass: float
    """Percent of views with ADD-S < 0.1 × diameter."""
    add_or_s_pass: float
    """Percent of views with ADD(-S) < 0.1 × diameter."""
    auc_add_s: float
    auc_add_or_s: float
    median_ms: float
    p90_ms: float
    failures: int


def load_object(
    mesh: str | Path | trimesh.Trimesh,
    seeds: list[int],
    *,
    name: str | None = None,
    symmetric: bool | None = None,
    occluders: int = 0,
    stress: Stress | str = "clean",
) -> BenchObject:
    """A mesh (file in metres or detected millimetres, or a Trimesh in metres)
    and one rendered view per seed. ``symmetric`` defaults to whether
    :func:`edgepose.symmetry.detect_symmetry` finds a symmetry.

    At the ``clean`` stress level (the default) the views are
    :func:`edgepose.eval.render_view`'s, with ``occluders`` flat rectangles:
    the clouds are identical to those of earlier benchmark runs. Any other
    level renders :func:`edgepose.eval.scenes.render_scene` scenes (support
    plane, neighbours, solid occluders, the level's sensor and mask effects);
    ``occluders`` must then be 0."""
    import trimesh

    from edgepose.eval.render import render_view
    from edgepose.model import load_model, read_mesh
    from edgepose.symmetry import detect_symmetry

    stress = STRESS_LEVELS[stress] if isinstance(stress, str) else stress
    if isinstance(mesh, trimesh.Trimesh):
        name = name or "object"
    else:
        name = name or Path(mesh).stem
        mesh = read_mesh(mesh, scale=None)
    model = load_model(mesh)
    if stress.background:
        if occluders:
            raise ValueError("occluders (flat rectangles) apply to the clean level only; stress levels set their own")
        scenes = [render_scene(mesh, stress, seed=s) for s in seeds]
        clouds, poses = [v.cloud for v in scenes], [v.T_cam_obj for v in scenes]
        frames = [(v.depth, v.K) for v in scenes]
        visible, spill = [v.visible_fraction for v in scenes], [v.spill_fraction for v in scenes]
    else:
        views = [
            render_view(
                mesh,
                seed=s,
                occluders=occluders,
                distance=stress.distance,
                depth_noise=stress.depth_noise,
                quantization=stress.quantization,
                dropout=stress.dropout,
            )
            for s in seeds
        ]
        clouds, poses = [v.cloud for v in views], [v.T_cam_obj for v in views]
        frames = [(v.depth, v.camera.K) for v in views]
        visible, spill = [float("nan") if occluders else 1.0] * len(seeds), [0.0] * len(seeds)
    return BenchObject(
        name=name,
        mesh=mesh,
        points=model.mesh_points,
        diameter=model.diameter,
        symmetric=detect_symmetry(model).symmetric if symmetric is None else symmetric,
        seeds=list(seeds),
        clouds=clouds,
        poses=poses,
        stress=stress.name,
        visible=visible,
        spill=spill,
        frames=frames,
    )


def run_method(
    method: PoseMethod,
    objects: list[BenchObject],
    progress: Callable[[BenchObject, int, list[ViewResult], float], None] | None = None,
) -> MethodRun:
    """Prepare ``method`` for each object and estimate every view. After each
    view, ``progress(object, views done, that object's results, prepare
    seconds)`` is called when given."""
    name = method.name
    run = MethodRun(name=name, prepare_s={}, views=[])
    for obj in objects:
        t0 = time.perf_counter()
        method.prepare(obj.mesh)
        run.prepare_s[obj.name] = time.perf_counter() - t0
        frames: list[tuple[np.ndarray, np.ndarray] | None] = list(obj.frames) or [None] * len(obj.clouds)
        timed_estimate(method, obj.clouds[0], frames[0])
        done: list[ViewResult] = []
        for i, (cloud, T_gt, seed) in enumerate(zip(obj.clouds, obj.poses, obj.seeds)):
            T_est, latency, error = timed_estimate(method, cloud, frames[i])
            last = getattr(method, "last", None)
            alternatives = getattr(last, "alternatives", ()) if not error else ()
            result = ViewResult(
                method=name,
                object=obj.name,
                view=i,
                seed=seed,
                points=len(cloud),
                latency_s=latency,
                errors=pose_errors(obj.points, T_est, T_gt, obj.diameter, obj.symmetric),
                score=float(getattr(last, "score", 0.0)) if not error else 0.0,
                T_est=T_est,
                error=error,
                confidence=float(getattr(last, "confidence", np.nan)) if not error else 0.0,
                strict_threshold=float(getattr(last, "strict_threshold", np.nan)),
                alternatives=len(alternatives),
                alternative_correct=any(
                    pose_errors(obj.points, T, T_gt, obj.diameter, obj.symmetric).correct_add_or_s for T in alternatives
                ),
            )
            run.views.append(result)
            done.append(result)
            if progress is not None:
                progress(obj, i + 1, done, run.prepare_s[obj.name])
    return run


def merge_runs(name: str, runs: list[MethodRun]) -> MethodRun:
    """One method's runs on different objects (e.g. one per catalogue job) as one run."""
    return MethodRun(name, {o: s for r in runs for o, s in r.prepare_s.items()}, [v for r in runs for v in r.views])


def timed_estimate(
    method: PoseMethod, cloud: np.ndarray, frame: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[np.ndarray, float, str]:
    """(T_est, seconds, error message); an exception counts as a miss
    (NO_POSE). A method whose ``uses_frame`` is true also gets the view's
    depth ``frame`` (when there is one)."""
    t0 = time.perf_counter()
    try:
        if frame is not None and getattr(method, "uses_frame", False):
            T = np.asarray(method.estimate(cloud, frame=frame), dtype=np.float64)  # type: ignore[call-arg]
        else:
            T = np.asarray(method.estimate(cloud), dtype=np.float64)
        error = ""
    except Exception as e:  # a failed estimate is a result, not a crash
        T, error = NO_POSE.copy(), f"{type(e).__name__}: {e}"
    latency = time.perf_counter() - t0
    if T.shape != (4, 4) or not np.isfinite(T).all():
        T, error = NO_POSE.copy(), error or f"invalid pose {T.shape}"
    return T, latency, error


def summarise(views: list[ViewResult]) -> Summary:
    """Accuracies (percent), AUCs (× 100) and latencies (ms) of some views."""
    latency = np.array([v.latency_s for v in views]) * 1e3
    return Summary(
        views=len(views),
        add_s_pass=percent(views, "correct_add_s"),
        add_or_s_pass=percent(views, "correct_add_or_s"),
        auc_add_s=100 * auc(np.array([v.errors.add_s for v in views])),
        auc_add_or_s=100 * auc(np.array([v.errors.add_or_s for v in views])),
        median_ms=float(np.median(latency)),
        p90_ms=float(np.percentile(latency, 90)),
        failures=sum(bool(v.error) for v in views),
    )


@dataclass
class ConfidenceSummary:
    """How well a method's confidences tell its correct poses (ADD(-S)) from its wrong ones."""

    views: int
    correct: float
    """Percent of views correct."""
    auroc: float
    """Area under the ROC curve (NaN when all views are correct or all wrong)."""
    ece: float
    """Expected calibration error, 10 bins."""
    wrong_accepted: float
    """Percent of wrong poses with confidence ≥ the trust threshold (NaN: none wrong)."""
    correct_kept: float
    """Percent of correct poses with confidence ≥ the trust threshold (NaN: none correct)."""
    threshold: float = TRUST_THRESHOLD
    strict_wrong_accepted: float = float("nan")
    """Percent of wrong poses with confidence ≥ their strict threshold (NaN: none wrong, or no strict rule) ..."""
    strict_correct_kept: float = float("nan")
    """... and of correct poses (NaN: none correct, or no strict rule)."""
    strict_thresholds: tuple[float, ...] = ()
    """The distinct strict thresholds of the views (none: no strict rule)."""


def summarise_confidence(views: list[ViewResult], threshold: float = TRUST_THRESHOLD) -> ConfidenceSummary | None:
    """Confidence quality over ``views``; None when the method gives no confidences."""
    p = np.array([v.confidence for v in views], dtype=np.float64)
    if not len(p) or not np.isfinite(p).all():
        return None
    y = np.array([v.errors.correct_add_or_s for v in views], dtype=bool)
    a = acceptance(p, y, threshold)
    # The strict rule: each pose against the threshold of the model that judged it.
    strict = np.array([v.strict_threshold for v in views], dtype=np.float64)
    known = bool(np.isfinite(strict).all())
    s = acceptance(p, y, strict) if known else Acceptance(strict, float("nan"), float("nan"))
    return ConfidenceSummary(
        len(views),
        100 * y.mean(),
        auroc(p, y),
        calibration(p, y).ece,
        100 * a.wrong_accepted,
        100 * a.correct_kept,
        threshold,
        100 * s.wrong_accepted,
        100 * s.correct_kept,
        tuple(sorted(set(strict.tolist()))) if known else (),
    )


def percent(views: list[ViewResult], field: str) -> float:
    """Percent of ``views`` whose boolean :class:`PoseErrors` ``field`` is true (0 for none)."""
    return 100.0 * sum(getattr(v.errors, field) for v in views) / max(len(views), 1)
