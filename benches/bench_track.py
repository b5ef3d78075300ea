"""Tracking benchmark: rendered 30 fps sequences of the shared YCB objects,
followed by ``edgepose.Tracker``, by ``edgepose.estimate`` on every frame and
by Open3D point-to-plane ICP from the previous pose (started from the first
frame's estimate).

    .venv/bin/python benches/bench_track.py [--frames 1000] [--objects power_drill,...] [--out benches/TRACKING.md]

Each sequence (one per object, seeded) is, at 30 fps:

* smooth 6-DoF motion: the object 0.55–0.85 m away, drifting up to ±8 cm
  across and turning at 30–90°/s about a slowly changing axis;
* a fast burst (frames 300–329): turning at 180°/s and moving at 0.5 m/s;
* an occluder (frames 450–529): a board sliding in front of the object at
  0.5 m/s, hiding up to ~70 % of it;
* a loss (frames 650–669): the object leaves the view (empty frames) and
  comes back turned by the motion it made meanwhile;
* smooth motion again to the end.

Depth: LINEMOD camera, 1 mm noise, 1 mm quantisation, 2 % dropout; the mask
is the object's visible pixels. Reported per method and object: the share of
frames with ADD(-S) < 0.1 d (on the smooth frames, and on all frames with
the object at least 50 % visible), drift (ADD(-S) at the last frame minus at
frame 10, mm), frames from the object's return until the pose is correct
again, pose flips (the pose turning by more than 90° between consecutive
frames while the truth turns by less than 20°: a symmetric object's
equivalent poses swapping), and time per frame (median, p99; the tracker's
tracked frames alone too). ADD-S for objects with a detected symmetry.
Then, pooled over the objects, how well each edgepose method's
``Pose.confidence`` tells its correct poses from its wrong ones, tracked
frames apart from estimated ones (the model was fitted on estimated poses
only): AUROC, calibration error, and what the 0.5 rule and the strict rule
(``Pose.strict_threshold``) accept.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path

import edgepose
import numpy as np
import trimesh
from edgepose import report
from edgepose.eval import pose_errors
from edgepose.eval.render import LINEMOD_CAMERA, depth_to_cloud, rasterize_depth
from edgepose.model import read_mesh

REPO = Path(__file__).resolve().parents[1]
YCB = REPO.parent / "shared" / "data" / "ycb"
FPS = 30.0
FAST = (300, 330)
OCCLUDED = (450, 530)
LOST = (650, 670)
SEED_BASE = 31_000


@dataclass
class Sequence:
    name: str
    poses: list[np.ndarray]
    """True T_cam_obj per frame."""
    clouds: list[np.ndarray]
    visible: list[float]
    """Visible share of the object's unoccluded pixels (0 when out of view)."""


@dataclass
class Run:
    method: str
    errors: list[float] = field(default_factory=list)
    """ADD(-S) per frame, metres (inf: no pose)."""
    seconds: list[float] = field(default_factory=list)
    modes: list[str] = field(default_factory=list)
    rotations: list[np.ndarray] = field(default_factory=list)
    confidences: list[float] = field(default_factory=list)
    """Pose.confidence per frame (NaN: no pose, or a method without one) ..."""
    strict: list[float] = field(default_factory=list)
    """... and its Pose.strict_threshold."""


def trajectory(frames: int, seed: int, centre: np.ndarray) -> list[np.ndarray]:
    """True poses T_cam_obj (about the mesh's bounding-box ``centre``)."""
    rng = np.random.default_rng(seed)
    R = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
    position = np.array([0.0, 0.0, 0.7])
    phases = rng.uniform(0, 2 * np.pi, size=6)
    axis = rng.normal(size=3)
    poses = []
    for f in range(frames):
        s = f / FPS
        # Slowly changing turning axis and speed, smooth drift about the start.
        axis = axis + 0.05 * rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        speed = np.radians(60 + 30 * np.sin(0.7 * s + phases[0]))
        target = np.array([0.08 * np.sin(0.5 * s + phases[1]), 0.06 * np.sin(0.4 * s + phases[2]), 0.0])
        target[2] = 0.7 + 0.15 * np.sin(0.3 * s + phases[3])
        velocity = (target - position) * FPS * 0.2
        if FAST[0] <= f < FAST[1]:
            speed = np.radians(180)
            velocity = 0.5 * np.array([np.cos(phases[4]), np.sin(phases[4]), 0.0]) * (1 if f < sum(FAST) / 2 else -1)
        R = trimesh.transformations.rotation_matrix(speed / FPS, axis)[:3, :3] @ R
        position = position + velocity / FPS
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = position - R @ centre
        if LOST[0] <= f < LOST[1]:
            T = T.copy()
            T[0, 3] += 1.0  # out of the camera's view
        poses.append(T)
    return poses


def render(mesh: trimesh.Trimesh, T: np.ndarray, frame: int, seed: int, board: trimesh.Trimesh | None) -> tuple:
    """(cloud, visible share) of one frame; ``board`` (camera frame) occludes."""
    rng = np.random.default_rng(seed * 100_000 + frame)
    camera = LINEMOD_CAMERA
    vertices = np.asarray(mesh.vertices) @ T[:3, :3].T + T[:3, 3]
    depth = rasterize_depth(vertices, np.asarray(mesh.faces), camera)
    own = np.isfinite(depth)
    if not own.any():
        return np.zeros((0, 3)), 0.0
    visible = own
    if board is not None:
        front = rasterize_depth(np.asarray(board.vertices), np.asarray(board.faces), camera)
        visible = own & ~(front < depth)
    share = float(visible.sum() / own.sum())
    noisy = depth + rng.normal(0, 0.001, depth.shape)
    noisy = np.round(noisy / 0.001) * 0.001
    measured = visible & (rng.random(depth.shape) >= 0.02)
    return depth_to_cloud(np.where(measured, noisy, 0.0), camera, measured), share


def make_sequence(name: str, mesh: trimesh.Trimesh, frames: int, seed: int) -> Sequence:
    centre = (np.asarray(mesh.vertices).min(0) + np.asarray(mesh.vertices).max(0)) / 2
    poses = trajectory(frames, seed, centre)
    clouds, visible = [], []
    for f, T in enumerate(poses):
        board = None
        if OCCLUDED[0] <= f < OCCLUDED[1]:
            # A 20 × 40 cm board 15 cm in front of the object, sliding across at 0.5 m/s.
            c = T[:3, :3] @ centre + T[:3, 3]
            x = c[0] - 0.35 + 0.5 * (f - OCCLUDED[0]) / FPS
            board = trimesh.creation.box([0.2, 0.4, 0.005])
            board.apply_translation([x - 0.1, c[1], c[2] - 0.15])
        cloud, share = render(mesh, T, f, seed, board)
        clouds.append(cloud)
        visible.append(share)
    return Sequence(name, poses, clouds, visible)


def rotation_deg(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(A.T @ B) - 1) / 2, -1, 1))))


def run_method(method: str, seq: Sequence, codebook: edgepose.Codebook) -> Run:
    run = Run(method)
    points = codebook.model.mesh_points
    symmetric = codebook.symmetry.symmetric
    tracker = edgepose.Tracker(codebook)
    icp_peer = Open3dIcp(codebook) if method == "open3d-icp" else None
    last_T: np.ndarray | None = None
    for cloud, T_true in zip(seq.clouds, seq.poses):
        t0 = time.perf_counter()
        mode, pose = "", None
        try:
            if method == "tracker":
                pose = tracker.update(cloud)
                T, mode = pose.matrix, pose.mode
            elif method == "estimate":
                pose = edgepose.estimate(cloud, codebook)
                T, mode = pose.matrix, "estimated"
            else:
                assert icp_peer is not None
                T = edgepose.estimate(cloud, codebook).matrix if last_T is None else icp_peer.refine(cloud, last_T)
        except edgepose.EdgePoseError:
            T = None
        elapsed = time.perf_counter() - t0
        if T is not None:
            last_T = T
        error = pose_errors(points, T, T_true, codebook.model.diameter, symmetric).add_or_s if T is not None else np.inf
        run.errors.append(error)
        run.seconds.append(elapsed)
        run.modes.append(mode if T is not None else "none")
        run.rotations.append(T[:3, :3] if T is not None else None)
        run.confidences.append(pose.confidence if pose is not None else np.nan)
        run.strict.append(pose.strict_threshold if pose is not None else np.nan)
    return run


class Open3dIcp:
    """Open3D point-to-plane ICP of the frame onto the model, from a pose."""

    def __init__(self, codebook: edgepose.Codebook) -> None:
        import open3d as o3d

        self.o3d = o3d
        model = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(codebook.model.mesh_points))
        model.normals = o3d.utility.Vector3dVector(codebook.model.normals.astype(np.float64))
        self.model = model
        self.max_distance = 0.15 * codebook.model.diameter

    def refine(self, cloud: np.ndarray, T_start: np.ndarray) -> np.ndarray:
        o3d = self.o3d
        if len(cloud) < 32:
            raise edgepose.InvalidCloudError("empty frame")
        scene = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(cloud, dtype=np.float64)))
        scene = scene.voxel_down_sample(0.005)
        # Model → scene: align the model (source) onto the frame (target) needs the
        # frame's normals; align the frame onto the model instead and invert.
        result = o3d.pipelines.registration.registration_icp(
            scene,
            self.model,
            self.max_distance,
            np.linalg.inv(T_start),
            o3d.pipelines.registration.TransformationEstimationPointToPlane(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=20),
        )
        return np.linalg.inv(result.transformation)


def summary(run: Run, seq: Sequence, diameter: float) -> dict:
    err = np.array(run.errors)
    ok = err < 0.1 * diameter
    frames = len(err)
    smooth = np.ones(frames, bool)
    for a, b in (FAST, OCCLUDED, LOST):
        smooth[a : min(b + 30, frames)] = False  # and a second to settle
    half = np.array(seq.visible) >= 0.5
    back = LOST[1]
    recovery = next((f - back for f in range(back, frames) if half[f] and ok[f]), None) if back < frames else None
    flips = 0
    for f in range(1, frames):
        a, b = run.rotations[f - 1], run.rotations[f]
        if a is not None and b is not None:
            truth = rotation_deg(seq.poses[f - 1][:3, :3], seq.poses[f][:3, :3])
            flips += rotation_deg(a, b) > 90 and truth < 20
    ms = np.array(run.seconds) * 1e3
    tracked = ms[np.array(run.modes) == "tracked"]
    last = frames - 1
    return {
        "smooth_ok": 100 * ok[smooth].mean() if smooth.any() else np.nan,
        "visible_ok": 100 * ok[half].mean() if half.any() else np.nan,
        "fast_ok": 100 * ok[FAST[0] : FAST[1]].mean() if frames > FAST[1] else np.nan,
        "occluded_ok": 100 * ok[OCCLUDED[0] : OCCLUDED[1]][half[OCCLUDED[0] : OCCLUDED[1]]].mean()
        if frames > OCCLUDED[1] and half[OCCLUDED[0] : OCCLUDED[1]].any()
        else np.nan,
        "drift_mm": 1e3 * (err[last] - err[10]) if np.isfinite(err[[10, last]]).all() else np.inf,
        "recovery": recovery,
        "flips": flips,
        "median_ms": float(np.median(ms)),
        "p99_ms": float(np.percentile(ms, 99)),
        "tracked_median_ms": float(np.median(tracked)) if len(tracked) else np.nan,
        "tracked_p99_ms": float(np.percentile(tracked, 99)) if len(tracked) else np.nan,
        "reinit": sum(m == "reinitialised" for m in run.modes),
    }


def confidence_rows(runs: list[tuple[Run, float]]) -> list[list[str]]:
    """Per method and kind of frame (tracked, estimated: the rest), pooled
    over ``runs`` (each with its object's diameter): how well confidence
    tells correct poses from wrong ones. Frames without a pose are left out."""
    from edgepose.confidence import TRUST_THRESHOLD
    from edgepose.eval.metrics import Acceptance, acceptance, auroc, calibration

    pooled: dict[tuple[str, str], list[np.ndarray]] = {}
    for run, diameter in runs:
        p, strict = np.array(run.confidences), np.array(run.strict)
        correct = np.array(run.errors) < 0.1 * diameter
        tracked = np.array(run.modes) == "tracked"
        for kind, mask in (("tracked", tracked), ("estimated", ~tracked)):
            keep = mask & np.isfinite(p)
            if keep.any():
                pooled.setdefault((run.method, kind), []).append(np.stack([p[keep], strict[keep], correct[keep]]))
    rows = []
    for (method, kind), parts in pooled.items():
        p, strict, y = np.concatenate(parts, axis=1)
        y = y.astype(bool)
        default = acceptance(p, y, TRUST_THRESHOLD)
        known = np.isfinite(strict).all()
        strict_rule = acceptance(p, y, strict) if known else Acceptance(strict, np.nan, np.nan)

        def share(v: float) -> str:
            return f"{100 * v:.1f} %" if np.isfinite(v) else "–"

        rows.append(
            [
                method,
                kind,
                f"{len(y)}",
                f"{100 * y.mean():.1f} %",
                f"{auroc(p, y):.3f}" if 0 < y.sum() < len(y) else "–",
                f"{calibration(p, y).ece:.3f}",
                share(default.wrong_accepted),
                share(default.correct_kept),
                share(strict_rule.wrong_accepted),
                share(strict_rule.correct_kept),
            ]
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--objects", default="banana,cracker_box,master_chef_can,mustard_bottle,power_drill")
    parser.add_argument("--methods", default="tracker,estimate,open3d-icp")
    parser.add_argument("--out", type=Path, default=REPO / "benches" / "TRACKING.md")
    args = parser.parse_args()
    methods = args.methods.split(",")
    started = time.perf_counter()
    load_before = os.getloadavg()
    rows, runs = [], []
    for k, name in enumerate(args.objects.split(",")):
        mesh = read_mesh(YCB / f"{name}.ply")
        codebook = edgepose.build_codebook(mesh)
        t0 = time.perf_counter()
        seq = make_sequence(name, mesh, args.frames, SEED_BASE + k)
        print(f"{name}: {args.frames} frames rendered in {time.perf_counter() - t0:.0f} s", flush=True)
        for method in methods:
            try:
                run = run_method(method, seq, codebook)
            except ImportError as e:
                print(f"  {method}: skipped ({e})", flush=True)
                continue
            s = summary(run, seq, codebook.model.diameter)
            rows.append((name, method, s))
            runs.append((run, codebook.model.diameter))
            print(
                f"  {method:<11} smooth {s['smooth_ok']:5.1f}%  visible≥50% {s['visible_ok']:5.1f}%  "
                f"drift {s['drift_mm']:+.1f} mm  recovery {s['recovery']}  flips {s['flips']}  "
                f"median {s['median_ms']:.2f} ms  p99 {s['p99_ms']:.2f} ms  tracked {s['tracked_median_ms']:.2f}/"
                f"{s['tracked_p99_ms']:.2f} ms  reinit {s['reinit']}",
                flush=True,
            )
    confidence = confidence_rows(runs)
    for row in confidence:
        print("  confidence: " + "  ".join(row), flush=True)
    write_markdown(args, rows, methods, confidence, time.perf_counter() - started, load_before)


def write_markdown(args, rows, methods, confidence: list[list[str]], wall_s: float, load_before) -> None:
    def fmt(v, spec: str) -> str:
        return "–" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, spec)

    table = report.markdown_table(
        [
            "object",
            "method",
            "smooth ok",
            "fast turn ok",
            "occluded (≥ 50 %) ok",
            "all ≥ 50 % visible ok",
            "drift mm",
            "frames to recover",
            "flips",
            "median ms",
            "p99 ms",
            "tracked median / p99 ms",
            "re-inits",
        ],
        "ll" + "r" * 11,
        [
            [
                name,
                method,
                fmt(s["smooth_ok"], ".1f") + " %",
                fmt(s["fast_ok"], ".1f") + " %",
                fmt(s["occluded_ok"], ".1f") + " %",
                fmt(s["visible_ok"], ".1f") + " %",
                fmt(s["drift_mm"], "+.1f"),
                fmt(s["recovery"], "d"),
                f"{s['flips']}",
                fmt(s["median_ms"], ".2f"),
                fmt(s["p99_ms"], ".2f"),
                f"{fmt(s['tracked_median_ms'], '.2f')} / {fmt(s['tracked_p99_ms'], '.2f')}",
                f"{s['reinit']}",
            ]
            for name, method, s in rows
        ],
    )
    pooled = []
    for method in methods:
        mine = [s for _, m, s in rows if m == method]
        if mine:
            pooled.append(
                f"- **{method}**: smooth frames correct {np.mean([s['smooth_ok'] for s in mine]):.1f} % "
                f"(mean over objects), flips {sum(s['flips'] for s in mine)}, median "
                f"{np.median([s['median_ms'] for s in mine]):.2f} ms per frame"
            )
    confidence_table = report.markdown_table(
        [
            "method",
            "frames",
            "poses",
            "correct",
            "AUROC",
            "ECE",
            "wrong accepted (≥ 0.5)",
            "correct kept (≥ 0.5)",
            "wrong accepted (strict)",
            "correct kept (strict)",
        ],
        "ll" + "r" * 8,
        confidence,
    )
    text = f"""# Tracking benchmark

Generated by `benches/bench_track.py`; do not edit by hand.

```bash
.venv/bin/python benches/bench_track.py --frames {args.frames} --objects {args.objects} --methods {",".join(methods)}
```

- date: {datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")}
- machine: {platform.machine()}, {os.cpu_count()} CPUs
- load average (1 min) before: {load_before[0]:.2f}, after: {os.getloadavg()[0]:.2f}
- wall time: {wall_s / 60:.1f} min

{__doc__.split(chr(10) + chr(10), 1)[1]}
{table}

{chr(10).join(pooled)}

## Confidence

Pooled over the objects; frames without a pose left out. Correct: ADD(-S) < 0.1 d.
Strict rule: confidence ≥ `Pose.strict_threshold`.

{confidence_table}
"""
    args.out.write_text(text)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
