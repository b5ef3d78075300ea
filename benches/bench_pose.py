"""Side-by-side pose benchmark: every method on the same synthetic depth views
of the shared YCB meshes, in one process.

    .venv/bin/python benches/bench_pose.py [--views 20] [--methods a,b] [--objects a,b]
                                           [--seed 0] [--occluders 0] [--out benches/RESULTS.md]

Methods: ``edgepose`` (picked up once ``edgepose.build_codebook`` and
``edgepose.estimate`` exist), ``open3d`` (FPFH + RANSAC + ICP), ``opencv-ppf``
(point-pair features + ICP) and ``opencv-ppf-fast`` (coarser PPF settings).
The peers need the ``baselines`` extra. Views are rendered once per object
from fixed seeds, so every method sees identical clouds.

Writes ``--out`` (markdown tables, the command, the machine), next to it
``<stem>_views.csv`` (every view's errors), ``<stem>_bop_<method>.csv`` (BOP
results) and two plots, and prints the tables.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import os
import platform
import shlex
import statistics
import sys
import time
import traceback
from pathlib import Path
from typing import Callable

import numpy as np

import edgepose
from edgepose.eval import BopRow, auc, write_bop_csv
from edgepose.eval.baselines import (
    EdgePoseMethod,
    Open3DBaseline,
    OpenCVPPFBaseline,
    PoseMethod,
    available_edgepose,
)
from edgepose.eval.benchmark import BenchObject as ObjectData
from edgepose.eval.benchmark import MethodRun, ViewResult, load_object, summarise
from edgepose.eval.benchmark import percent as _pct
from edgepose.eval.benchmark import run_method as run_views

REPO = Path(__file__).resolve().parents[1]
YCB = REPO.parent / "shared" / "data" / "ycb"

#: BOP object ids of the YCB-Video dataset (others get 100 + their index).
YCBV_OBJ_ID = {
    "master_chef_can": 1,
    "cracker_box": 2,
    "sugar_box": 3,
    "tomato_soup_can": 4,
    "mustard_bottle": 5,
    "tuna_fish_can": 6,
    "pudding_box": 7,
    "gelatin_box": 8,
    "potted_meat_can": 9,
    "banana": 10,
    "pitcher_base": 11,
    "bleach_cleanser": 12,
    "bowl": 13,
    "mug": 14,
    "power_drill": 15,
    "wood_block": 16,
    "scissors": 17,
    "large_marker": 18,
    "large_clamp": 19,
    "extra_large_clamp": 20,
    "foam_brick": 21,
}

#: Method name → (constructor, one-line description for the report).
METHODS: dict[str, tuple[Callable[[], PoseMethod], str]] = {
    "edgepose": (
        EdgePoseMethod,
        "codebook of 2,100 views, encoder + IRR + keypoint verification + ICP of the 3 best distinct candidates",
    ),
    "edgepose-norefine": (
        lambda: _named(EdgePoseMethod(refine=False), "edgepose-norefine"),
        "the same without ICP (estimate(..., refine=False)): the verified codebook pose alone",
    ),
    "open3d": (
        Open3DBaseline,
        "Open3D FPFH + RANSAC (mutual filter, edge-length 0.9 + distance checks, 1-voxel gate, ≤100k "
        "iterations, confidence 0.9999) + point-to-plane ICP on the mesh normals; voxel = diameter/25; "
        "2 OpenMP threads",
    ),
    "opencv-ppf": (
        OpenCVPPFBaseline,
        "OpenCV ppf_match_3d (Drost PPF): sampling step 0.07, distance step 0.05, scene sample step 1/20, "
        "scene distance 0.05; ICP on the 5 best-voted poses, lowest residual wins; model in mm",
    ),
    "opencv-ppf-fast": (
        lambda: _named(OpenCVPPFBaseline(relative_sampling_step=0.1, scene_sample_step=1 / 10), "opencv-ppf-fast"),
        "the same with sampling step 0.1, scene sample step 1/10 (trains in < 1 s)",
    ),
}

DEFAULT_VIEWS = 20
PROGRESS_EVERY = 5


def _named(method: PoseMethod, name: str) -> PoseMethod:
    method.name = name
    return method


def load_objects(names: list[str], views: int, seed: int, occluders: int) -> list[ObjectData]:
    """Meshes, metric points and ``views`` rendered views per object; view
    ``i`` of object ``k`` (in sorted order of all objects) has seed
    ``seed·100000 + k·1000 + i``, so a subset sees the same views."""
    every = sorted(p.stem for p in YCB.glob("*.ply"))
    objects = []
    for name in names:
        k = every.index(name)
        seeds = [seed * 100_000 + k * 1000 + i for i in range(views)]
        objects.append(load_object(YCB / f"{name}.ply", seeds, occluders=occluders))
    return objects


def run_method(name: str, objects: list[ObjectData]) -> MethodRun:
    """Prepare and run one method on every view of every object. One untimed
    warm-up estimate per object (on its first view) precedes the timed ones."""

    def progress(obj: ObjectData, i: int, done: list[ViewResult], prepare_s: float) -> None:
        if i % PROGRESS_EVERY == 0 or i == len(obj.clouds):
            print(
                f"  {name:<16} {obj.name:<16} {i:>3}/{len(obj.clouds)} views  "
                f"ADD-S {_pct(done, 'correct_add_s'):>5.1f}%  "
                f"median {statistics.median(v.latency_s for v in done) * 1e3:7.0f} ms  "
                f"(prepare {prepare_s:.2f} s)",
                flush=True,
            )

    method = METHODS[name][0]()
    method.name = name
    return run_views(method, objects, progress)


# ----------------------------------------------------------------- summaries


def tables(runs: list[MethodRun], objects: list[ObjectData]) -> tuple[str, str, str]:
    """(overall table, per-object table, name of the speed reference)."""
    summaries = {r.name: summarise(r.views) for r in runs}
    if "edgepose" in summaries:
        reference = "edgepose"
    else:
        reference = min(summaries, key=lambda n: summaries[n].median_ms)
    ref_ms = summaries[reference].median_ms
    overall = [
        "| method | views | ADD-S < 0.1d | ADD(-S) < 0.1d | AUC ADD-S | AUC ADD(-S) | median ms | p90 ms "
        f"| prepare s (median/object) | median latency / {reference} |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in runs:
        s = summaries[r.name]
        fails = f" ({s.failures} errors)" if s.failures else ""
        overall.append(
            f"| {r.name}{fails} | {s.views} | {s.add_s_pass:.1f} % | {s.add_or_s_pass:.1f} % | {s.auc_add_s:.1f} "
            f"| {s.auc_add_or_s:.1f} | {s.median_ms:.0f} | {s.p90_ms:.0f} "
            f"| {statistics.median(r.prepare_s.values()):.2f} | {s.median_ms / ref_ms:.2f}× |"
        )
    per_object = [
        "| object | sym. | method | ADD-S < 0.1d | ADD(-S) < 0.1d | AUC ADD-S | AUC ADD(-S) | median ms | p90 ms | prepare s |",
        "| --- | :---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for obj in objects:
        for r in runs:
            s = summarise([v for v in r.views if v.object == obj.name])
            per_object.append(
                f"| {obj.name} | {'yes' if obj.symmetric else 'no'} | {r.name} | {s.add_s_pass:.0f} % "
                f"| {s.add_or_s_pass:.0f} % | {s.auc_add_s:.1f} | {s.auc_add_or_s:.1f} | {s.median_ms:.0f} "
                f"| {s.p90_ms:.0f} | {r.prepare_s[obj.name]:.2f} |"
            )
    return "\n".join(overall), "\n".join(per_object), reference


# ----------------------------------------------------------------- outputs


def write_views_csv(path: Path, runs: list[MethodRun]) -> None:
    fields = [
        "method", "object", "view", "seed", "points", "latency_ms", "add_mm", "add_s_mm", "add_or_s_mm",
        "rotation_deg", "translation_mm", "diameter_mm", "correct_add_s", "correct_add_or_s", "score", "error",
    ]  # fmt: skip
    with path.open("w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(fields)
        for r in runs:
            for v in r.views:
                e = v.errors
                writer.writerow(
                    [
                        v.method, v.object, v.view, v.seed, v.points, f"{v.latency_s * 1e3:.3f}",
                        f"{e.add * 1e3:.3f}", f"{e.add_s * 1e3:.3f}", f"{e.add_or_s * 1e3:.3f}",
                        f"{e.rotation_deg:.3f}", f"{e.translation_mm:.3f}", f"{e.diameter * 1e3:.3f}",
                        int(e.correct_add_s), int(e.correct_add_or_s), f"{v.score:.6g}", v.error,
                    ]
                )  # fmt: skip


def write_bop(path: Path, run: MethodRun) -> None:
    """BOP rows: scene 0, image = the view's seed, YCB-Video object ids."""
    every = sorted(p.stem for p in YCB.glob("*.ply"))
    rows = [
        BopRow(
            scene_id=0,
            im_id=v.seed,
            obj_id=YCBV_OBJ_ID.get(v.object, 100 + every.index(v.object)),
            score=v.score,
            R=v.T_est[:3, :3],
            t=v.T_est[:3, 3],
            time=v.latency_s,
        )
        for v in run.views
    ]
    write_bop_csv(path, rows)


def plot(runs: list[MethodRun], scatter_path: Path, cdf_path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for c, r in zip(colours, runs):
        s = summarise(r.views)
        objects = sorted({v.object for v in r.views})
        for obj in objects:
            o = summarise([v for v in r.views if v.object == obj])
            ax.scatter(o.median_ms, o.add_s_pass, color=c, alpha=0.35, s=18)
        ax.scatter(s.median_ms, s.add_s_pass, color=c, s=90, edgecolor="black", label=f"{r.name} ADD-S", zorder=3)
        ax.scatter(
            s.median_ms, s.add_or_s_pass, facecolor="white", edgecolor=c, linewidth=2, s=90, marker="D",
            label=f"{r.name} ADD(-S)", zorder=3,
        )  # fmt: skip
        ax.errorbar(
            s.median_ms, s.add_s_pass, xerr=[[0], [s.p90_ms - s.median_ms]], color=c, capsize=3, zorder=2
        )
    ax.set_xscale("log")
    ax.xaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("estimate latency, ms (median; bar to p90; log scale)")
    ax.set_ylabel("correct poses (< 0.1 × diameter), % of views")
    ax.set_ylim(-2, 102)
    ax.set_title("Latency vs accuracy (large: all objects; small: ADD-S per object)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(scatter_path, dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    thresholds = np.geomspace(0.1, 100, 600)  # mm
    for c, r in zip(colours, runs):
        errors = np.array([v.errors.add_s for v in r.views]) * 1e3
        accuracy = [(errors <= t).mean() * 100 for t in thresholds]
        ax.plot(thresholds, accuracy, color=c, label=f"{r.name} (AUC 0–10 cm {100 * auc(errors / 1e3):.1f})")
    ax.set_xscale("log")
    ax.set_xlabel("ADD-S threshold, mm (log scale)")
    ax.set_ylabel("views with ADD-S ≤ threshold, %")
    ax.set_xlim(0.1, 100)
    ax.set_ylim(0, 101)
    ax.set_title("Cumulative distribution of ADD-S error")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(cdf_path, dpi=120)
    plt.close(fig)


def machine() -> str:
    model = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{os.cpu_count()} logical CPUs (nproc {len(os.sched_getaffinity(0))}), {model}, {platform.system()} {platform.machine()}"


def versions() -> str:
    found = [f"edgepose {edgepose.__version__}", f"numpy {np.__version__}", f"Python {platform.python_version()}"]
    for module, label in (("open3d", "open3d"), ("cv2", "opencv")):
        if module in sys.modules:
            found.append(f"{label} {sys.modules[module].__version__}")
    return ", ".join(found)


def command_line() -> str:
    script = Path(sys.argv[0]).resolve()
    try:
        script_text = str(script.relative_to(Path.cwd()))
    except ValueError:
        script_text = str(script)
    python = Path(sys.executable)
    try:
        python_text = str(python.relative_to(Path.cwd()))
    except ValueError:
        python_text = "python"
    return " ".join([python_text, script_text, *map(shlex.quote, sys.argv[1:])])


def write_markdown(
    path: Path,
    args: argparse.Namespace,
    runs: list[MethodRun],
    objects: list[ObjectData],
    load: tuple[tuple[float, ...], tuple[float, ...]],
    wall_s: float,
    extra_files: dict[str, Path],
) -> str:
    overall, per_object, reference = tables(runs, objects)
    symmetric = ", ".join(o.name for o in objects if o.symmetric) or "none"
    described = "\n".join(f"- **{r.name}**: {METHODS[r.name][1]}" for r in runs)
    text = f"""# Pose benchmark: edgepose and its peers

Generated by `benches/bench_pose.py`; do not edit by hand.

```bash
{command_line()}
```

- date: {datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")}
- machine: {machine()}
- load average (1/5/15 min) before: {" / ".join(f"{x:.2f}" for x in load[0])}, after: {" / ".join(f"{x:.2f}" for x in load[1])}
- software: {versions()}
- wall time of the whole run: {wall_s / 60:.1f} min

**Setup.** {len(objects)} YCB objects ({", ".join(o.name for o in objects)}), {args.views} views each,
rendered once by `edgepose.eval.render_view` (LINEMOD camera 640×480, object 0.45–0.9 m away,
uniformly random rotation, depth noise 1 mm, 1 mm quantisation, 2 % dropout, {args.occluders} occluders,
perfect segmentation) from seeds derived from `--seed {args.seed}`; every method gets the identical
clouds. A pose is correct when its error is below 0.1 × the object's diameter. ADD(-S) uses ADD-S for
the geometrically symmetric objects ({symmetric}) and ADD otherwise. AUC is the YCB-Video area under
the accuracy curve for thresholds 0–10 cm (× 100). Latency is the wall-clock time of one `estimate`
call (cloud in, 4×4 pose out) after one untimed warm-up call per object; "prepare" is the per-object
preparation (model sampling + features, PPF training, or codebook build). A method error counts as
a miss with the identity pose.

**Methods.**
{described}

## All objects

{overall}

Latency ratio: median latency of the method divided by that of **{reference}** (> 1 = slower).

## Per object

{per_object}

## Plots

![latency vs accuracy]({extra_files["scatter"].name})

![ADD-S CDF]({extra_files["cdf"].name})

## Files

- per-view errors: `{extra_files["views"].name}`
- BOP results per method: {", ".join(f"`{p.name}`" for k, p in extra_files.items() if k.startswith("bop:"))}

## Notes

- Timings come from a shared 2-core machine on which other work may run at the same time (see the
  load averages above); compare medians and ratios rather than single views. Each method uses both
  cores where it can (Open3D: OpenMP; OpenCV's PPF matcher is single-threaded in the pip wheels).
- Views are synthetic (clean geometry, perfect masks): absolute accuracies are upper bounds for
  real sensors; the comparison between methods is the point.
"""
    path.write_text(text)
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=DEFAULT_VIEWS, help="views per object")
    parser.add_argument(
        "--methods",
        default=None,
        help=f"comma-separated, from {', '.join(METHODS)} (default: edgepose when available, open3d, opencv-ppf)",
    )
    parser.add_argument("--objects", default=None, help="comma-separated YCB names (default: all five)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--occluders", type=int, default=0, help="occluding rectangles per view")
    parser.add_argument("--out", type=Path, default=REPO / "benches" / "RESULTS.md")
    args = parser.parse_args()

    if args.methods:
        methods = [m.strip() for m in args.methods.split(",") if m.strip()]
        unknown = [m for m in methods if m not in METHODS]
        if unknown:
            parser.error(f"unknown methods {unknown}; choose from {list(METHODS)}")
        if "edgepose" in methods and not available_edgepose():
            parser.error("this edgepose build has no build_codebook()/estimate() yet")
    else:
        methods = (["edgepose"] if available_edgepose() else []) + ["open3d", "opencv-ppf"]
    all_objects = sorted(p.stem for p in YCB.glob("*.ply"))
    names = [o.strip() for o in args.objects.split(",")] if args.objects else all_objects
    missing = [n for n in names if n not in all_objects]
    if missing:
        parser.error(f"no mesh for {missing} in {YCB}")

    load_before = os.getloadavg()
    started = time.perf_counter()
    print(f"rendering {args.views} views of {len(names)} objects ...", flush=True)
    objects = load_objects(names, args.views, args.seed, args.occluders)
    runs = []
    for name in methods:
        print(f"{name}:", flush=True)
        try:
            runs.append(run_method(name, objects))
        except ImportError as e:
            print(f"  skipped: {e} (install the 'baselines' extra)", flush=True)
        except Exception:
            traceback.print_exc()
            print(f"  skipped {name}: it failed outside estimate()", flush=True)
    if not runs:
        sys.exit("no method ran")

    out = args.out.resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    stem = out.stem
    files = {
        "views": out.with_name(f"{stem}_views.csv"),
        "scatter": out.with_name(f"{stem}_latency_vs_adds.png"),
        "cdf": out.with_name(f"{stem}_adds_cdf.png"),
    }
    write_views_csv(files["views"], runs)
    for r in runs:
        files[f"bop:{r.name}"] = out.with_name(f"{stem}_bop_{r.name}.csv")
        write_bop(files[f"bop:{r.name}"], r)
    plot(runs, files["scatter"], files["cdf"])
    wall = time.perf_counter() - started
    write_markdown(out, args, runs, objects, (load_before, os.getloadavg()), wall, files)
    overall, per_object, _ = tables(runs, objects)
    print()
    print(overall)
    print()
    print(per_object)
    print(f"\nwrote {out} and {', '.join(p.name for p in files.values())} ({wall / 60:.1f} min)")


if __name__ == "__main__":
    main()
