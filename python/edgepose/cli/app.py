"""The ``edgepose`` typer app and what its commands share: error handling,
consoles, options, ``--version``.
"""

import inspect
import sys
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, TextIO

import typer

if TYPE_CHECKING:
    from edgepose.catalog import ObjectResult

#: Codebooks shipped inside the package (``codebooks/`` in a checkout links here),
#: with the mesh of the demo object.
SHIPPED_DIR = Path(__file__).resolve().parents[1] / "codebooks"
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

  [dim]# one object through a sequence of depth frames (PNGs + masks of the same names); poses.csv[/dim]
  [cyan]edgepose track -c mug.codebook frames/ --K cam.json --masks masks/ -o poses.csv[/cyan]

  [dim]# accuracy, latency and confidence quality on rendered views with known poses[/dim]
  [cyan]edgepose eval ../shared/data/ycb --views 20[/cyan]
  [cyan]edgepose eval ../shared/data/ycb --stress visible70 --reliability rel.png[/cyan]

  [dim]# a BOP dataset (LM-O, T-LESS, YCB-V…): codebooks, poses, the BOP results CSV and AR[/dim]
  [cyan]edgepose bop lmo/ -o results/[/cyan]
  [cyan]edgepose bop lmo/ --scenes 2 --masks cnos-fastsam_lmo-test.json[/cyan]

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

# Options of more than one command.
ScaleOption = Annotated[float | None, typer.Option(help="Mesh file units → metres (default: detect mm).")]
RerunOption = Annotated[bool, typer.Option("--rerun", help="Also log to a rerun viewer (viz extra).")]
RrdOption = Annotated[Path | None, typer.Option(help="Also save a rerun recording (.rrd, viz extra).")]
CodebookOption = Annotated[Path, typer.Option("-c", "--codebook", help="The object's codebook (edgepose build).")]
IntrinsicsOption = Annotated[
    str | None, typer.Option("--K", help="Depth camera intrinsics: a JSON file or 9 numbers (row-major 3×3).")
]
DepthScaleOption = Annotated[float, typer.Option(help="Depth units per metre (1000 for millimetre PNGs).")]
RayOption = Annotated[
    bool,
    typer.Option(
        "--ray",
        help="Run one Ray task per object: on the cluster in RAY_ADDRESS, else on a Ray instance started on this "
        "machine (dist extra).",
    ),
]
RayAddressOption = Annotated[
    str | None,
    typer.Option(help="With --ray (implied): the Ray cluster to join, e.g. auto, host:6379 or ray://host:10001."),
]


class Failure(Exception):
    """A CLI-level error: printed as one line, exit status 1."""


@contextmanager
def handle_errors() -> Iterator[None]:
    """Turn deliberate errors into one stderr line and exit status 1, and a
    stale codebook's warning into one stderr line (not Python's two, with
    a source line)."""
    from rich.markup import escape

    from edgepose.codebook import StaleCodebookWarning
    from edgepose.errors import EdgePoseError

    with warnings.catch_warnings():
        show_other = warnings.showwarning

        def show(
            message: Warning | str,
            category: type[Warning],
            filename: str,
            lineno: int,
            file: TextIO | None = None,
            line: str | None = None,
        ) -> None:
            if issubclass(category, StaleCodebookWarning):
                stderr_console().print(f"[yellow]warning:[/yellow] {escape(str(message))}")
            else:
                show_other(message, category, filename, lineno, file, line)

        warnings.showwarning = show
        try:
            yield
        except (EdgePoseError, Failure) as e:
            stderr_console().print(f"[red]error:[/red] {escape(str(e))}")
            raise typer.Exit(1) from None


def stdout_console():
    """Standard output as a rich console."""
    from rich.console import Console

    # Piped output keeps whole table rows (rich would assume 80 columns).
    return Console(soft_wrap=True, highlight=False, width=None if sys.stdout.isatty() else 160)


def stderr_console():
    """Standard error as a rich console (errors, progress, summaries)."""
    from rich.console import Console

    return Console(stderr=True, soft_wrap=True, highlight=False)


def _version(value: bool) -> None:
    """``--version``: print the versions and exit."""
    if not value:
        return
    from edgepose.report import version_text

    with handle_errors():
        text = version_text()
    print(text)
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


def exit_if_failed(results: "list[ObjectResult]") -> None:
    """Print each failed object's error on stderr; exit status 1 if any."""
    from rich.markup import escape

    failed = [r for r in results if r.failed]
    for r in failed:
        stderr_console().print(f"[red]error:[/red] {escape(r.error)} ({r.attempts} attempts)")
    if failed:
        raise typer.Exit(1)


def executor_for(ray: bool, address: str | None, cpus_per_task: int):
    """None (run locally) or a Ray executor."""
    if not ray:
        return None
    from edgepose.catalog import RayExecutor

    return RayExecutor(address, cpus_per_task=cpus_per_task)
