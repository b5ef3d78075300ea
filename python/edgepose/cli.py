"""The ``edgepose`` command line: ``demo``, ``build``, ``estimate``, ``eval``.

Heavy imports (numpy, onnxruntime, trimesh) happen inside the commands, so
``--help`` is instant. Deliberate errors print one ``error: …`` line on
stderr and exit with status 1; usage errors exit with status 2.
"""

import inspect
import json
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

if TYPE_CHECKING:
    import numpy as np

#: Codebooks shipped inside the package (``codebooks/`` in a checkout links here),
#: with the mesh of the demo object.
SHIPPED_DIR = Path(__file__).resolve().parent / "codebooks"
#: The demo's object: a YCB mesh (CC BY 4.0) whose codebook and mesh ship with edgepose.
DEMO_OBJECT = "power_drill"

EXAMPLES = """
[bold]Examples[/bold] (units are metres; poses are T_cam_obj, camera frame as OpenCV)

  [dim]# the shipped power drill at a random pose; writes edgepose_demo.png[/dim]
  [cyan]edgepose demo[/cyan]
  [cyan]edgepose demo --seed 3 --show drill.png[/cyan]
  [dim]# your own mesh, in millimetres[/dim]
  [cyan]edgepose demo --mesh part.stl --scale 0.001[/cyan]

  [dim]# codebooks for one mesh or a folder of them (seconds each)[/dim]
  [cyan]edgepose build mug.ply -o codebooks/[/cyan]
  [cyan]edgepose build ../shared/data/ycb -o codebooks/[/cyan]
  [dim]# a whole catalogue, one Ray task per object; a rerun skips what is up to date[/dim]
  [cyan]edgepose build catalog/ -o codebooks/ --ray[/cyan]

  [dim]# a pose as JSON from a cloud (.ply/.pcd/.npy) ...[/dim]
  [cyan]edgepose estimate -c codebooks/mug.codebook cloud.ply[/cyan]
  [dim]# ... or from a 16-bit depth PNG (mm), intrinsics and a mask[/dim]
  [cyan]edgepose estimate -c mug.codebook d.png --K cam.json --mask m.png --show out.png[/cyan]
  [cyan]edgepose estimate -c mug.codebook depth.png --mask m.png \\
      --K "572.4 0 325.3 0 573.6 242 0 0 1" --bop-csv results.csv[/cyan]

  [dim]# accuracy and latency on rendered views with known poses[/dim]
  [cyan]edgepose eval ../shared/data/ycb --views 20[/cyan]

  [dim]# versions; proves the compiled core and the networks load[/dim]
  [cyan]edgepose --version[/cyan]
"""

app = typer.Typer(
    name="edgepose",
    help="6D pose of an object from its segmented depth cloud, on a CPU in milliseconds.",
    epilog=EXAMPLES,
    rich_markup_mode="rich",
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


class Failure(Exception):
    """A CLI-level error: printed as one line, exit status 1."""


@contextmanager
def _errors() -> Iterator[None]:
    """Turn deliberate errors into one stderr line and exit status 1."""
    from rich.markup import escape

    from edgepose.errors import EdgePoseError

    try:
        yield
    except (EdgePoseError, Failure) as e:
        _stderr().print(f"[red]error:[/red] {escape(str(e))}")
        raise typer.Exit(1) from None


def _stdout():
    from rich.console import Console

    # Piped output keeps whole table rows (rich would assume 80 columns).
    return Console(soft_wrap=True, highlight=False, width=None if sys.stdout.isatty() else 160)


def _stderr():
    from rich.console import Console

    return Console(stderr=True, soft_wrap=True, highlight=False)


def _version(value: bool) -> None:
    if not value:
        return
    import onnxruntime

    import edgepose
    from edgepose import _core
    from edgepose.encoder import MODELS_DIR, Encoder

    with _errors():
        encoder = Encoder()
        manifest = json.loads((MODELS_DIR / "manifest.json").read_text())
    files = manifest["files"]
    print(f"edgepose {edgepose.__version__}")
    print(f"core        {_core.__name__} (compiled core loaded from {Path(_core.__file__).name})")
    print(
        f"networks    encoder.onnx {files['encoder.onnx'][:12]}, irr.onnx {files['irr.onnx'][:12]} "
        f"({manifest['parameters']['total']:,} parameters, sha256 checked, code size {encoder.code_size})"
    )
    print(f"onnxruntime {onnxruntime.__version__}")
    raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool | None,
        typer.Option(
            "--version",
            callback=_version,
            is_eager=True,
            help="Print versions; proves the compiled core and the networks load.",
        ),
    ] = None,
) -> None:
    """6D pose of an object from its segmented depth cloud, on a CPU in milliseconds."""


def command(name: str | None = None) -> Callable[[Callable], Callable]:
    """``app.command`` whose help is the function's docstring with each
    paragraph's line breaks joined (typer keeps them), so docstrings wrap at
    the line length."""

    def register(function: Callable) -> Callable:
        paragraphs = inspect.cleandoc(function.__doc__ or "").split("\n\n")
        text = "\n\n".join(" ".join(paragraph.split()) for paragraph in paragraphs)
        return app.command(name, help=text)(function)

    return register


# ----------------------------------------------------------------- demo


@command()
def demo(
    mesh: Annotated[
        Path | None,
        typer.Option(help="A mesh file to use instead of the shipped power drill (a codebook is built first)."),
    ] = None,
    scale: Annotated[float | None, typer.Option(help="Mesh file units → metres (default: detect mm).")] = None,
    views: Annotated[int, typer.Option(help="Viewpoints of a codebook built for --mesh.")] = 2100,
    seed: Annotated[
        int | None, typer.Option(help="Seed of the rendered pose (default: a random one, printed).")
    ] = None,
    show: Annotated[Path, typer.Option(help="Where to write the picture of the result.")] = Path("edgepose_demo.png"),
    rerun: Annotated[bool, typer.Option("--rerun", help="Also log to a rerun viewer (viz extra).")] = False,
    rrd: Annotated[Path | None, typer.Option(help="Also save a rerun recording (.rrd, viz extra).")] = None,
) -> None:
    """Estimate the pose of the shipped example object rendered at a random pose.

    Renders a depth view of the power drill (or --mesh), estimates its pose, prints the estimate, the truth, the
    errors and the timings, and writes a picture (--show). Needs nothing but the installed package: the drill's
    codebook and mesh ship with it.
    """
    import secrets

    import numpy as np

    import edgepose
    from edgepose.eval import YCB_SYMMETRIC, pose_errors, render_view
    from edgepose.model import read_mesh
    from edgepose.viz import Frame, recorder, save_result_png

    out = _stdout()
    with _errors():
        if mesh is None:
            name, mesh_path = DEMO_OBJECT, SHIPPED_DIR / f"{DEMO_OBJECT}.ply"
            codebook_path = SHIPPED_DIR / f"{DEMO_OBJECT}.codebook"
            triangles = read_mesh(mesh_path)
            try:
                codebook = edgepose.Codebook.load(codebook_path)
            except edgepose.CodebookError as e:
                raise Failure(f"{e} (the shipped ones: `make codebooks`)") from None
            origin = f"shipped codebook {codebook_path.name}, {len(codebook)} views"
        else:
            name, mesh_path = mesh.stem, mesh
            triangles = read_mesh(mesh_path, scale=scale)
            codebook = edgepose.build_codebook(triangles, views=views, scale=1.0)
            t = codebook.timings
            origin = (
                f"codebook {len(codebook)} views built in {t['total']:.2f} s "
                f"(maps {t['maps']:.2f} s, encoding {t['encode']:.2f} s)"
            )
        seed = secrets.randbelow(1_000_000) if seed is None else seed
        view = render_view(triangles, seed=seed)
        edgepose.estimate(view.cloud, codebook)  # the first call loads onnxruntime's kernels
        pose = edgepose.estimate(view.cloud, codebook)
    model_points = codebook.model.mesh_points
    symmetric = name in YCB_SYMMETRIC
    errors = pose_errors(model_points, pose.matrix, view.T_cam_obj, codebook.model.diameter, symmetric)
    metric = "ADD-S" if symmetric else "ADD"
    threshold_mm = errors.diameter * 100
    correct = errors.correct_add_or_s

    out.print(f"[bold]object[/bold]      {name} ({codebook.model.diameter * 1000:.0f} mm across): {origin}")
    out.print(
        f"[bold]rendered[/bold]    {len(view.cloud)} points, {np.linalg.norm(view.T_cam_obj[:3, 3]):.2f} m away "
        f"(640×480 depth, 1 mm noise, seed {seed}; --seed {seed} repeats it)"
    )
    out.print("[bold]estimated[/bold]   T_cam_obj =\n" + _matrix_text(pose.matrix))
    out.print("[bold]true[/bold]        T_cam_obj =\n" + _matrix_text(view.T_cam_obj))
    verdict = "[green]correct[/green]" if correct else "[red]WRONG[/red]"
    out.print(
        f"[bold]errors[/bold]      rotation {errors.rotation_deg:.2f}°, translation {errors.translation_mm:.1f} mm, "
        f"{metric} {errors.add_or_s * 1000:.1f} mm ({verdict} at 0.1 × diameter = {threshold_mm:.1f} mm)"
    )
    stages = ", ".join(f"{k} {v * 1000:.2f}" for k, v in pose.timings.items() if k != "total")
    out.print(f"[bold]timings[/bold]     {pose.timings['total'] * 1000:.1f} ms in all ({stages} ms)")

    frame = Frame(view.cloud, model_points, pose.matrix, K=view.camera.K, depth=view.depth)
    lines = [
        f"edgepose demo: {name}, seed {seed}, {len(view.cloud)} points, estimate {pose.timings['total'] * 1000:.1f} ms",
        f"{metric} {errors.add_or_s * 1000:.1f} mm: {'correct' if correct else 'WRONG'} "
        f"(threshold 0.1 x diameter = {threshold_mm:.1f} mm)",
        f"rotation error {errors.rotation_deg:.2f}°, translation error {errors.translation_mm:.1f} mm",
    ]
    with _errors():
        picture = save_result_png(show, frame, lines)
    recorder(spawn=rerun, save=rrd).log(name, frame)
    out.print(f"[bold]picture[/bold]     {picture}")


def _matrix_text(matrix: "np.ndarray") -> str:
    return "\n".join("            " + "  ".join(f"{x:8.4f}" for x in row) for row in matrix)


# ----------------------------------------------------------------- build


RAY_HELP = (
    "Run one Ray task per object: on the cluster in RAY_ADDRESS, else on a Ray instance started on this machine "
    "(dist extra)."
)
RAY_ADDRESS_HELP = "With --ray (implied): the Ray cluster to join, e.g. auto, host:6379 or ray://host:10001."


@command()
def build(
    meshes: Annotated[
        list[Path], typer.Argument(help="Mesh files, or folders of them (.ply .obj .stl .off .glb .gltf).")
    ],
    out_dir: Annotated[Path, typer.Option("-o", "--out", help="Folder for the codebooks (<mesh name>.codebook).")],
    views: Annotated[int, typer.Option(help="Viewpoints per codebook.")] = 2100,
    scale: Annotated[float | None, typer.Option(help="Mesh file units → metres (default: detect mm).")] = None,
    points: Annotated[int, typer.Option(help="Surface points of the standard model.")] = 4096,
    force: Annotated[
        bool, typer.Option("--force", help="Rebuild codebooks that are up to date too (e.g. after changing --scale).")
    ] = False,
    ray: Annotated[bool, typer.Option("--ray", help=RAY_HELP)] = False,
    ray_address: Annotated[str | None, typer.Option(help=RAY_ADDRESS_HELP)] = None,
    cpus_per_task: Annotated[int, typer.Option(help="With --ray: CPUs each object's task reserves and uses.")] = 1,
    retries: Annotated[int, typer.Option(help="Attempts after the first for an object that fails.")] = 2,
) -> None:
    """Build a codebook for each mesh (seconds each): DIR/<mesh name>.codebook.

    Codebooks already up to date (same mesh sha256, encoder, views and points) are skipped, so rerunning an
    interrupted build resumes it. An object that fails is retried, then reported; the others are still built (exit
    status 1 if any failed). --ray runs one Ray task per object on a cluster (dist extra).
    """
    from rich.markup import escape
    from rich.table import Table

    from edgepose.catalog import BuildSettings, build_catalog, find_meshes

    with _errors():
        if views < 16:
            raise Failure(f"--views must be at least 16, got {views}")
        files = find_meshes(meshes)
        executor = _executor(ray or ray_address is not None, ray_address, cpus_per_task)
    started = time.perf_counter()
    with _catalog_progress("building", len(files)) as on_result, _errors():
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
    table = Table(title=f"codebooks in {out_dir}/")
    for column, justify in (
        ("object", "left"),
        ("status", "left"),
        ("views", "right"),
        ("build s", "right"),
        ("size MB", "right"),
        ("file", "left"),
    ):
        table.add_column(column, justify=justify)  # type: ignore[arg-type]
    for r in results:
        if r.failed:
            table.add_row(r.name, "[red]failed[/red]", "", "", "", "")
        else:
            seconds = f"{r.seconds:.2f}" if r.status == "built" else ""
            table.add_row(r.name, r.status, str(r.views), seconds, f"{r.bytes / 1e6:.2f}", Path(r.codebook).name)
    _stdout().print(table)
    failed = [r for r in results if r.failed]
    counts = {status: sum(r.status == status for r in results) for status in ("built", "skipped")}
    _stderr().print(
        f"{counts['built']} built, {counts['skipped']} up to date (skipped), {len(failed)} failed; "
        f"{len(results)} objects in {wall:.1f} s ({60 * len(results) / max(wall, 1e-9):.1f} objects/min"
        f"{', Ray' if executor is not None else ''})"
    )
    for r in failed:
        _stderr().print(f"[red]error:[/red] {escape(r.error)} ({r.attempts} attempts)")
    if failed:
        raise typer.Exit(1)


def _executor(ray: bool, address: str | None, cpus_per_task: int):
    """None (run locally) or a Ray executor."""
    if not ray:
        return None
    from edgepose.catalog import RayExecutor

    return RayExecutor(address, cpus_per_task=cpus_per_task)


@contextmanager
def _catalog_progress(verb: str, total: int):
    """A progress bar on stderr; yields the callback that advances it per finished object."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    progress = Progress(
        TextColumn("{task.description:<28}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
        console=_stderr(),
        transient=True,
    )
    with progress:
        task = progress.add_task(verb, total=total)

        def on_result(result) -> None:
            progress.update(task, description=f"{verb}: {result.name} {result.status}")
            progress.advance(task)

        yield on_result


# ----------------------------------------------------------------- estimate


@command()
def estimate(
    cloud: Annotated[
        Path,
        typer.Argument(
            help="The object's points: .ply/.pcd/.npy (metres, camera frame), "
            "or a 16-bit depth .png with --K and --mask."
        ),
    ],
    codebook: Annotated[Path, typer.Option("-c", "--codebook", help="The object's codebook (edgepose build).")],
    K: Annotated[
        str | None, typer.Option("--K", help="Depth camera intrinsics: a JSON file or 9 numbers (row-major 3×3).")
    ] = None,
    mask: Annotated[
        Path | None,
        typer.Option(help="Segmentation mask PNG of the object (non-zero = object), same size as the depth image."),
    ] = None,
    depth_scale: Annotated[float, typer.Option(help="Depth units per metre (1000 for millimetre PNGs).")] = 1000.0,
    refine: Annotated[bool, typer.Option(help="Refine with point-to-plane ICP.")] = True,
    k: Annotated[int, typer.Option(help="Candidate viewpoints verified.")] = 16,
    truth: Annotated[
        Path | None, typer.Option(help="True T_cam_obj (JSON 4×4 / BOP gt entry, or .npy) to report the errors.")
    ] = None,
    show: Annotated[Path | None, typer.Option(help="Write a picture of the estimate (PNG).")] = None,
    bop_csv: Annotated[
        Path | None, typer.Option(help="Append the pose to a BOP results CSV (created with its header).")
    ] = None,
    scene_id: Annotated[int, typer.Option(help="BOP scene id.")] = 0,
    im_id: Annotated[int, typer.Option(help="BOP image id.")] = 0,
    obj_id: Annotated[int, typer.Option(help="BOP object id.")] = 1,
    rerun: Annotated[bool, typer.Option("--rerun", help="Also log to a rerun viewer (viz extra).")] = False,
    rrd: Annotated[Path | None, typer.Option(help="Also save a rerun recording (.rrd, viz extra).")] = None,
) -> None:
    """Estimate an object's pose in a cloud or a depth image; print it as JSON.

    JSON fields: matrix (4×4 T_cam_obj, metres), score (code cosine), fit (metres), view, refined, points, timings
    (seconds per stage of a warm call), and errors with --truth.
    """

    import edgepose
    from edgepose import io
    from edgepose.viz import Frame, recorder, save_result_png

    with _errors():
        book = edgepose.Codebook.load(codebook)
        camera, depth = None, None
        if cloud.suffix.lower() == ".png":
            if K is None or mask is None:
                raise Failure(f"{cloud}: a depth image needs --K (intrinsics) and --mask (the object's pixels)")
            camera = io.parse_intrinsics(K)
            depth = io.read_depth_png(cloud)
            segmentation = io.read_mask_png(mask)
            points = edgepose.cloud_from_depth(depth, camera, segmentation, depth_scale=depth_scale)
        else:
            if K is not None or mask is not None:
                raise Failure("--K and --mask apply to depth images (.png) only")
            points = io.read_cloud(cloud)
        T_true = io.read_pose(truth) if truth is not None else None
        # One untimed call first, so the timings are those of a long-running process.
        edgepose.estimate(points, book, refine=refine, k=k)
        pose = edgepose.estimate(points, book, refine=refine, k=k)

    result = {
        "matrix": pose.matrix.tolist(),
        "score": pose.score,
        "fit": pose.fit,
        "view": pose.view,
        "refined": pose.refined,
        "inlier_fraction": pose.inlier_fraction,
        "free_space_violation": pose.free_space_violation,
        "points": int(len(points)),
        "kept_points": pose.kept_points,
        "timings": pose.timings,
    }
    model_points = book.model.mesh_points
    lines = [
        f"{cloud.name}: {len(points)} points, estimate {pose.timings['total'] * 1000:.1f} ms, "
        f"fit {pose.fit * 1000:.1f} mm, score {pose.score:.3f}"
    ]
    if T_true is not None:
        from edgepose.eval import pose_errors

        e = pose_errors(model_points, pose.matrix, T_true, book.model.diameter, symmetric=False)
        result["errors"] = {
            "rotation_deg": e.rotation_deg,
            "translation_mm": e.translation_mm,
            "add_mm": e.add * 1000,
            "add_s_mm": e.add_s * 1000,
            "diameter_mm": e.diameter * 1000,
            "correct_add": e.add < 0.1 * e.diameter,
            "correct_add_s": e.correct_add_s,
        }
        lines.append(
            f"ADD {e.add * 1000:.1f} mm, ADD-S {e.add_s * 1000:.1f} mm (threshold 0.1 x diameter = "
            f"{e.diameter * 100:.1f} mm); rotation {e.rotation_deg:.2f}°, translation {e.translation_mm:.1f} mm"
        )
    print(_json_text(result))

    frame = Frame(points, model_points, pose.matrix, K=camera, depth=depth)
    with _errors():
        if show is not None:
            save_result_png(show, frame, lines)
        if bop_csv is not None:
            _append_bop(bop_csv, scene_id, im_id, obj_id, pose)
    recorder(spawn=rerun, save=rrd).log(codebook.stem, frame)


def _json_text(result: dict) -> str:
    """JSON with one line per field and per matrix row."""
    fields = []
    for key, value in result.items():
        if key == "matrix":
            rows = ",\n".join("    " + json.dumps(row) for row in value)
            fields.append(f'  "matrix": [\n{rows}\n  ]')
        else:
            fields.append(f"  {json.dumps(key)}: {json.dumps(value)}")
    return "{\n" + ",\n".join(fields) + "\n}"


def _append_bop(path: Path, scene_id: int, im_id: int, obj_id: int, pose) -> None:
    from edgepose.eval import BopRow, read_bop_csv, write_bop_csv

    try:
        rows = read_bop_csv(path) if path.is_file() else []
    except ValueError as e:
        raise Failure(str(e)) from None
    rows.append(BopRow(scene_id, im_id, obj_id, pose.score, pose.R, pose.t, pose.timings["total"]))
    write_bop_csv(path, rows)


# ----------------------------------------------------------------- eval


@command("eval")
def evaluate(
    meshes: Annotated[list[Path], typer.Argument(help="Mesh files (metres or detected mm), or folders of them.")],
    views: Annotated[int, typer.Option(help="Rendered views per object.")] = 10,
    seed: Annotated[int, typer.Option(help="Seed of the views (view i of object k: seed·100000 + k·1000 + i).")] = 0,
    occluders: Annotated[int, typer.Option(help="Occluding rectangles per view.")] = 0,
    methods: Annotated[
        str, typer.Option(help="Comma-separated: edgepose, open3d, opencv-ppf (peers need the baselines extra).")
    ] = "edgepose",
    symmetric: Annotated[
        list[str] | None,
        typer.Option(
            help="Object (file stem) judged with ADD-S in ADD(-S); repeatable. Default: the symmetric YCB objects."
        ),
    ] = None,
    ray: Annotated[bool, typer.Option("--ray", help=RAY_HELP)] = False,
    ray_address: Annotated[str | None, typer.Option(help=RAY_ADDRESS_HELP)] = None,
    cpus_per_task: Annotated[int, typer.Option(help="With --ray: CPUs each object's task reserves.")] = 1,
) -> None:
    """Benchmark on rendered depth views of meshes, with known poses.

    Prints per object: ADD-S and ADD(-S) below 0.1 × diameter, their AUC (0–10 cm), the median estimate latency and
    the preparation (codebook build) time. --ray evaluates one object per Ray task (accuracy is the same; latencies
    then include the tasks' competition for the CPUs).
    """
    from rich.markup import escape
    from rich.table import Table

    from edgepose.catalog import eval_methods, evaluate_catalog, find_meshes
    from edgepose.eval.benchmark import MethodRun, summarise
    from edgepose.eval.metrics import YCB_SYMMETRIC

    constructors = eval_methods()
    with _errors():
        chosen = [m.strip() for m in methods.split(",") if m.strip()]
        unknown = [m for m in chosen if m not in constructors]
        if unknown or not chosen:
            raise Failure(f"unknown methods {unknown}; choose from {', '.join(constructors)}")
        if views < 1:
            raise Failure(f"--views must be at least 1, got {views}")
        for name in chosen:
            try:
                constructors[name]()
            except ImportError as e:
                raise Failure(f"{name} needs the baselines extra ({e})") from None
        files = find_meshes(meshes)
        executor = _executor(ray or ray_address is not None, ray_address, cpus_per_task)
    with _catalog_progress("evaluating", len(files)) as on_result, _errors():
        results = evaluate_catalog(
            files,
            lambda k: [seed * 100_000 + k * 1000 + i for i in range(views)],
            chosen,
            symmetric=lambda stem: stem in (YCB_SYMMETRIC if symmetric is None else symmetric),
            occluders=occluders,
            executor=executor,
            on_result=on_result,
        )
    evaluated = [r for r in results if not r.failed]
    runs = [
        MethodRun(
            name,
            {r.name: r.runs[name].prepare_s[r.name] for r in evaluated},
            [v for r in evaluated for v in r.runs[name].views],
        )
        for name in chosen
    ]
    symmetric_names = set(YCB_SYMMETRIC if symmetric is None else symmetric)

    if evaluated:
        table = Table(
            title=f"{views} rendered views per object (seed {seed}, {occluders} occluders); "
            "correct = error < 0.1 × diameter"
        )
        for column in (
            "object",
            "sym.",
            "method",
            "ADD-S ok",
            "ADD(-S) ok",
            "AUC ADD-S",
            "AUC ADD(-S)",
            "median ms",
            "prepare s",
        ):
            table.add_column(column, justify="left" if column in ("object", "sym.", "method") else "right")
        for obj in [*[r.name for r in evaluated], None]:
            for run in runs:
                views_of = [v for v in run.views if obj is None or v.object == obj]
                s = summarise(views_of)
                prepare = (
                    run.prepare_s[obj] if obj is not None else sorted(run.prepare_s.values())[len(run.prepare_s) // 2]
                )
                table.add_row(
                    obj if obj is not None else "[bold]all[/bold]",
                    ("yes" if obj in symmetric_names else "no") if obj is not None else "",
                    run.name,
                    f"{s.add_s_pass:.0f} %",
                    f"{s.add_or_s_pass:.0f} %",
                    f"{s.auc_add_s:.1f}",
                    f"{s.auc_add_or_s:.1f}",
                    f"{s.median_ms:.1f}",
                    f"{prepare:.2f}",
                )
        _stdout().print(table)
    failed = [r for r in results if r.failed]
    for r in failed:
        _stderr().print(f"[red]error:[/red] {escape(r.error)} ({r.attempts} attempts)")
    if failed:
        raise typer.Exit(1)


def main() -> None:
    """Console-script entry point."""
    app(prog_name="edgepose")


if __name__ == "__main__":
    main()
