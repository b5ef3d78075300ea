"""``edgepose build`` and ``edgepose eval``: a catalogue of meshes, one
object at a time, locally or as Ray tasks (see :mod:`edgepose.catalog`).
"""

import time
from pathlib import Path
from typing import Annotated

import numpy as np
import typer

from edgepose.catalog import DEFAULT_CPUS_PER_TASK, DEFAULT_RETRIES
from edgepose.cli.app import (
    Failure,
    RayAddressOption,
    RayOption,
    ScaleOption,
    executor_for,
    exit_if_failed,
    handle_errors,
    stderr_console,
    stdout_console,
)
from edgepose.eval.methods import METHODS
from edgepose.model import DEFAULT_MODEL_POINTS
from edgepose.settings import DEFAULT_SETTINGS
from edgepose.views import DEFAULT_VIEWS


def build(
    meshes: Annotated[
        list[Path], typer.Argument(help="Mesh files, or folders of them (.ply .obj .stl .off .glb .gltf).")
    ],
    out_dir: Annotated[Path, typer.Option("-o", "--out", help="Folder for the codebooks (<mesh name>.codebook).")],
    views: Annotated[int, typer.Option(help="Viewpoints per codebook.")] = DEFAULT_VIEWS,
    scale: ScaleOption = None,
    points: Annotated[int, typer.Option(help="Surface points of the standard model.")] = DEFAULT_MODEL_POINTS,
    force: Annotated[
        bool, typer.Option("--force", help="Rebuild codebooks that are up to date too (e.g. after changing --scale).")
    ] = False,
    ray: RayOption = False,
    ray_address: RayAddressOption = None,
    cpus_per_task: Annotated[
        int, typer.Option(help="With --ray: CPUs each object's task reserves and uses.")
    ] = DEFAULT_CPUS_PER_TASK,
    retries: Annotated[int, typer.Option(help="Attempts after the first for an object that fails.")] = DEFAULT_RETRIES,
) -> None:
    """Build a codebook for each mesh (seconds each): DIR/<mesh name>.codebook.

    Codebooks already up to date (same mesh sha256, encoder, views, points and symmetry search) are skipped, so
    rerunning an interrupted build resumes it. An object that fails is retried, then reported; the others are still
    built (exit status 1 if any failed). --ray runs one Ray task per object on a cluster (dist extra).
    """
    from edgepose.catalog import BuildSettings, build_catalog, find_meshes
    from edgepose.report import build_summary, build_table, progress

    with handle_errors():
        if views < DEFAULT_SETTINGS.retrieve.k:  # estimate verifies k codebook views
            raise Failure(f"--views must be at least {DEFAULT_SETTINGS.retrieve.k}, got {views}")
        files = find_meshes(meshes)
        executor = executor_for(ray or ray_address is not None, ray_address, cpus_per_task)
    started = time.perf_counter()
    with progress(stderr_console(), "building", len(files)) as on_result, handle_errors():
        results = build_catalog(
            files,
            out_dir,
            BuildSettings(views, points, scale),
            executor=executor,
            force=force,
            retries=retries,
            on_result=on_result,
        )
    wall = time.perf_counter() - started
    stdout_console().print(build_table(results, out_dir))
    stderr_console().print(build_summary(results, wall, on_ray=executor is not None))
    exit_if_failed(results)


def evaluate(
    meshes: Annotated[list[Path], typer.Argument(help="Mesh files (metres or detected mm), or folders of them.")],
    views: Annotated[int, typer.Option(help="Rendered views per object.")] = 10,
    seed: Annotated[int, typer.Option(help="Seed of the views (view i of object k: seed·100000 + k·1000 + i).")] = 0,
    occluders: Annotated[int, typer.Option(help="Occluding rectangles per view (clean level only).")] = 0,
    stress: Annotated[
        str,
        typer.Option(
            help="Stress level of the views (edgepose.eval.STRESS_LEVELS): clean, visible70, visible40, visible20, "
            "spill2, spill5, spill8, eroded3, partial, noise_far, occluded30_spill5, sensor_holes, on_table."
        ),
    ] = "clean",
    reliability: Annotated[
        Path | None, typer.Option(help="Write edgepose's reliability diagram (confidence vs share correct) here, PNG.")
    ] = None,
    methods: Annotated[
        str, typer.Option(help=f"Comma-separated: {', '.join(METHODS)} (peers need the baselines extra).")
    ] = "edgepose",
    symmetric: Annotated[
        list[str] | None,
        typer.Option(
            help="Object (file stem) judged with ADD-S in ADD(-S); repeatable. Default: the objects in which "
            "edgepose detects a rotational symmetry."
        ),
    ] = None,
    ray: RayOption = False,
    ray_address: RayAddressOption = None,
    cpus_per_task: Annotated[
        int, typer.Option(help="With --ray: CPUs each object's task reserves.")
    ] = DEFAULT_CPUS_PER_TASK,
) -> None:
    """Benchmark on rendered depth views of meshes, with known poses.

    Prints per object: ADD-S and ADD(-S) below 0.1 × diameter, their AUC (0–10 cm), the median estimate latency and
    the preparation (codebook build) time; then how well each edgepose method's confidence tells its correct poses
    from its wrong ones (AUROC, calibration error, what the >= 0.5 rule and the strict rule accept).
    --ray evaluates one object per Ray task (accuracy is the same; latencies
    then include the tasks' competition for the CPUs).
    """
    from edgepose.catalog import evaluate_catalog, find_meshes
    from edgepose.report import progress

    with handle_errors():
        chosen = _checked_evaluation(methods, views, stress, reliability, occluders)
        files = find_meshes(meshes)
        executor = executor_for(ray or ray_address is not None, ray_address, cpus_per_task)
    with progress(stderr_console(), "evaluating", len(files)) as on_result, handle_errors():
        results = evaluate_catalog(
            files,
            lambda k: [seed * 100_000 + k * 1000 + i for i in range(views)],
            chosen,
            symmetric=lambda stem: None if symmetric is None else stem in symmetric,
            occluders=occluders,
            stress=stress,
            executor=executor,
            on_result=on_result,
        )
    _print_evaluation(results, chosen, views, seed, stress, occluders, reliability)
    exit_if_failed(results)


def _checked_evaluation(methods: str, views: int, stress: str, reliability: Path | None, occluders: int) -> list[str]:
    """The methods ``edgepose eval`` runs, after checking its options fit
    together (and that each method's extra is installed); Failure otherwise."""
    from edgepose.eval.methods import create_method, parse_methods
    from edgepose.eval.stress import STRESS_LEVELS

    try:
        chosen = parse_methods(methods)
    except ValueError as e:
        raise Failure(str(e)) from None
    if views < 1:
        raise Failure(f"--views must be at least 1, got {views}")
    if stress not in STRESS_LEVELS:
        raise Failure(f"--stress must be one of {', '.join(STRESS_LEVELS)}, got {stress!r}")
    if reliability is not None and not any(m.startswith("edgepose") for m in chosen):
        raise Failure("--reliability needs an edgepose method: only edgepose gives confidences")
    if occluders and stress != "clean":
        raise Failure("--occluders applies to the clean level only; stress levels set their own occluders")
    for name in chosen:
        try:
            create_method(name)
        except ImportError as e:
            raise Failure(f"{name} needs the baselines extra ({e})") from None
    return chosen


def _print_evaluation(
    results: list, chosen: list[str], views: int, seed: int, stress: str, occluders: int, reliability: Path | None
) -> None:
    """The accuracy table of the evaluated objects, the confidence table, and
    the reliability diagram when asked for."""
    from edgepose.eval.benchmark import merge_runs, summarise_confidence
    from edgepose.report import confidence_rows, eval_table, rich_table
    from edgepose.viz import save_reliability_png

    evaluated = [r for r in results if not r.failed]
    if not evaluated:
        return
    runs = [merge_runs(name, [r.runs[name] for r in evaluated]) for name in chosen]
    title = (
        f"{views} rendered views per object (seed {seed}, stress {stress}, {occluders} occluders); "
        "correct = error < 0.1 × diameter"
    )
    symmetric_names = {r.name for r in evaluated if r.symmetric}
    stdout_console().print(eval_table(runs, [r.name for r in evaluated], symmetric_names, title))
    header, rows = confidence_rows({run.name: run.views for run in runs})
    if rows:
        stdout_console().print(
            rich_table(f"confidence at stress {stress}", header, "l" + "r" * (len(header) - 1), rows)
        )
    if reliability is not None:
        with_confidence = [r for r in runs if summarise_confidence(r.views) is not None]
        save_reliability_png(
            reliability,
            {
                r.name: (
                    np.array([v.confidence for v in r.views]),
                    np.array([v.errors.correct_add_or_s for v in r.views]),
                )
                for r in with_confidence
            },
        )
        stdout_console().print(f"reliability diagram: {reliability}")
