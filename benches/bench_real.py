"""Real-data benchmark: edgepose on real depth frames in the BOP layout
(default ``../shared/data/ycbv_real``: YCB-Video, Asus Xtion depth), per
object and overall, with the annotated visible masks and with masks grown
by 2, 4 and 8 px (a detector's spill), from the cloud alone and given the
depth frame; Open3D FPFH+RANSAC+ICP on the same clouds; the tracker over
each scene's clip; and, in the same process, edgepose on clean synthetic
views of the shared YCB meshes (the latency reference).

    .venv/bin/python benches/bench_real.py [--data DIR] [--grow 0,2,4,8] [--out benches/REAL.md]

Correct means depth-fair ADD(-S) < 0.1 × diameter: ADD-S for objects
edgepose finds shape-symmetric, ADD otherwise (:mod:`edgepose.eval.real`).
BOP's AR (VSD, MSSD, MSPD) uses the dataset's own symmetries. Times are
wall-clock per estimate call (median, 90th percentile), the frame read
before the clock starts. Writes ``REAL.md`` and ``REAL_targets.csv``
beside ``--out``; codebooks are cached in ``benches/.cache/``.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import subprocess
import time
from pathlib import Path

import numpy as np
from bench_pose import settings_from
from edgepose.eval.baselines import Open3DBaseline
from edgepose.eval.benchmark import load_object, timed_estimate
from edgepose.eval.bop import YCBV_OBJ_ID, BopDataset
from edgepose.eval.bop_run import bop_codebooks
from edgepose.eval.bop_score import score_bop
from edgepose.eval.metrics import acceptance, auroc, calibration, pose_errors
from edgepose.eval.real import TargetResult, bop_rows, estimate_targets, real_objects, target_instances, track_clips
from edgepose.model import read_mesh

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "ycbv_real"
YCB = REPO.parent / "shared" / "data" / "ycb"
CACHE = REPO / "benches" / ".cache"
#: YCB-Video object names by BOP id (for the tables).
NAMES = {obj_id: name for name, obj_id in YCBV_OBJ_ID.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DATA, help="a BOP-layout folder of real frames")
    parser.add_argument("--grow", default="0,2,4,8", help="mask growth levels, pixels")
    parser.add_argument("--peer-grow", default="0,4", help="levels Open3D runs at ('' for none)")
    parser.add_argument("--ar-grow", default="0,4", help="levels BOP's AR is scored at (VSD renders every pose)")
    parser.add_argument("--synthetic-views", type=int, default=8, help="clean synthetic views per shared YCB mesh")
    parser.add_argument("--no-track", action="store_true", help="skip the clips")
    parser.add_argument("--out", type=Path, default=REPO / "benches" / "REAL.md")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="change an EstimateSettings field, a stage's by its dotted name (repeatable; never for benches/REAL.md)",
    )
    args = parser.parse_args()
    settings = settings_from(args.set)
    if args.set and args.out.resolve() == (REPO / "benches" / "REAL.md").resolve():
        parser.error("--set never writes the reported figures (benches/REAL.md); choose another --out")
    load_before = os.getloadavg()
    started = time.perf_counter()
    dataset = BopDataset(args.data)
    targets = dataset.targets()
    obj_ids = sorted({t.obj_id for t in targets})
    codebooks = bop_codebooks(dataset, obj_ids, CACHE / f"{dataset.name}_codebooks")
    levels = [int(g) for g in args.grow.split(",") if g != ""]
    results: list[TargetResult] = []
    for grow in levels:
        for with_frame in (False, True):
            t0 = time.perf_counter()
            results += estimate_targets(dataset, targets, codebooks, grow, with_frame=with_frame, settings=settings)
            print(f"grow {grow} px, frame {with_frame}: {time.perf_counter() - t0:.1f} s", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    _write_csv(args.out.with_name(args.out.stem + "_targets.csv"), results)
    t0 = time.perf_counter()
    peer = _open3d(dataset, targets, codebooks, [int(g) for g in args.peer_grow.split(",") if g != ""])
    print(f"Open3D: {time.perf_counter() - t0:.1f} s", flush=True)
    t0 = time.perf_counter()
    synthetic = _synthetic_clean(args.synthetic_views)
    print(f"synthetic: {time.perf_counter() - t0:.1f} s", flush=True)
    t0 = time.perf_counter()
    clips = None if args.no_track else track_clips(dataset, codebooks, settings=settings)
    print(f"clips: {time.perf_counter() - t0:.1f} s", flush=True)
    t0 = time.perf_counter()
    ar = {}
    for grow in [int(g) for g in args.ar_grow.split(",") if g != "" and int(g) in levels]:
        for method in ("estimate", "estimate+frame"):
            level = [r for r in results if r.grow_px == grow and r.method == method]
            ar[(method, grow)] = score_bop(dataset, bop_rows(level), targets)
    print(f"BOP scores: {time.perf_counter() - t0:.1f} s", flush=True)
    report = _report(args, dataset, results, ar, peer, synthetic, clips, load_before, time.perf_counter() - started)
    args.out.write_text(report)
    print(report)


def _open3d(dataset, targets, codebooks, levels: list[int]) -> dict[int, list[tuple[float, bool, int]]]:
    """Per mask level: (seconds, correct, obj_id) of Open3D on each target's cloud."""
    from edgepose.cloud import cloud_from_depth, dilate

    out: dict[int, list[tuple[float, bool, int]]] = {g: [] for g in levels}
    if not levels:
        return out
    objects = real_objects(codebooks)
    instances = target_instances(dataset, targets)
    method = Open3DBaseline()
    for obj_id in sorted({i[2] for i in instances}):
        method.prepare(read_mesh(dataset.objects[obj_id].mesh, scale=0.001))
        obj = objects[obj_id]
        for image, gt_id, oid in instances:
            if oid != obj_id:
                continue
            depth = image.depth()
            gt = next(g for g in image.gts if g.gt_id == gt_id)
            for grow in levels:
                mask = image.mask(gt_id)
                cloud = cloud_from_depth(depth, image.K, dilate(mask, grow) if grow else mask, depth_scale=1.0)
                T, seconds, _ = timed_estimate(method, cloud)
                correct = pose_errors(obj.points, T, gt.matrix, obj.diameter, obj.symmetric).correct_add_or_s
                out[grow].append((seconds, bool(correct), obj_id))
    return out


def _synthetic_clean(views: int) -> list[tuple[float, dict, int, int]]:
    """(seconds, stage timings, searches, points) per estimate on clean
    synthetic views of the shared YCB meshes (same process)."""
    import edgepose

    out = []
    for mesh in sorted(YCB.glob("*.ply")):
        obj = load_object(mesh, list(range(900000, 900000 + views)))
        codebook = edgepose.build_codebook(obj.mesh)
        edgepose.estimate(obj.clouds[0], codebook)
        for cloud in obj.clouds:
            t0 = time.perf_counter()
            pose = edgepose.estimate(cloud, codebook)
            out.append((time.perf_counter() - t0, pose.timings, pose.searches, len(cloud)))
    return out


def _stage_medians(timings: list[dict]) -> str:
    stages: dict[str, list[float]] = {}
    for t in timings:
        for k, v in t.items():
            stages.setdefault(k, []).append(v * 1000)
    return ", ".join(f"{k} {np.median(v):.2f} ms ({len(v)})" for k, v in stages.items())


def _pct(x: float) -> str:
    return "—" if not np.isfinite(x) else f"{x:.1f} %"


def _confidence_cells(level: list[TargetResult]) -> str:
    posed = [r for r in level if r.pose is not None]
    p = np.array([r.pose.confidence for r in posed])
    y = np.array([r.correct for r in posed])
    if not len(p) or not np.isfinite(p).all():
        return "| — | — | — | — | — | — |"
    strict = np.array([r.pose.strict_threshold for r in posed])
    a, s = acceptance(p, y, 0.5), acceptance(p, y, strict)
    wrong = int((~y).sum())
    trusted = int(round(s.wrong_accepted * wrong)) if wrong else 0
    return (
        f"| {auroc(p, y):.3f} | {calibration(p, y).ece:.3f} | {_pct(100 * a.wrong_accepted)} | "
        f"{_pct(100 * a.correct_kept)} | {_pct(100 * s.wrong_accepted)} ({trusted} of {wrong}) | "
        f"{_pct(100 * s.correct_kept)} |"
    )


def _report(args, dataset, results, ar, peer, synthetic, clips, load_before, seconds) -> str:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=REPO)
    levels = sorted({r.grow_px for r in results})
    methods = ("estimate", "estimate+frame")
    n_targets = len({(r.scene_id, r.im_id, r.obj_id) for r in results})
    lines = [
        "# Real depth frames",
        "",
        f"`benches/bench_real.py` on `{args.data.name}` ({n_targets} targets, "
        f"{len({(r.scene_id, r.im_id) for r in results})} images, {len({r.obj_id for r in results})} objects), "
        f"commit {commit.stdout.strip()}, {datetime.datetime.now():%Y-%m-%d %H:%M}, {platform.machine()}, "
        f"{os.cpu_count()} CPUs, load {load_before[0]:.2f} before, {seconds / 60:.1f} min in all.",
        "",
        f"Settings changed from the defaults: {', '.join(f'`{c}`' for c in args.set)}."
        if args.set
        else "Default settings.",
        "",
        "Correct: depth-fair ADD(-S) < 0.1 × diameter (ADD-S for objects edgepose finds shape-symmetric). "
        "Masks: the annotated visible masks (`grow 0`), or grown by 2, 4, 8 px as a detector's spill. "
        "`estimate`: from the cloud alone; `estimate+frame`: given the depth frame (`depth=`, `K=`).",
        "",
        "View-fair: right, or the view hides what breaks the object's near symmetry (read from the ground truth by "
        "`edgepose.eval.view_ambiguity`: a mug's handle) and the pose says it cannot tell (confidence below "
        "`pose.strict_threshold`, the truth among its alternatives). " + _hidden_views(results) + ".",
        "",
        "## Accuracy and time",
        "",
        "| method | mask | ADD(-S) | view-fair | or an alternative | BOP AR | VSD | MSSD | MSPD | second searches | "
        "median ms | p90 ms |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for method, grow, level in _by_level(results, methods, levels):
        ms = np.array([r.seconds for r in level]) * 1000
        scored = ar.get((method, grow))
        bop = " | ".join(
            f"{100 * x:.1f}" if scored else "—"
            for x in (
                (scored.overall.ar, scored.overall.ar_vsd, scored.overall.ar_mssd, scored.overall.ar_mspd)
                if scored
                else (0,) * 4
            )
        )
        second = np.mean([r.pose is not None and r.pose.searches == 2 for r in level])
        lines.append(
            f"| {method} | grow {grow} | {_pct(100 * np.mean([r.correct for r in level]))} | "
            f"{_pct(100 * np.mean([r.view_fair_correct for r in level]))} | "
            f"{_pct(100 * np.mean([r.correct or r.alternative_correct for r in level]))} | "
            f"{bop} | "
            f"{_pct(100 * second)} | {np.median(ms):.1f} | {np.percentile(ms, 90):.1f} |"
        )
    for grow, rows in peer.items():
        ms = np.array([r[0] for r in rows]) * 1000
        lines.append(
            f"| Open3D FPFH+RANSAC+ICP | grow {grow} | {_pct(100 * np.mean([r[1] for r in rows]))} | — | — | — | — | "
            f"— | — | — | {np.median(ms):.1f} | {np.percentile(ms, 90):.1f} |"
        )
    lines += ["", "## Speed against peers and against synthetic views (same process)", ""]
    base = [r.seconds for r in results if r.method == "estimate" and r.grow_px == 0]
    syn = np.median([s[0] for s in synthetic]) * 1000 if synthetic else float("nan")
    real_points = np.median([r.points for r in results if r.method == "estimate" and r.grow_px == 0])
    lines.append(
        f"- edgepose on clean synthetic views of the shared YCB meshes ({len(synthetic)} views, median "
        f"{np.median([s[3] for s in synthetic]):.0f} points, second searches "
        f"{100 * np.mean([s[2] == 2 for s in synthetic]):.0f} %): median {syn:.1f} ms; real frames (GT masks, "
        f"cloud alone, median {real_points:.0f} points): median {np.median(base) * 1000:.1f} ms, "
        f"**{np.median(base) * 1000 / syn:.2f}×** the synthetic median."
    )
    lines.append("- Synthetic stage medians: " + _stage_medians([s[1] for s in synthetic]) + ".")
    for grow, rows in peer.items():
        mine = [r.seconds for r in results if r.method == "estimate" and r.grow_px == grow]
        lines.append(
            f"- Open3D on the same real clouds (grow {grow}): median {np.median([r[0] for r in rows]) * 1000:.1f} ms, "
            f"**{np.median([r[0] for r in rows]) / np.median(mine):.1f}×** edgepose's median."
        )
    real_timings = [r.pose.timings for r in results if r.method == "estimate" and r.grow_px == 0 and r.pose]
    lines.append(
        "- Real stage medians (GT masks, cloud alone, over the estimates that ran the stage): "
        + _stage_medians(real_timings)
        + "."
    )
    lines += [
        "",
        "## Confidence",
        "",
        "Wrong poses trusted and right poses kept by the default rule (`confidence >= 0.5`) and the strict rule "
        "(`confidence >= pose.strict_threshold`).",
        "",
        "| method | mask | right | AUROC | ECE | wrong trusted at 0.5 | right kept at 0.5 | strict: wrong trusted "
        "| strict: right kept |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for method, grow, level in _by_level(results, methods, levels):
        lines.append(
            f"| {method} | grow {grow} | {_pct(100 * np.mean([r.correct for r in level]))} " + _confidence_cells(level)
        )
    lines += ["", "## Per object (ADD(-S), depth-fair)", ""]
    header = " | ".join(f"{m} g{g}" for m in methods for g in levels)
    lines += [f"| object | targets | symmetric | {header} |", "| --- | ---: | --- |" + " ---: |" * (2 * len(levels))]
    for obj_id in sorted({r.obj_id for r in results}):
        mine = [r for r in results if r.obj_id == obj_id]
        cells = " | ".join(
            _pct(100 * np.mean([r.correct for r in mine if r.method == m and r.grow_px == g]))
            for m in methods
            for g in levels
        )
        n = len([r for r in mine if r.method == "estimate" and r.grow_px == levels[0]])
        sym = "yes" if real_objects_symmetric(mine) else "no"
        lines.append(f"| {obj_id} {NAMES.get(obj_id, '')} | {n} | {sym} | {cells} |")
    if clips is not None:
        frames = clips.frames
        modes = {m: sum(f.mode == m for f in frames) for m in ("initialised", "tracked", "reinitialised", "lost")}
        tracked_ms = [f.seconds * 1000 for f in frames if f.mode == "tracked"]
        lines += [
            "",
            "## Tracking the clips (GT masks)",
            "",
            f"Each scene's {len(clips.tracker_image_seconds) // max(len(dataset.scene_ids()), 1)} frames in order, one "
            "`Tracker` per object (`update_depth`), the same with `track_many`, and `estimate_many` on the same "
            "frames.",
            "",
            f"- Tracker: **{_pct(100 * np.mean([f.correct for f in frames]))}** of {len(frames)} object-frames right "
            f"(view-fair: {_pct(100 * np.mean([f.view_fair for f in frames]))}); "
            + ", ".join(f"{k} {v}" for k, v in modes.items())
            + f"; a tracked object-frame {np.median(tracked_ms) if tracked_ms else float('nan'):.2f} ms at the median.",
            f"- Per image (all its objects), medians: `track_many` (the objects' trackers in parallel threads, "
            f"as `estimate_many` runs its objects) {np.median(clips.track_many_image_seconds) * 1000:.1f} ms, "
            f"the trackers one after another {np.median(clips.tracker_image_seconds) * 1000:.1f} ms, "
            f"`estimate_many` {np.median(clips.many_image_seconds) * 1000:.1f} ms: "
            f"**{np.median(clips.track_many_image_seconds) / np.median(clips.many_image_seconds):.2f}×** and "
            f"{np.median(clips.tracker_image_seconds) / np.median(clips.many_image_seconds):.2f}×; "
            f"`track_many`'s poses equal the lone trackers' on {sum(clips.track_many_same)} of "
            f"{len(clips.track_many_same)} object-frames; "
            f"`estimate_many` right on {_pct(100 * np.mean(clips.many_correct))}.",
        ]
        lines += [
            "",
            "| object | frames | right | view-fair | re-initialised |",
            "| --- | ---: | ---: | ---: | ---: |",
        ]
        for obj_id in sorted({f.obj_id for f in frames}):
            mine = [f for f in frames if f.obj_id == obj_id]
            lines.append(
                f"| {obj_id} {NAMES.get(obj_id, '')} | {len(mine)} | {_pct(100 * np.mean([f.correct for f in mine]))} "
                f"| {_pct(100 * np.mean([f.view_fair for f in mine]))} "
                f"| {sum(f.mode == 'reinitialised' for f in mine)} |"
            )
    return "\n".join(lines) + "\n"


def _hidden_views(results: list[TargetResult]) -> str:
    """Which targets' views hide a feature, and how their poses fared."""
    hidden = {(r.scene_id, r.im_id, r.obj_id) for r in results if r.view_hides_feature}
    if not hidden:
        return "No view hides a feature"
    objects = ", ".join(f"{obj_id} {NAMES.get(obj_id, '')}".strip() for obj_id in sorted({key[2] for key in hidden}))
    cells = [r for r in results if r.view_hides_feature]
    return (
        f"Views hiding a feature: {len(hidden)} targets ({objects}); over every method and mask, their poses are right "
        f"in {sum(r.correct for r in cells)} of {len(cells)} cells, flagged in {sum(r.flagged for r in cells)}, "
        f"neither in {sum(not r.view_fair_correct for r in cells)}"
    )


def _by_level(results: list[TargetResult], methods, levels):
    """(method, mask growth, its results) for each method and level, in order."""
    for method in methods:
        for grow in levels:
            yield method, grow, [r for r in results if r.method == method and r.grow_px == grow]


def real_objects_symmetric(results: list[TargetResult]) -> bool:
    """Whether these results' object was judged by ADD-S (its pose's symmetry)."""
    return any(r.pose is not None and r.pose.symmetry.symmetric for r in results)


def _write_csv(path: Path, results: list[TargetResult]) -> None:
    lines = [
        "method,grow_px,scene_id,im_id,obj_id,visib_fract,points,ms,correct,add_or_s_m,confidence,"
        "strict_threshold,searches,alternatives,alternative_correct,view_hides_feature,flagged,error"
    ]
    for r in results:
        p = r.pose
        lines.append(
            f"{r.method},{r.grow_px},{r.scene_id},{r.im_id},{r.obj_id},{r.visib_fract:.3f},{r.points},"
            f"{r.seconds * 1000:.2f},{int(r.correct)},{r.errors.add_or_s:.5f},"
            f"{p.confidence if p else float('nan'):.4f},{p.strict_threshold if p else float('nan'):.2f},"
            f"{p.searches if p else 0},{len(p.alternatives) if p else 0},{int(r.alternative_correct)},"
            f'{int(r.view_hides_feature)},{int(r.flagged)},"{r.error}"'
        )
    path.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
