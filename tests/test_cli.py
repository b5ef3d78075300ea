"""The command line through its real entry point."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest


def run(*args: str) -> subprocess.CompletedProcess[str]:
    beside_python = Path(sys.executable).with_name("edgepose")
    exe = str(beside_python) if beside_python.exists() else shutil.which("edgepose")
    if exe is None:
        pytest.skip("edgepose entry point not installed")
    return subprocess.run([exe, *args], capture_output=True, text=True, timeout=120)


def test_version_proves_the_core_loads():
    out = run("--version")
    assert out.returncode == 0
    assert "compiled core loaded" in out.stdout


def test_demo_estimates_a_rendered_pose(ycb_dir):
    out = run("demo", "--mesh", str(ycb_dir / "banana.ply"), "--seed", "1")
    assert out.returncode == 0, out.stderr
    assert "codebook    2100 views" in out.stdout
    assert "estimated   T_cam_obj" in out.stdout and "true        T_cam_obj" in out.stdout
    assert "(correct at 0.1 × diameter" in out.stdout


def test_demo_reports_a_missing_mesh_clearly(tmp_path):
    out = run("demo", "--mesh", str(tmp_path / "nope.obj"))
    assert out.returncode == 1
    assert "no such file" in out.stderr
    assert "Traceback" not in out.stderr


def test_module_entry_point_matches_console_script():
    out = subprocess.run([sys.executable, "-m", "edgepose.cli", "--version"], capture_output=True, text=True)
    assert out.returncode == 0 and "edgepose" in out.stdout
