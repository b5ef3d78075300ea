"""Side-by-side pose benchmark: every method on the same synthetic depth views
of the shared YCB meshes, at every stress level, in one process.

    .venv/bin/python benches/bench_pose.py [--views 20] [--methods a,b] [--objects a,b]
                                           [--stress clean,visible70,...] [--peer-views N]
                                           [--seed 0] [--occluders 0] [--out benches/RESULTS.md]
    .venv/bin/python benches/bench_pose.py --tune [...]          # tuning objects -> benches/TUNING.md
    .venv/bin/python benches/bench_pose.py --tune --set second_search.pair_poses=0 --out /tmp/t/TUNING.md  # a setting
    .venv/bin/python benches/bench_pose.py --meshes DIR_OR_FILES [...]

Methods: ``edgepose`` (picked up once ``edgepose.build_codebook`` and
``edgepose.estimate`` exist), ``open3d`` (FPFH + RANSAC + ICP), ``opencv-ppf``
(point-pair features + ICP) and ``opencv-ppf-fast`` (coarser PPF settings).
The peers need the ``baselines`` extra.

Stress levels (``edgepose.eval.stress.STRESS_LEVELS``; default: all): views
of each object at each level are rendered once from fixed seeds (the same
seeds at every level, so one seed gives the same pose at every level with the
same distance range), and every method sees identical clouds. Each method
prepares each object once and runs it at every level. ``--peer-views N``
runs the peers (every method but edgepose*) on the first N views only.

Objects: the five YCB meshes (the reported figures), or ``--tune``: six CAD
parts from ``../shared/data/train_shapes/cad/`` scaled to diameters drawn in
8–25 cm, with seeds from 777000 on, written to ``benches/TUNING.md``: tune on
these, never on the YCB figures. ``--meshes`` takes other files or folders.

Writes ``--out`` (markdown tables, the command, the machine), next to it
``<stem>_views.csv`` (every view's errors and stress level),
``<stem>_bop_<method>.csv`` (BOP results; scene_id = the stress level's index
in STRESS_LEVELS), ``<stem>_stress.png`` (ADD(-S) per level) and two plots of
the first level, and prints the tables.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import datetime
import os
import platform
import shlex
import sys
import time
import traceback
from pathlib import Path

import edgepose
import numpy as np
from edgepose import report
from edgepose.catalog import CatalogError, find_meshes
from edgepose.confidence import TRUST_THRESHOLD
from edgepose.eval import YCBV_OBJ_ID, BopRow, auc, write_bop_csv
from edgepose.eval.baselines import EdgePoseMethod, PoseMethod, available_edgepose
from edgepose.eval.benchmark import BenchObject as ObjectData
from edgepose.eval.benchmark import MethodRun, ViewResult, load_object, summarise
from edgepose.eval.benchmark import run_method as run_views
from edgepose.eval.methods import METHODS, create_method
from edgepose.eval.stress import STRESS_LEVELS
from edgepose.settings import DEFAULT_SETTINGS, EstimateSettings, unknown_setting

REPO = Path(__file__).resolve().parents[1]
YCB = REPO.parent / "shared" / "data" / "ycb"
CAD = REPO.parent / "shared" / "data" / "train_shapes" / "cad"
#: Tuning objects (``--tune``): disjoint from the reported YCB objects.
TUNE_MESHES = ["bunny.ply", "fandisk.obj", "teapot.stl", "suzanne.ply", "idler_riser.STL", "busted.STL"]
#: Diameter range (metres) the tuning meshes are scaled to, one deterministic draw per mesh.
TUNE_DIAMETER = (0.08, 0.25)
#: Seeds of tuning views start here (the reported views use seed·100000 + k·1000 + i, k < 100).
TUNE_SEED_BASE = 777_000
#: Rendered views per object and stress level (``--views``).
RENDERED_VIEWS = 20


@dataclasses.dataclass
class Source:
    """One benchmark object before rendering: its mesh (metres) and seed block."""

    name: str
    mesh: object
    seed_base: int
    obj_id: int


def load_sources(args: argparse.Namespace, parser: argparse.ArgumentParser) -> list[Source]:
    """The objects to render: YCB (``--objects``), ``--tune`` or ``--meshes``.
    View ``i`` of object ``k`` has seed ``base + seed·100000 + k·1000 + i``
    (base 0, or TUNE_SEED_BASE for ``--tune``; k is the object's index in
    the sorted YCB list, TUNE_MESHES or the ``--meshes`` list), so a subset
    sees the same views."""
    from edgepose.model import load_model, read_mesh

    if args.tune or args.meshes:
        if args.tune:
            paths = [CAD / n for n in TUNE_MESHES]
            missing = [str(p) for p in paths if not p.is_file()]
            if missing:
                parser.error(f"no mesh file {missing}")
        else:
            try:
                paths = find_meshes(item.strip() for item in args.meshes.split(","))
            except CatalogError as e:
                parser.error(str(e))
        sources = []
        for k, path in enumerate(paths):
            if args.tune:  # mixed units: scale to a diameter drawn per mesh, deterministic
                mesh = read_mesh(path, scale=1.0)
                target = np.random.default_rng(TUNE_SEED_BASE + k).uniform(*TUNE_DIAMETER)
                mesh.apply_scale(1.0 / float(np.linalg.norm(mesh.extents)))  # about 1 m: within load_model's range
                mesh.apply_scale(target / load_model(mesh, scale=1.0).diameter)
            else:
                mesh = read_mesh(path, scale=None)
            base = (TUNE_SEED_BASE if args.tune else 0) + args.seed * 100_000 + k * 1000
            sources.append(Source(path.stem, mesh, base, 100 + k))
        return sources
    every = sorted(p.stem for p in YCB.glob("*.ply"))
    names = [o.strip() for o in args.objects.split(",")] if args.objects else every
    missing = [n for n in names if n not in every]
    if missing:
        parser.error(f"no mesh for {missing} in {YCB}")
    return [
        Source(
            n,
            read_mesh(YCB / f"{n}.ply", scale=None),
            args.seed * 100_000 + every.index(n) * 1000,
            YCBV_OBJ_ID.get(n, 100 + every.index(n)),
        )
        for n in names
    ]


class PrepareOnce:
    """A method that prepares each mesh once, whatever the number of stress
    levels it is then run at; records the preparation time per object."""

    def __init__(self, method: PoseMethod) -> None:
        self.method, self.name, self.mesh, self.prepare_s = method, method.name, None, {}

    def prepare(self, mesh: object) -> None:
        if mesh is not self.mesh:
            self.method.prepare(mesh)
            self.mesh = mesh

    @property
    def uses_frame(self) -> bool:
        return bool(getattr(self.method, "uses_frame", False))

    def estimate(self, cloud: np.ndarray, frame: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """``frame``: given by the benchmark only when ``uses_frame``."""
        if frame is None:
            return self.method.estimate(cloud)
        return self.method.estimate(cloud, frame=frame)  # type: ignore[call-arg]

    @property
    def last(self) -> object:
        return getattr(self.method, "last", None)


def is_peer(method: str) -> bool:
    """Every method but edgepose*: those ``--peer-views`` limits."""
    return not method.startswith("edgepose")


def peer_notes(methods: list[str], peer_views: int | None) -> dict[str, str]:
    """What the tables say after a peer's name when ``--peer-views`` limited its views."""
    if peer_views is None:
        return {}
    return {m: f" (first {peer_views} views per object)" for m in methods if is_peer(m)}


def run_all(
    sources: list[Source],
    levels: list[str],
    methods: list[str],
    views: int,
    peer_views: int | None,
    occluders: int,
    settings: EstimateSettings = DEFAULT_SETTINGS,
) -> tuple[dict[str, list[MethodRun]], dict[str, list[ObjectData]]]:
    """Every method on every view of every object at every level: (runs by
    level, in ``methods`` order; objects by level, without their clouds).
    The edgepose methods estimate with ``settings``."""
    instances = {}
    for name in methods:
        try:
            method = create_method(name)
            if isinstance(method, EdgePoseMethod):
                method.estimate_options["settings"] = settings
            instances[name] = PrepareOnce(method)
        except ImportError as e:
            print(f"{name}: skipped: {e} (install the 'baselines' extra)", flush=True)
    runs = {lv: {m: MethodRun(m, {}, []) for m in instances} for lv in levels}
    objects: dict[str, list[ObjectData]] = {lv: [] for lv in levels}
    failed: set[str] = set()
    for src in sources:
        for level in levels:
            t0 = time.perf_counter()
            seeds = [src.seed_base + i for i in range(views)]
            obj = load_object(
                src.mesh, seeds, name=src.name, occluders=occluders if level == "clean" else 0, stress=level
            )
            print(
                f"{src.name} @ {level}: {views} views rendered in {time.perf_counter() - t0:.1f} s "
                f"(visible {np.mean(obj.visible):.2f}, spill {np.mean(obj.spill):.2f})",
                flush=True,
            )
            for name, method in instances.items():
                if name in failed:
                    continue
                subset = obj
                if peer_views is not None and is_peer(name):
                    n = min(peer_views, views)
                    subset = dataclasses.replace(
                        obj,
                        seeds=obj.seeds[:n],
                        clouds=obj.clouds[:n],
                        poses=obj.poses[:n],
                        visible=obj.visible[:n],
                        spill=obj.spill[:n],
                        frames=obj.frames[:n],
                    )
                try:
                    t0 = time.perf_counter()
                    method.prepare(src.mesh)  # timed here once per object; a no-op at later levels
                    method.prepare_s.setdefault(src.name, time.perf_counter() - t0)
                    run = run_views(method, [subset])
                except Exception:
                    traceback.print_exc()
                    print(f"  skipped {name}: it failed outside estimate()", flush=True)
                    failed.add(name)
                    continue
                s = summarise(run.views)
                print(
                    f"  {name:<18} ADD(-S) {s.add_or_s_pass:5.1f}%  ADD-S {s.add_s_pass:5.1f}%  "
                    f"median {s.median_ms:7.0f} ms  ({s.views} views)",
                    flush=True,
                )
                runs[level][name].views += run.views
                runs[level][name].prepare_s[src.name] = method.prepare_s[src.name]
            objects[level].append(dataclasses.replace(obj, clouds=[], frames=[]))
    kept = {lv: [r for m, r in by_method.items() if m not in failed and r.views] for lv, by_method in runs.items()}
    return kept, objects


# ----------------------------------------------------------------- outputs


def write_views_csv(path: Path, runs: dict[str, list[MethodRun]], objects: dict[str, list[ObjectData]]) -> None:
    fields = [
        "stress",
        "method",
        "object",
        "view",
        "seed",
        "visible_fraction",
        "spill_fraction",
        "points",
        "latency_ms",
        "add_mm",
        "add_s_mm",
        "add_or_s_mm",
        "rotation_deg",
        "translation_mm",
        "diameter_mm",
        "correct_add_s",
        "correct_add_or_s",
        "score",
        "confidence",
        "strict_threshold",
        "alternatives",
        "alternative_correct",
        "error",
    ]
    with path.open("w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(fields)
        for level, by_level in runs.items():
            scenes = {o.name: o for o in objects[level]}
            for r in by_level:
                for v in r.views:
                    e, o = v.errors, scenes[v.object]
                    writer.writerow(
                        [
                            level,
                            v.method,
                            v.object,
                            v.view,
                            v.seed,
                            f"{o.visible[v.view]:.4f}",
                            f"{o.spill[v.view]:.4f}",
                            v.points,
                            f"{v.latency_s * 1e3:.3f}",
                            f"{e.add * 1e3:.3f}",
                            f"{e.add_s * 1e3:.3f}",
                            f"{e.add_or_s * 1e3:.3f}",
                            f"{e.rotation_deg:.3f}",
                            f"{e.translation_mm:.3f}",
                            f"{e.diameter * 1e3:.3f}",
                            int(e.correct_add_s),
                            int(e.correct_add_or_s),
                            f"{v.score:.6g}",
                            f"{v.confidence:.4f}",
                            f"{v.strict_threshold:.2f}",
                            v.alternatives,
                            int(v.alternative_correct),
                            v.error,
                        ]
                    )


def write_bop(path: Path, runs: dict[str, MethodRun], obj_ids: dict[str, int]) -> None:
    """BOP rows of one method: scene = the stress level's index in
    STRESS_LEVELS, image = the view's seed, YCB-Video object ids (others 100 + k)."""
    order = list(STRESS_LEVELS)
    rows = [
        BopRow(
            scene_id=order.index(level),
            im_id=v.seed,
            obj_id=obj_ids[v.object],
            score=v.score,
            R=v.T_est[:3, :3],
            t=v.T_est[:3, 3],
            time=v.latency_s,
        )
        for level, run in runs.items()
        for v in run.views
    ]
    write_bop_csv(path, rows)


def plot_stress(runs: dict[str, list[MethodRun]], methods: list[str], path: Path) -> None:
    """ADD(-S) per stress level, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    levels = list(runs)
    fig, ax = plt.subplots(figsize=(max(6.4, 0.75 * len(levels) + 2), 4.4))
    for m in methods:
        y = [next((summarise(r.views).add_or_s_pass for r in runs[lv] if r.name == m), np.nan) for lv in levels]
        ax.plot(range(len(levels)), y, marker="o", label=m)
    ax.set_xticks(range(len(levels)), levels, rotation=30, ha="right")
    ax.set_xlabel("stress level")
    ax.set_ylabel("ADD(-S) < 0.1 × diameter, % of views")
    ax.set_ylim(-2, 102)
    ax.set_title("Accuracy under stress")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def confidence_groups(runs: dict[str, list[MethodRun]], method: str = "edgepose") -> dict[str, list[ViewResult]]:
    """``method``'s views: clean, all stressed levels pooled, then each level."""
    by_level = {lv: [v for r in rs if r.name == method for v in r.views] for lv, rs in runs.items()}
    groups = {"clean": by_level.get("clean", [])}
    groups["stressed (all other levels)"] = [v for lv, vs in by_level.items() if lv != "clean" for v in vs]
    groups.update({f"`{lv}`": vs for lv, vs in by_level.items()})
    return {k: v for k, v in groups.items() if v}


def plot_reliability(runs: dict[str, list[MethodRun]], path: Path) -> bool:
    """edgepose's reliability diagram (clean and stressed views); False when it did not run."""
    from edgepose.viz import save_reliability_png

    groups = {k: v for k, v in confidence_groups(runs).items() if not k.startswith("`")}
    if not groups:
        return False
    pairs = {
        k: (np.array([v.confidence for v in vs]), np.array([v.errors.correct_add_or_s for v in vs]))
        for k, vs in groups.items()
    }
    save_reliability_png(path, pairs)
    return True


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
            s.median_ms,
            s.add_or_s_pass,
            facecolor="white",
            edgecolor=c,
            linewidth=2,
            s=90,
            marker="D",
            label=f"{r.name} ADD(-S)",
            zorder=3,
        )
        ax.errorbar(s.median_ms, s.add_s_pass, xerr=[[0], [s.p90_ms - s.median_ms]], color=c, capsize=3, zorder=2)
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
    cpus = f"{os.cpu_count()} logical CPUs (nproc {len(os.sched_getaffinity(0))})"
    return f"{cpus}, {model}, {platform.system()} {platform.machine()}"


def versions() -> str:
    found = [f"edgepose {edgepose.__version__}", f"numpy {np.__version__}", f"Python {platform.python_version()}"]
    for module, label in (("open3d", "open3d"), ("cv2", "opencv")):
        if module in sys.modules:
            found.append(f"{label} {sys.modules[module].__version__}")
    return ", ".join(found)


def estimate_settings(settings: EstimateSettings) -> str:
    """Every field of ``settings``, for the report (changed ones in bold)."""
    default = DEFAULT_SETTINGS.flat()
    return ", ".join(
        f"`{k}={v}`" if v == default[k] else f"**`{k}={v}`** (default {default[k]})" for k, v in settings.flat().items()
    )


def settings_from(changes: list[str]) -> EstimateSettings:
    """The default EstimateSettings with ``FIELD=VALUE`` changes (ValueError
    naming an unknown field or a value of the wrong type)."""
    fields = DEFAULT_SETTINGS.flat()
    parsed: dict[str, object] = {}
    for change in changes:
        field_name, _, text = change.partition("=")
        if field_name not in fields or not text:
            why = f"{unknown_setting(field_name)}; " if field_name not in fields else ""
            raise ValueError(f"--set {change!r}: {why}expected FIELD=VALUE with FIELD one of {', '.join(fields)}")
        kind = type(fields[field_name])
        try:
            if kind is bool:
                parsed[field_name] = {"True": True, "False": False}[text]
            elif kind is tuple:  # numbers, comma-separated
                parsed[field_name] = tuple(float(x) for x in text.split(","))
            else:
                parsed[field_name] = kind(text)
        except (KeyError, ValueError):
            raise ValueError(f"--set {change!r}: {field_name} takes a {kind.__name__}") from None
    return DEFAULT_SETTINGS.with_(**parsed)


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
    runs: dict[str, list[MethodRun]],
    objects: dict[str, list[ObjectData]],
    methods: list[str],
    load: tuple[tuple[float, ...], tuple[float, ...]],
    wall_s: float,
    extra_files: dict[str, Path],
) -> str:
    first = next(iter(runs))
    reference = report.speed_reference(runs[first])
    overall = report.overall_table(runs[first], reference)
    per_object = report.per_object_table(runs[first], objects[first])
    objs = objects[first]
    symmetric = ", ".join(o.name for o in objs if o.symmetric) or "none"
    described = "\n".join(f"- **{m}**: {METHODS[m].description}" for m in methods)
    levels = "\n".join(f"- `{lv}`: {STRESS_LEVELS[lv].description}" for lv in runs)
    notes = peer_notes(methods, args.peer_views)
    per_level = "\n\n".join(f"### Stress level `{lv}`\n\n{report.level_table(rs, notes)}" for lv, rs in runs.items())
    if args.tune:
        kind = (
            f"{len(objs)} tuning objects (CAD parts from `../shared/data/train_shapes/cad/`, disjoint from the "
            f"reported YCB objects, each scaled to a diameter drawn in {TUNE_DIAMETER[0] * 100:.0f}–"
            f"{TUNE_DIAMETER[1] * 100:.0f} cm: "
            + ", ".join(f"{o.name} {o.diameter * 100:.1f} cm" for o in objs)
            + f"); seeds from {TUNE_SEED_BASE}"
        )
    elif args.meshes:
        kind = f"{len(objs)} objects from `--meshes` ({', '.join(o.name for o in objs)})"
    else:
        kind = f"{len(objs)} YCB objects ({', '.join(o.name for o in objs)})"
    peers = (
        f" Peers (methods other than edgepose*) ran on the first {args.peer_views} views of each object only "
        "(the `views` columns say how many)."
        if args.peer_views is not None
        else ""
    )
    title = "Tuning benchmark (not the reported figures)" if args.tune else "Pose benchmark: edgepose and its peers"
    load_before, load_after = (" / ".join(f"{x:.2f}" for x in averages) for averages in load)
    scene_ids = ", ".join(f"{i} {n}" for i, n in enumerate(STRESS_LEVELS))
    text = f"""# {title}

Generated by `benches/bench_pose.py`; do not edit by hand.

```bash
{command_line()}
```

- date: {datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")}
- machine: {machine()}
- load average (1/5/15 min) before: {load_before}, after: {load_after}
- software: {versions()}
- wall time of the whole run: {wall_s / 60:.1f} min
- edgepose settings (`edgepose.settings.EstimateSettings`; distances × diameter): {estimate_settings(args.settings)}
- `cloud_from_depth` defaults: no depth-jump filter, no mask erosion

**Setup.** {kind}, {args.views} views each per stress level, from seeds derived from `--seed {args.seed}`
(the same seeds at every level: one seed is one pose at every level with the same distance range, on
`on_table` at the same place turned to rest on the table); every
method gets the identical clouds.{peers} Level `clean` is `edgepose.eval.render_view` (LINEMOD camera
640×480, object 0.45–0.9 m away, uniformly random rotation, depth noise 1 mm, 1 mm quantisation, 2 %
dropout, {args.occluders} occluders, perfect segmentation, no background), identical to earlier runs; the
other levels are `edgepose.eval.scenes.render_scene` scenes: the object in front of a support plane
(2–6 cm behind it, tilted up to 30°), or at `on_table` resting on it (a table seen from 30–70° above,
the object in one of its stable poses), beside 1–3 boxes/cylinders, with the level's occluder, sensor
noise and detector mask:

{levels}

A pose is correct when its error is below 0.1 × the object's diameter. ADD(-S) uses ADD-S for the
geometrically symmetric objects ({symmetric}) and ADD otherwise. AUC is the YCB-Video area under the
accuracy curve for thresholds 0–10 cm (× 100). Latency is the wall-clock time of one `estimate` call
(cloud in, 4×4 pose out) after one untimed warm-up call per object and level; "prepare" is the
per-object preparation (model sampling + features, PPF training, or codebook build), done once per
object for all levels. A method error counts as a miss with the identity pose.

**Methods.**
{described}

## Stress summary: ADD(-S) < 0.1d per level

Visible fraction: visible object pixels / the object's pixels alone (occlusion); spill fraction: cloud
points off the object / points on it (mask spill). Parentheses: views.

{report.stress_table(runs, objects, methods)}

![ADD(-S) per stress level]({extra_files["stress"].name})

## Per stress level

{per_level}

## Stress level `{first}`: all objects

{overall}

Latency ratio: median latency of the method divided by that of **{reference}** (> 1 = slower).

## Stress level `{first}`: per object

{per_object}

{confidence_section(runs, extra_files)}

## Plots (stress level `{first}`)

![latency vs accuracy]({extra_files["scatter"].name})

![ADD-S CDF]({extra_files["cdf"].name})

## Files

- per-view errors with their stress level: `{extra_files["views"].name}`
- BOP results per method (scene_id = the stress level's index in `STRESS_LEVELS`: {scene_ids}):
  {", ".join(f"`{p.name}`" for k, p in extra_files.items() if k.startswith("bop:"))}

## Notes

- Timings come from a shared 2-core machine on which other work may run at the same time (see the
  load averages above); compare medians and ratios rather than single views. Each method uses both
  cores where it can (Open3D: OpenMP; OpenCV's PPF matcher is single-threaded in the pip wheels).
- Views are synthetic: even the stressed levels are idealised (exact geometry, simple noise models);
  absolute accuracies are upper bounds for real sensors; the comparison between methods is the point.
"""
    path.write_text(text)
    return text


def confidence_section(runs: dict[str, list[MethodRun]], extra_files: dict[str, Path]) -> str:
    groups = confidence_groups(runs)
    if not groups or "reliability" not in extra_files:
        return ""
    framed = confidence_groups(runs, "edgepose-frame")
    with_frame = (
        f"""

Given each view's depth frame too (`edgepose-frame`: `estimate(cloud, codebook, depth=, K=)`), with
the model of the manifest's `confidence.with_scene` where it has one:

{report.confidence_table(framed)}"""
        if framed
        else ""
    )
    alternatives_with_frame = (
        f"\n\nGiven each view's depth frame too (`edgepose-frame`):\n\n{report.alternatives_table(framed)}"
        if framed
        else ""
    )
    return f"""## Confidence (edgepose)

`Pose.confidence` is the probability that the pose is correct (ADD(-S) < 0.1 × diameter), from a
logistic model over the scoring terms of `estimate`, each a piecewise-linear curve, fitted on training
shapes (`python -m export.confidence`; never these objects).
Default rule: trust a pose at confidence ≥ {TRUST_THRESHOLD}. Strict rule: trust it at confidence ≥
`Pose.strict_threshold`, the lowest threshold that let at most 5 % of the wrong poses through on the fitting
data's cross-validated stressed views (recorded with each model; none of these objects).
AUROC: chance that a correct pose scores above a wrong one; ECE: expected calibration error (10 bins).

{report.confidence_table(groups)}{with_frame}

![reliability diagram]({extra_files["reliability"].name})

### Alternatives

`Pose.alternatives`: other poses that explain the view nearly as well (within
`EstimateSettings.alternatives.within` of the pose's explained share net of violations), each more than
0.1 × diameter from the pose and from each other: where the object may be instead. Of the wrong poses,
how many had the truth among them; of the right poses, how many came with any (a robot that looks
again whenever there are alternatives looks again this often when it need not).

{report.alternatives_table(groups)}{alternatives_with_frame}"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=RENDERED_VIEWS, help="views per object and stress level")
    parser.add_argument(
        "--methods",
        default=None,
        help=f"comma-separated, from {', '.join(METHODS)} (default: edgepose when available, open3d, opencv-ppf)",
    )
    parser.add_argument("--objects", default=None, help="comma-separated YCB names (default: all five)")
    parser.add_argument(
        "--stress", default=",".join(STRESS_LEVELS), help="comma-separated stress levels (default: all)"
    )
    parser.add_argument(
        "--peer-views", type=int, default=None, help="views per object for the peers (default: --views)"
    )
    parser.add_argument("--tune", action="store_true", help="tuning objects (CAD parts, not YCB) -> benches/TUNING.md")
    parser.add_argument("--meshes", default=None, help="comma-separated mesh files or folders instead of YCB")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--occluders", type=int, default=0, help="occluding rectangles per view (clean level only)")
    parser.add_argument("--out", type=Path, default=None, help="default benches/RESULTS.md (--tune: benches/TUNING.md)")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="change an EstimateSettings field, a stage's by its dotted name (refine.icp_iterations=20), for the "
        "edgepose methods (repeatable; never for RESULTS.md)",
    )
    args = parser.parse_args()
    try:
        args.settings = settings_from(args.set)
    except ValueError as e:
        parser.error(str(e))

    if args.methods:
        methods = [m.strip() for m in args.methods.split(",") if m.strip()]
        unknown = [m for m in methods if m not in METHODS]
        if unknown:
            parser.error(f"unknown methods {unknown}; choose from {', '.join(METHODS)}")
        if "edgepose" in methods and not available_edgepose():
            parser.error("this edgepose build has no build_codebook()/estimate() yet")
    else:
        methods = (["edgepose"] if available_edgepose() else []) + ["open3d", "opencv-ppf"]
    levels = [lv.strip() for lv in args.stress.split(",") if lv.strip()]
    unknown = [lv for lv in levels if lv not in STRESS_LEVELS]
    if unknown or not levels:
        parser.error(f"unknown stress levels {unknown}; choose from {list(STRESS_LEVELS)}")
    if args.tune and (args.meshes or args.objects):
        parser.error("--tune picks its own objects: no --meshes or --objects with it")
    results = REPO / "benches" / "RESULTS.md"
    out = (args.out or (REPO / "benches" / ("TUNING.md" if args.tune else "RESULTS.md"))).resolve()
    if (args.tune or args.meshes or args.set) and out == results.resolve():
        parser.error(f"--tune/--meshes/--set never write the reported figures ({results}); choose another --out")
    sources = load_sources(args, parser)

    load_before = os.getloadavg()
    started = time.perf_counter()
    print(
        f"{args.views} views of {len(sources)} objects at {len(levels)} stress levels: {', '.join(levels)}", flush=True
    )
    runs, objects = run_all(sources, levels, methods, args.views, args.peer_views, args.occluders, args.settings)
    ran = [m for m in methods if any(r.name == m for rs in runs.values() for r in rs)]
    if not ran:
        sys.exit("no method ran")

    out.parent.mkdir(parents=True, exist_ok=True)
    stem = out.stem
    files = {
        "views": out.with_name(f"{stem}_views.csv"),
        "stress": out.with_name(f"{stem}_stress.png"),
        "scatter": out.with_name(f"{stem}_latency_vs_adds.png"),
        "cdf": out.with_name(f"{stem}_adds_cdf.png"),
    }
    write_views_csv(files["views"], runs, objects)
    obj_ids = {s.name: s.obj_id for s in sources}
    for m in ran:
        files[f"bop:{m}"] = out.with_name(f"{stem}_bop_{m}.csv")
        write_bop(files[f"bop:{m}"], {lv: r for lv, rs in runs.items() for r in rs if r.name == m}, obj_ids)
    plot_stress(runs, ran, files["stress"])
    files["reliability"] = out.with_name(f"{stem}_reliability.png")
    if not plot_reliability(runs, files["reliability"]):
        del files["reliability"]
    first = next(iter(runs))
    plot(runs[first], files["scatter"], files["cdf"])
    wall = time.perf_counter() - started
    write_markdown(out, args, runs, objects, ran, (load_before, os.getloadavg()), wall, files)
    print()
    print(report.stress_table(runs, objects, ran))
    for level, rs in runs.items():
        print(f"\n{level}:\n{report.level_table(rs, peer_notes(ran, args.peer_views))}")
    print(f"\nconfidence:\n{report.confidence_table(confidence_groups(runs))}")
    print(f"\nwrote {out} and {', '.join(p.name for p in files.values())} ({wall / 60:.1f} min)")


if __name__ == "__main__":
    main()
