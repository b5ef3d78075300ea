"""How results are shown: the command line's JSON and rich tables, and the
benchmark's markdown tables.

Units as printed: millimetres for errors and distances (``_mm``), metres in
the JSON pose (``matrix``, ``fit``), milliseconds for latencies, seconds for
preparation and timings; accuracies are percent of views correct at
0.1 × diameter, AUCs × 100. Poses are ``T_cam_obj``. rich is imported only
by the functions that return rich tables.
"""

from __future__ import annotations

import json
import statistics
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from edgepose.confidence import TRUST_THRESHOLD
from edgepose.eval.benchmark import BenchObject, MethodRun, ViewResult, summarise, summarise_confidence
from edgepose.eval.metrics import CORRECT_FRACTION, PoseErrors

if TYPE_CHECKING:
    from rich.console import Console
    from rich.table import Table

    from edgepose.catalog import ObjectResult
    from edgepose.eval.render import RenderedView
    from edgepose.pose import Pose

#: Column alignments: markdown separators and rich ``justify`` values.
_MARKDOWN_ALIGN = {"l": "---", "r": "---:", "c": ":---:"}
_RICH_ALIGN = {"l": "left", "r": "right", "c": "center"}


def markdown_table(header: Sequence[str], align: str, rows: Iterable[Sequence[str]]) -> str:
    """A markdown table; ``align`` has one letter per column: l, r or c."""
    lines = [header, [_MARKDOWN_ALIGN[a] for a in align], *rows]
    return "\n".join("| " + " | ".join(cells) + " |" for cells in lines)


def rich_table(title: str, header: Sequence[str], align: str, rows: Iterable[Sequence[str]]) -> Table:
    """A rich table (cells may hold rich markup); ``align`` as :func:`markdown_table`."""
    from rich.table import Table

    table = Table(title=title)
    for column, a in zip(header, align):
        table.add_column(column, justify=_RICH_ALIGN[a])  # type: ignore[arg-type]
    for row in rows:
        table.add_row(*row)
    return table


def version_text() -> str:
    """``edgepose --version``: versions of edgepose, its compiled core, its
    networks (loading and checking them) and onnxruntime."""
    import onnxruntime

    import edgepose
    from edgepose import _core
    from edgepose.encoder import MODELS_DIR, Encoder

    encoder = Encoder()
    manifest = json.loads((MODELS_DIR / "manifest.json").read_text())
    files = manifest["files"]
    return "\n".join(
        [
            f"edgepose {edgepose.__version__}",
            f"core        {_core.__name__} (compiled core loaded from {Path(_core.__file__).name})",
            f"networks    encoder.onnx {files['encoder.onnx'][:12]}, irr.onnx {files['irr.onnx'][:12]} "
            f"({manifest['parameters']['total']:,} parameters, sha256 checked, code size {encoder.code_size})",
            f"codes       fingerprint {encoder.fingerprint[:12]} (what a codebook must record)",
            f"onnxruntime {onnxruntime.__version__}",
        ]
    )


class Step(Protocol):
    """What a progress bar shows of a finished step (an :class:`ObjectResult`, an image…)."""

    name: str
    status: str


@contextmanager
def progress(console: Console, verb: str, total: int) -> Iterator[Callable[[Step], None]]:
    """A transient progress bar of ``total`` steps (objects, images); yields
    the callback that advances it as each step's result arrives."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    bar = Progress(
        TextColumn("{task.description:<28}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    )
    with bar:
        task = bar.add_task(verb, total=total)

        def on_result(result: Step) -> None:
            bar.update(task, description=f"{verb}: {result.name} {result.status}")
            bar.advance(task)

        yield on_result


# ----------------------------------------------------------------- one pose


def pose_json(pose: Pose, points: int) -> dict[str, Any]:
    """``edgepose estimate``'s fields of a pose found in a cloud of ``points`` points."""
    return {
        "matrix": pose.matrix.tolist(),
        "confidence": pose.confidence if np.isfinite(pose.confidence) else None,
        "trusted": bool(pose.confidence >= TRUST_THRESHOLD),
        "strict_threshold": pose.strict_threshold if np.isfinite(pose.strict_threshold) else None,
        "trusted_strict": bool(pose.confidence >= pose.strict_threshold),
        "symmetry": pose.symmetry.describe(),
        "alternatives": [{"matrix": a.matrix.tolist(), "margin": a.margin} for a in pose.alternatives],
        "score": pose.score,
        "fit": pose.fit,
        "view": pose.view,
        "refined": pose.refined,
        "inlier_fraction": pose.inlier_fraction,
        "free_space_violation": pose.free_space_violation,
        "points": int(points),
        "kept_points": pose.kept_points,
        "searches": pose.searches,
        "evidence": pose.evidence,
        "timings": pose.timings,
    }


def errors_json(e: PoseErrors) -> dict[str, Any]:
    """A pose's errors against the truth, millimetres and degrees."""
    return {
        "rotation_deg": e.rotation_deg,
        "translation_mm": e.translation_mm,
        "add_mm": e.add * 1000,
        "add_s_mm": e.add_s * 1000,
        "diameter_mm": e.diameter * 1000,
        "correct_add": e.add < CORRECT_FRACTION * e.diameter,
        "correct_add_s": e.correct_add_s,
    }


def json_text(result: dict[str, Any]) -> str:
    """JSON with one line per field and per matrix row."""
    fields = []
    for key, value in result.items():
        if key == "matrix":
            rows = ",\n".join("    " + json.dumps(row) for row in value)
            fields.append(f'  "matrix": [\n{rows}\n  ]')
        else:
            fields.append(f"  {json.dumps(key)}: {json.dumps(value)}")
    return "{\n" + ",\n".join(fields) + "\n}"


def estimate_caption(cloud_name: str, points: int, pose: Pose, e: PoseErrors | None) -> list[str]:
    """The lines written on ``edgepose estimate --show``'s picture."""
    lines = [
        f"{cloud_name}: {points} points, estimate {pose.timings['total'] * 1000:.1f} ms, "
        f"confidence {pose.confidence:.2f}, fit {pose.fit * 1000:.1f} mm, score {pose.score:.3f}"
    ]
    if e is not None:
        lines.append(
            f"ADD {e.add * 1000:.1f} mm, ADD-S {e.add_s * 1000:.1f} mm (threshold 0.1 x diameter = "
            f"{e.diameter * 100:.1f} mm); rotation {e.rotation_deg:.2f}°, translation {e.translation_mm:.1f} mm"
        )
    return lines


def alternatives_text(pose: Pose) -> str:
    """How many other poses explain the view nearly as well, and by how much less."""
    if not pose.alternatives:
        return "none"
    margins = ", ".join(f"{a.margin:.3f}" for a in pose.alternatives)
    return f"{len(pose.alternatives)} (explaining less by {margins})"


def trust_text(confidence: float, strict_threshold: float = float("nan")) -> str:
    """What the default rule, and the strict one when known, say about a confidence."""
    if confidence != confidence:  # NaN
        return "no confidence model shipped with these networks"

    def verdict(threshold: float) -> str:
        return "trusted" if confidence >= threshold else "doubtful"

    text = f"{verdict(TRUST_THRESHOLD)}: the rule is >= {TRUST_THRESHOLD}"
    if strict_threshold == strict_threshold:
        text += f"; {verdict(strict_threshold)} by the strict rule, >= {strict_threshold:.2f}"
    return text


def matrix_text(matrix: np.ndarray, indent: int = 12) -> str:
    """A 4×4 matrix, one indented row per line."""
    return "\n".join(" " * indent + "  ".join(f"{x:8.4f}" for x in row) for row in matrix)


def demo_text(
    name: str, origin: str, view: RenderedView, seed: int, pose: Pose, e: PoseErrors, symmetric: bool
) -> tuple[str, list[str]]:
    """``edgepose demo``'s report (rich markup) and the caption of its picture."""
    metric = "ADD-S" if symmetric else "ADD"
    threshold_mm = e.diameter * 100
    verdict = "[green]correct[/green]" if e.correct_add_or_s else "[red]WRONG[/red]"
    stages = ", ".join(f"{k} {v * 1000:.2f}" for k, v in pose.timings.items() if k != "total")
    text = [
        f"[bold]object[/bold]      {name} ({e.diameter * 1000:.0f} mm across): {origin}",
        f"[bold]rendered[/bold]    {len(view.cloud)} points, {np.linalg.norm(view.T_cam_obj[:3, 3]):.2f} m away "
        f"(640×480 depth, 1 mm noise, seed {seed}; --seed {seed} repeats it)",
        "[bold]estimated[/bold]   T_cam_obj =\n" + matrix_text(pose.matrix),
        "[bold]true[/bold]        T_cam_obj =\n" + matrix_text(view.T_cam_obj),
        f"[bold]errors[/bold]      rotation {e.rotation_deg:.2f}°, translation {e.translation_mm:.1f} mm, "
        f"{metric} {e.add_or_s * 1000:.1f} mm ({verdict} at 0.1 × diameter = {threshold_mm:.1f} mm)",
        f"[bold]confidence[/bold]  {pose.confidence:.2f} ({trust_text(pose.confidence, pose.strict_threshold)}); "
        f"symmetries: {pose.symmetry.describe()}; alternatives: {alternatives_text(pose)}",
        f"[bold]timings[/bold]     {pose.timings['total'] * 1000:.1f} ms in all ({stages} ms)",
    ]
    caption = [
        f"edgepose demo: {name}, seed {seed}, {len(view.cloud)} points, estimate {pose.timings['total'] * 1000:.1f} ms",
        f"{metric} {e.add_or_s * 1000:.1f} mm: {'correct' if e.correct_add_or_s else 'WRONG'} "
        f"(threshold 0.1 x diameter = {threshold_mm:.1f} mm)",
        f"rotation error {e.rotation_deg:.2f}°, translation error {e.translation_mm:.1f} mm, "
        f"confidence {pose.confidence:.2f}",
    ]
    return "\n".join(text), caption


# ----------------------------------------------------------------- catalogues


def build_table(results: list[ObjectResult], out_dir: str | Path) -> Table:
    """``edgepose build``'s table: one row per object (sizes in MB, times in s)."""
    rows = []
    for r in results:
        if r.failed:
            rows.append([r.name, "[red]failed[/red]", "", "", "", ""])
        else:
            seconds = f"{r.seconds:.2f}" if r.status == "built" else ""
            rows.append([r.name, r.status, str(r.views), seconds, f"{r.bytes / 1e6:.2f}", Path(r.codebook).name])
    header = ["object", "status", "views", "build s", "size MB", "file"]
    return rich_table(f"codebooks in {out_dir}/", header, "llrrrl", rows)


def build_summary(results: list[ObjectResult], wall_s: float, on_ray: bool) -> str:
    """One line: objects built, skipped and failed, and the throughput."""
    counts = {status: sum(r.status == status for r in results) for status in ("built", "skipped", "failed")}
    return (
        f"{counts['built']} built, {counts['skipped']} up to date (skipped), {counts['failed']} failed; "
        f"{len(results)} objects in {wall_s:.1f} s ({60 * len(results) / max(wall_s, 1e-9):.1f} objects/min"
        f"{', Ray' if on_ray else ''})"
    )


def eval_table(runs: list[MethodRun], objects: list[str], symmetric: set[str], title: str) -> Table:
    """``edgepose eval``'s table: each object × method, then each method over
    every object ("all"; prepare s is then the median object's)."""
    rows = []
    for obj in [*objects, None]:
        for run in runs:
            s = summarise([v for v in run.views if obj is None or v.object == obj])
            prepare = run.prepare_s[obj] if obj is not None else sorted(run.prepare_s.values())[len(run.prepare_s) // 2]
            rows.append(
                [
                    obj if obj is not None else "[bold]all[/bold]",
                    ("yes" if obj in symmetric else "no") if obj is not None else "",
                    run.name,
                    f"{s.add_s_pass:.0f} %",
                    f"{s.add_or_s_pass:.0f} %",
                    f"{s.auc_add_s:.1f}",
                    f"{s.auc_add_or_s:.1f}",
                    f"{s.median_ms:.1f}",
                    f"{prepare:.2f}",
                ]
            )
    header = [
        "object",
        "sym.",
        "method",
        "ADD-S ok",
        "ADD(-S) ok",
        "AUC ADD-S",
        "AUC ADD(-S)",
        "median ms",
        "prepare s",
    ]
    return rich_table(title, header, "lllrrrrrr", rows)


# ----------------------------------------------------------------- benchmark pages (markdown)


def speed_reference(runs: list[MethodRun]) -> str:
    """The method latencies are compared with: edgepose if it ran, else the fastest."""
    names = [r.name for r in runs]
    if "edgepose" in names:
        return "edgepose"
    medians = {r.name: summarise(r.views).median_ms for r in runs}
    return min(medians, key=lambda n: medians[n])


def overall_table(runs: list[MethodRun], reference: str) -> str:
    """One row per method over every object, latency relative to ``reference``'s."""
    summaries = {r.name: summarise(r.views) for r in runs}
    ref_ms = summaries[reference].median_ms
    rows = []
    for r in runs:
        s = summaries[r.name]
        fails = f" ({s.failures} errors)" if s.failures else ""
        rows.append(
            [
                f"{r.name}{fails}",
                f"{s.views}",
                f"{s.add_s_pass:.1f} %",
                f"{s.add_or_s_pass:.1f} %",
                f"{s.auc_add_s:.1f}",
                f"{s.auc_add_or_s:.1f}",
                f"{s.median_ms:.0f}",
                f"{s.p90_ms:.0f}",
                f"{statistics.median(r.prepare_s.values()):.2f}",
                f"{s.median_ms / ref_ms:.2f}×",
            ]
        )
    header = ["method", "views", "ADD-S < 0.1d", "ADD(-S) < 0.1d", "AUC ADD-S", "AUC ADD(-S)", "median ms"]
    header += ["p90 ms", "prepare s (median/object)", f"median latency / {reference}"]
    return markdown_table(header, "l" + "r" * 9, rows)


def per_object_table(runs: list[MethodRun], objects: list[BenchObject]) -> str:
    """One row per object and method."""
    rows = []
    for obj in objects:
        for r in runs:
            s = summarise([v for v in r.views if v.object == obj.name])
            rows.append(
                [
                    obj.name,
                    "yes" if obj.symmetric else "no",
                    r.name,
                    f"{s.add_s_pass:.0f} %",
                    f"{s.add_or_s_pass:.0f} %",
                    f"{s.auc_add_s:.1f}",
                    f"{s.auc_add_or_s:.1f}",
                    f"{s.median_ms:.0f}",
                    f"{s.p90_ms:.0f}",
                    f"{r.prepare_s[obj.name]:.2f}",
                ]
            )
    header = ["object", "sym.", "method", "ADD-S < 0.1d", "ADD(-S) < 0.1d", "AUC ADD-S", "AUC ADD(-S)"]
    header += ["median ms", "p90 ms", "prepare s"]
    return markdown_table(header, "lcl" + "r" * 7, rows)


def level_table(runs: list[MethodRun], notes: dict[str, str] | None = None) -> str:
    """One stress level: accuracy and latency per method; ``notes`` are
    appended to the named methods' names."""
    rows = []
    for r in runs:
        s = summarise(r.views)
        fails = f" ({s.failures} errors)" if s.failures else ""
        rows.append(
            [
                f"{r.name}{fails}{(notes or {}).get(r.name, '')}",
                f"{s.views}",
                f"{s.add_or_s_pass:.1f} %",
                f"{s.add_s_pass:.1f} %",
                f"{s.auc_add_or_s:.1f}",
                f"{s.median_ms:.0f}",
                f"{s.p90_ms:.0f}",
            ]
        )
    header = ["method", "views", "ADD(-S) < 0.1d", "ADD-S < 0.1d", "AUC ADD(-S)", "median ms", "p90 ms"]
    return markdown_table(header, "l" + "r" * 6, rows)


def stress_table(runs: dict[str, list[MethodRun]], objects: dict[str, list[BenchObject]], methods: list[str]) -> str:
    """Rows: stress levels with their achieved mean visible and spill
    fractions (over every rendered view); columns: each method's ADD(-S)
    (views in parentheses)."""
    rows = []
    for level, by_level in runs.items():
        visible = np.nanmean([x for o in objects[level] for x in o.visible])
        spill = np.mean([x for o in objects[level] for x in o.spill])
        found = {r.name: summarise(r.views) for r in by_level}
        cells = [f"{found[m].add_or_s_pass:.1f} % ({found[m].views})" if m in found else "–" for m in methods]
        rows.append([level, f"{visible:.2f}", f"{spill:.2f}", *cells])
    header = ["stress level", "mean visible fraction", "mean spill fraction", *(f"{m} ADD(-S)" for m in methods)]
    return markdown_table(header, "lrr" + "r" * len(methods), rows)


# ----------------------------------------------------------------- confidence


def confidence_rows(groups: dict[str, list[ViewResult]]) -> tuple[list[str], list[list[str]]]:
    """Header and rows: per group of views (a stress level, "stressed", …),
    how well confidence tells correct poses from wrong ones; groups without
    confidences are left out."""
    rows = []
    for label, views in groups.items():
        c = summarise_confidence(views)
        if c is None:
            continue
        rows.append(
            [
                label,
                f"{c.views}",
                f"{c.correct:.1f} %",
                f"{c.auroc:.3f}" if np.isfinite(c.auroc) else "–",
                f"{c.ece:.3f}",
                f"{c.wrong_accepted:.1f} %" if np.isfinite(c.wrong_accepted) else "–",
                f"{c.correct_kept:.1f} %" if np.isfinite(c.correct_kept) else "–",
                " / ".join(f"{t:.2f}" for t in c.strict_thresholds) or "–",
                f"{c.strict_wrong_accepted:.1f} %" if np.isfinite(c.strict_wrong_accepted) else "–",
                f"{c.strict_correct_kept:.1f} %" if np.isfinite(c.strict_correct_kept) else "–",
            ]
        )
    header = [
        "views of",
        "views",
        "correct",
        "AUROC",
        "ECE",
        f"wrong accepted (≥ {TRUST_THRESHOLD})",
        f"correct kept (≥ {TRUST_THRESHOLD})",
        "strict rule (≥)",
        "wrong accepted (strict)",
        "correct kept (strict)",
    ]
    return header, rows


def confidence_table(groups: dict[str, list[ViewResult]]) -> str:
    """:func:`confidence_rows` as markdown."""
    header, rows = confidence_rows(groups)
    return markdown_table(header, "l" + "r" * (len(header) - 1), rows)


def alternatives_table(groups: dict[str, list[ViewResult]]) -> str:
    """Per group of views (as :func:`confidence_rows`), markdown: of the wrong
    poses, how many had the truth among ``Pose.alternatives`` (all, and those
    trusted at the default rule); of the right ones, how many came with any."""
    rows = []
    for label, views in groups.items():
        wrong = [v for v in views if not v.errors.correct_add_or_s]
        right = [v for v in views if v.errors.correct_add_or_s]
        trusted = [v for v in wrong if v.confidence >= TRUST_THRESHOLD]
        rows.append(
            [
                label,
                f"{len(views)}",
                f"{len(wrong)}",
                f"{sum(v.alternative_correct for v in wrong)}",
                f"{sum(v.alternative_correct for v in trusted)} of {len(trusted)}",
                f"{100 * np.mean([v.alternatives > 0 for v in right]):.1f} %" if right else "–",
                f"{np.mean([v.alternatives for v in views]):.2f}",
            ]
        )
    header = [
        "views of",
        "views",
        "wrong",
        "wrong, truth among alternatives",
        f"... of those trusted (≥ {TRUST_THRESHOLD})",
        "right with any alternative",
        "alternatives per pose",
    ]
    return markdown_table(header, "l" + "r" * (len(header) - 1), rows)
