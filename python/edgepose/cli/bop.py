"""``edgepose bop``: run and score edgepose on a BOP-format dataset folder
(see :mod:`edgepose.eval.bop`, :mod:`edgepose.eval.bop_run`,
:mod:`edgepose.eval.bop_score`).
"""

import json
import time
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer

from edgepose.catalog import DEFAULT_CPUS_PER_TASK
from edgepose.cli.app import (
    Failure,
    RayAddressOption,
    RayOption,
    executor_for,
    handle_errors,
    stderr_console,
    stdout_console,
)

if TYPE_CHECKING:
    from rich.console import Console

    from edgepose.eval.bop import BopDataset, BopRow, BopTarget


def bop(
    dataset_dir: Annotated[
        Path, typer.Argument(help="A BOP dataset folder (models/, test/, test_targets_bop19.json), e.g. lmo/.")
    ],
    split: Annotated[
        str,
        typer.Option(
            help="Split (test; a sole test_primesense folder is found as test; name one of several: test_kinect)."
        ),
    ] = "test",
    targets: Annotated[
        Path | None,
        typer.Option(help="Targets file (default: the dataset's test_targets_bop19.json, else all ≥10 % visible)."),
    ] = None,
    scenes: Annotated[str | None, typer.Option(help="Only these scenes, comma-separated, e.g. 2,3.")] = None,
    masks: Annotated[
        str,
        typer.Option(help="gt: the annotated visible masks (mask_visib); or a BOP default-detections JSON file."),
    ] = "gt",
    out: Annotated[Path, typer.Option("-o", "--out", help="Folder for the results CSV and the score tables.")] = Path(
        "bop_results"
    ),
    codebooks: Annotated[
        Path | None, typer.Option(help="Folder for the objects' codebooks (default: OUT/codebooks); reused.")
    ] = None,
    images: Annotated[int | None, typer.Option(help="Only the first N images with targets (a quick look).")] = None,
    ray: RayOption = False,
    ray_address: RayAddressOption = None,
    cpus_per_task: Annotated[
        int, typer.Option(help="With --ray: CPUs each object's codebook build reserves.")
    ] = DEFAULT_CPUS_PER_TASK,
) -> None:
    """Run edgepose on a BOP dataset and score it: AR (VSD, MSSD, MSPD) and ADD(-S).

    Builds a codebook per object model (skipped when up to date, so reruns start at once), estimates every target
    with the annotated visible masks (or a detector's, --masks FILE), one estimate_many call per image, and writes
    OUT/edgepose_DATASET-SPLIT.csv in the BOP results format (R row-major, t in mm, time per image in seconds), then
    the scores per object and overall: printed, and written as OUT/edgepose_DATASET-SPLIT_scores.json and .md
    (when the split's ground truth is published; otherwise the CSV alone, for the BOP server).
    """
    from edgepose.eval.bop import BopDataset, write_bop_csv
    from edgepose.eval.bop_run import bop_codebooks, read_detections, run_bop
    from edgepose.eval.bop_score import score_bop
    from edgepose.report import progress

    err = stderr_console()
    with handle_errors():
        dataset = BopDataset(dataset_dir, split)
        wanted, scored = _targets_to_run(dataset, targets, scenes, images, masks)
        detections = None if masks == "gt" else read_detections(masks)
        obj_ids = sorted({t.obj_id for t in wanted})
        executor = executor_for(ray or ray_address is not None, ray_address, cpus_per_task)
        with progress(err, "codebooks", len(obj_ids)) as on_result:
            books = bop_codebooks(
                dataset, obj_ids, codebooks or out / "codebooks", executor=executor, on_result=on_result
            )
        image_count = len({(t.scene_id, t.im_id) for t in wanted})
        started = time.perf_counter()
        with progress(err, "images", image_count) as advance:
            rows = run_bop(
                dataset,
                wanted,
                books,
                detections=detections,
                on_image=lambda image, _: advance(SimpleNamespace(name=f"scene {image.scene_id}", status="done")),
            )
        wall = time.perf_counter() - started
        out.mkdir(parents=True, exist_ok=True)
        stem = f"edgepose_{dataset.name}-{dataset.split}"
        write_bop_csv(out / f"{stem}.csv", rows)
        table = "no ground truth published for this split: the results CSV is for the BOP server to score\n"
        if scored:
            with err.status("scoring: VSD, MSSD, MSPD, ADD(-S)"):
                scores = score_bop(dataset, rows, wanted)
            table = scores.markdown()
            (out / f"{stem}_scores.json").write_text(json.dumps(scores.to_json(), indent=1) + "\n")
            (out / f"{stem}_scores.md").write_text(table)
    stdout_console().print(table, markup=False)
    _print_run(err, rows, wanted, image_count, wall, out / f"{stem}.csv")


def _targets_to_run(
    dataset: "BopDataset", targets: Path | None, scenes: str | None, images: int | None, masks: str
) -> tuple[list["BopTarget"], bool]:
    """The targets ``edgepose bop`` estimates (``--targets``, ``--scenes``,
    ``--images``) and whether their ground truth is published (so they can be
    scored); Failure when there are none, or when ``--masks gt`` has no masks."""
    try:
        scene_ids = None if scenes is None else [int(s) for s in scenes.split(",") if s.strip()]
    except ValueError:
        raise Failure(f"--scenes must be comma-separated scene numbers, got {scenes!r}") from None
    wanted = dataset.targets(targets, scene_ids)
    if images is not None:
        keep = set(sorted({(t.scene_id, t.im_id) for t in wanted})[: max(images, 0)])
        wanted = [t for t in wanted if (t.scene_id, t.im_id) in keep]
    if not wanted:
        raise Failure(f"{dataset.root}: no targets to estimate (check --split, --scenes and --targets)")
    scored = all(dataset.has_ground_truth(s) for s in {t.scene_id for t in wanted})
    if masks == "gt" and not scored:
        raise Failure(
            f"{dataset.root}: this split's ground truth (scene_gt.json, mask_visib/) is not published; "
            "give a detector's masks with --masks DETECTIONS.json"
        )
    return wanted, scored


def _print_run(
    err: "Console", rows: list["BopRow"], wanted: list["BopTarget"], images: int, wall: float, csv: Path
) -> None:
    """The run's last line (on stderr): estimates, targets, images, wall time, per-image median."""
    times = sorted({(r.scene_id, r.im_id): r.time for r in rows}.values())
    median = f"{1000 * float(np.median(times)):.1f} ms" if times else "n/a"
    err.print(
        f"{len(rows)} estimates of {sum(t.inst_count for t in wanted)} targets in {images} images "
        f"({wall:.1f} s with image loading; per-image time median {median}); "
        f"wrote {csv} and the scores beside it"
    )
