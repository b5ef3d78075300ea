"""The README's Python snippets run as written, in order, in one namespace,
on files made from the shipped example object: a rendered depth PNG and mask
PNG of the power drill (``depth.png``, ``mask.png``, with the README's
intrinsics), its mesh as ``drill.ply`` and the shipped ``codebooks/``."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import SHIPPED
from edgepose.eval import pose_errors, render_view
from edgepose.io import write_png

README = Path(__file__).resolve().parents[1] / "README.md"


def python_snippets() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.DOTALL)


@pytest.fixture
def readme_files(tmp_path, monkeypatch, drill):
    """The files the snippets name, in a fresh working directory; returns the true pose."""
    mesh, _ = drill
    view = render_view(mesh, seed=7)  # LINEMOD intrinsics, as in the README
    write_png(tmp_path / "depth.png", np.round(view.depth * 1000).astype(np.uint16))
    write_png(tmp_path / "mask.png", view.mask.astype(np.uint8) * 255)
    shutil.copy(SHIPPED / "power_drill.ply", tmp_path / "drill.ply")
    (tmp_path / "codebooks").symlink_to(SHIPPED)
    monkeypatch.chdir(tmp_path)
    return view.T_cam_obj


def test_the_readme_has_python_snippets():
    assert len(python_snippets()) >= 2


def test_every_python_snippet_of_the_readme_runs_and_finds_the_pose(readme_files, drill):
    namespace: dict = {}
    for i, snippet in enumerate(python_snippets()):
        try:
            exec(compile(snippet, f"README.md python snippet {i + 1}", "exec"), namespace)
        except Exception as e:  # name the snippet in the failure
            pytest.fail(f"README snippet {i + 1} fails: {type(e).__name__}: {e}\n{snippet}")
    pose = namespace["pose"]
    model = drill[1].model
    errors = pose_errors(model.mesh_points, pose.matrix, readme_files, model.diameter, symmetric=False)
    assert errors.add < 0.1 * model.diameter
    assert Path("drill.codebook").stat().st_size > 100_000  # the build-and-save snippet wrote it
