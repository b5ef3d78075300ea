"""The ``edgepose`` command line: ``demo``, ``build``, ``estimate``, ``track``, ``eval``, ``bop``.

Heavy imports (onnxruntime, trimesh, rich) happen inside the commands, so
``--help`` is quick. Deliberate errors print one ``error: …`` line on stderr
and exit with status 1; usage errors exit with status 2.

``app.py`` holds the typer app and what the commands share; ``pose.py`` the
commands on one object's pose (demo, estimate); ``track.py`` one object
through a sequence of frames; ``catalog.py`` those on a catalogue of meshes
(build, eval); ``bop.py`` a BOP-format dataset, run and scored.
"""

from edgepose.cli.app import DEMO_OBJECT, SHIPPED_DIR, app, command
from edgepose.cli.bop import bop
from edgepose.cli.catalog import build, evaluate
from edgepose.cli.pose import demo, estimate
from edgepose.cli.track import track

# In the order --help lists them.
command()(demo)
command()(build)
command()(estimate)
command()(track)
command("eval")(evaluate)
command()(bop)

__all__ = ["DEMO_OBJECT", "SHIPPED_DIR", "app", "main"]


def main() -> None:
    """Console-script entry point."""
    app(prog_name="edgepose")
