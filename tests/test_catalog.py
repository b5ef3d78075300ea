"""Catalogue builds and evaluations (edgepose.catalog, ``edgepose build/eval
[--ray]``): locally and on a real local Ray instance (2 CPUs), on real mesh
files. Ray builds must write the same bytes as local ones; reruns skip what
is up to date and rebuild what is not; one bad object never ends a run."""

from __future__ import annotations

import hashlib
import shutil
import warnings
from pathlib import Path

import edgepose
import numpy as np
import pytest
from edgepose.catalog import (
    BuildSettings,
    CatalogError,
    LocalExecutor,
    RayExecutor,
    build_catalog,
    build_object,
    find_meshes,
)
from edgepose.symmetry import SEARCH_FINGERPRINT
from test_cli import run
from test_codebook import _resealed

SETTINGS = BuildSettings(views=300)


def write_catalogue(folder: Path) -> Path:
    """Three small meshes in metres: a box, a cylinder and an L-bracket of two boxes."""
    import trimesh

    folder.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=(0.08, 0.05, 0.03)).export(folder / "box.stl")
    trimesh.creation.cylinder(radius=0.03, height=0.1, sections=48).export(folder / "cylinder.ply")
    foot = trimesh.creation.box(extents=(0.1, 0.02, 0.02))
    upright = trimesh.creation.box(extents=(0.02, 0.02, 0.06))
    upright.apply_translation((0.04, 0.0, 0.04))
    trimesh.util.concatenate([foot, upright]).export(folder / "bracket.obj")
    return folder


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def books(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.glob("*.codebook"))}


def mtimes(folder: Path) -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in folder.glob("*.codebook")}


@pytest.fixture(scope="module")
def catalogue(tmp_path_factory) -> Path:
    return write_catalogue(tmp_path_factory.mktemp("catalogue") / "meshes")


@pytest.fixture(scope="module")
def local_books(catalogue, tmp_path_factory) -> Path:
    """The catalogue built locally (one object after another)."""
    out = tmp_path_factory.mktemp("local")
    results = build_catalog(find_meshes([catalogue]), out, SETTINGS)
    assert [(r.name, r.status) for r in results] == [("box", "built"), ("bracket", "built"), ("cylinder", "built")]
    return out


@pytest.fixture(scope="module")
def ray_cluster():
    """A Ray instance on this machine, for this module."""
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def copy_of(folder: Path, to: Path) -> Path:
    shutil.copytree(folder, to)
    return to


# ----------------------------------------------------------------- local


def test_local_build_records_each_mesh_hash_in_its_codebook(catalogue, local_books):
    for mesh in find_meshes([catalogue]):
        book = edgepose.Codebook.load(local_books / f"{mesh.stem}.codebook")
        assert book.source_sha256 == sha256(mesh)
        assert len(book) == 300 and len(book.model.points) == 4096
    # Built from memory, a codebook records no source.
    import trimesh

    assert edgepose.build_codebook(trimesh.creation.box(extents=(0.05, 0.04, 0.03)), views=64).source_sha256 is None


def test_the_source_hash_is_covered_by_the_checksum(local_books, tmp_path):
    from safetensors.numpy import load_file

    blob = (local_books / "box.codebook").read_bytes()
    digest = edgepose.Codebook.load(local_books / "box.codebook").source_sha256
    altered = blob.replace(digest.encode(), digest[::-1].encode())
    assert altered != blob and len(altered) == len(blob)
    (tmp_path / "box.codebook").write_bytes(altered)
    assert load_file(tmp_path / "box.codebook").keys()  # still a readable safetensors file
    with pytest.raises(edgepose.CodebookError, match="checksum mismatch"):
        edgepose.Codebook.load(tmp_path / "box.codebook")


def test_rerun_skips_up_to_date_codebooks(catalogue, local_books):
    before, times = books(local_books), mtimes(local_books)
    results = build_catalog(find_meshes([catalogue]), local_books, SETTINGS)
    assert [r.status for r in results] == ["skipped"] * 3
    assert all(r.bytes == len(before[f"{r.name}.codebook"]) for r in results)
    assert books(local_books) == before and mtimes(local_books) == times


def test_other_views_corrupt_files_and_force_are_rebuilt(catalogue, local_books, tmp_path):
    out = copy_of(local_books, tmp_path / "books")
    box = out / "box.codebook"
    box.write_bytes(box.read_bytes()[:-100] + bytes(100))  # corrupt: checksum fails
    results = build_catalog(find_meshes([catalogue]), out, SETTINGS)
    assert [(r.name, r.status) for r in results] == [("box", "built"), ("bracket", "skipped"), ("cylinder", "skipped")]
    assert books(out) == books(local_books)

    results = build_catalog(find_meshes([catalogue]), out, BuildSettings(views=64))
    assert [r.status for r in results] == ["built"] * 3
    assert all(len(edgepose.Codebook.load(out / f"{n}.codebook")) == 64 for n in ("box", "bracket", "cylinder"))

    mesh = catalogue / "box.stl"
    assert build_object(mesh, out, BuildSettings(views=64)).status == "skipped"
    assert build_object(mesh, out, BuildSettings(views=64), force=True).status == "built"


def test_a_codebook_of_another_encoder_is_rebuilt(catalogue, local_books, tmp_path):
    out = copy_of(local_books, tmp_path / "books")
    cylinder = out / "cylinder.codebook"
    other = hashlib.sha256(b"another encoder").hexdigest()
    cylinder.write_bytes(_resealed(cylinder.read_bytes(), lambda m: m.update(encoder=other)))  # a valid file
    with pytest.raises(edgepose.CodebookError, match="built by encoder"):
        edgepose.Codebook.load(out / "cylinder.codebook")

    results = build_catalog(find_meshes([catalogue]), out, SETTINGS)
    assert [(r.name, r.status) for r in results] == [("box", "skipped"), ("bracket", "skipped"), ("cylinder", "built")]
    assert books(out) == books(local_books)


@pytest.mark.parametrize("search", ["an older search", None])
def test_a_codebook_whose_symmetries_an_older_search_found_is_rebuilt(catalogue, local_books, tmp_path, search):
    out = copy_of(local_books, tmp_path / "books")
    bracket = out / "bracket.codebook"

    def older(metadata: dict) -> None:
        assert metadata["symmetry_search"] == SEARCH_FINGERPRINT
        if search is None:  # saved by an edgepose that recorded no search
            del metadata["symmetry_search"]
        else:
            metadata["symmetry_search"] = search

    bracket.write_bytes(_resealed(bracket.read_bytes(), older))  # a valid file, still usable
    with pytest.warns(edgepose.StaleCodebookWarning, match="older or unknown symmetry search"):
        assert edgepose.Codebook.load(out / "bracket.codebook").symmetry_search == search

    with warnings.catch_warnings():
        warnings.simplefilter("error", edgepose.StaleCodebookWarning)  # the up-to-date check must not warn
        results = build_catalog(find_meshes([catalogue]), out, SETTINGS)
    assert [(r.name, r.status) for r in results] == [("box", "skipped"), ("bracket", "built"), ("cylinder", "skipped")]
    assert books(out) == books(local_books)


def test_find_meshes_refuses_clashes_and_empty_folders(catalogue, tmp_path):
    with pytest.raises(CatalogError, match="same codebook: box"):
        find_meshes([catalogue, catalogue / "box.stl"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(CatalogError, match="no mesh files"):
        find_meshes([tmp_path / "empty"])
    with pytest.raises(CatalogError, match="no such file or folder"):
        find_meshes([tmp_path / "missing"])


# ----------------------------------------------------------------- Ray


def test_ray_build_is_byte_identical_to_the_local_build(ray_cluster, catalogue, local_books, tmp_path):
    seen = []
    results = build_catalog(
        find_meshes([catalogue]), tmp_path, SETTINGS, executor=RayExecutor(), on_result=lambda r: seen.append(r.name)
    )
    assert [(r.name, r.status, r.attempts) for r in results] == [
        ("box", "built", 1),
        ("bracket", "built", 1),
        ("cylinder", "built", 1),
    ]
    assert sorted(seen) == ["box", "bracket", "cylinder"]  # streamed, in the order they finished
    assert books(tmp_path) == books(local_books) and len(books(tmp_path)) == 3


def test_ray_rerun_rebuilds_only_the_changed_mesh(ray_cluster, catalogue, local_books, tmp_path):
    import trimesh

    meshes = copy_of(catalogue, tmp_path / "meshes")
    out = copy_of(local_books, tmp_path / "books")
    times = mtimes(out)
    trimesh.creation.box(extents=(0.09, 0.05, 0.03)).export(meshes / "box.stl")  # the box changed
    results = build_catalog(find_meshes([meshes]), out, SETTINGS, executor=RayExecutor())
    assert [(r.name, r.status) for r in results] == [("box", "built"), ("bracket", "skipped"), ("cylinder", "skipped")]
    new_box = edgepose.Codebook.load(out / "box.codebook")
    assert new_box.source_sha256 == sha256(meshes / "box.stl")
    assert new_box.model.diameter == pytest.approx(np.linalg.norm([0.09, 0.05, 0.03]), rel=0.03)
    changed = {name for name, t in mtimes(out).items() if t != times[name]}
    assert changed == {"box.codebook"}


def test_ray_reports_a_broken_mesh_after_retries_and_builds_the_others(ray_cluster, catalogue, tmp_path):
    meshes = copy_of(catalogue, tmp_path / "meshes")
    (meshes / "broken.obj").write_text("v 0 0 0\nf 1 1 1\n")
    results = build_catalog(find_meshes([meshes]), tmp_path / "books", SETTINGS, executor=RayExecutor(), retries=2)
    status = {r.name: (r.status, r.attempts) for r in results}
    assert status == {"box": ("built", 1), "bracket": ("built", 1), "broken": ("failed", 3), "cylinder": ("built", 1)}
    broken = next(r for r in results if r.failed)
    assert "broken.obj" in broken.error and "zero surface area" in broken.error
    assert sorted(books(tmp_path / "books")) == ["box.codebook", "bracket.codebook", "cylinder.codebook"]


def test_ray_reports_a_task_whose_worker_died_and_finishes_the_others(ray_cluster, catalogue, tmp_path):
    def build_or_die(mesh: str, **options):
        if "cylinder" in mesh:
            import os

            os._exit(3)  # the worker process dies: a system failure, re-run by Ray, then reported
        return build_object(mesh, **options)

    jobs = [
        (m.stem, {"mesh": str(m), "out_dir": str(tmp_path), "settings": SETTINGS}) for m in find_meshes([catalogue])
    ]
    results = {r.name: r for r in RayExecutor(system_retries=1).map(build_or_die, jobs)}
    assert results["box"].status == "built" and results["bracket"].status == "built"
    assert results["cylinder"].failed and results["cylinder"].attempts == 2
    assert "cylinder" in results["cylinder"].error and "Worker" in results["cylinder"].error
    assert not (tmp_path / "cylinder.codebook").exists()


# ----------------------------------------------------------------- command line


def test_cli_build_through_ray_matches_local_and_resumes(ray_cluster, catalogue, local_books, tmp_path):
    address = ray_cluster.get_runtime_context().gcs_address
    out = run("build", str(catalogue), "-o", str(tmp_path), "--views", "300", "--ray-address", address)
    assert out.returncode == 0, out.stderr
    assert "3 built, 0 up to date" in out.stderr and "objects/min, Ray" in out.stderr
    assert books(tmp_path) == books(local_books)

    (tmp_path / "bracket.codebook").unlink()  # as if the run had been killed before the bracket
    out = run("build", str(catalogue), "-o", str(tmp_path), "--views", "300", "--ray-address", address)
    assert out.returncode == 0, out.stderr
    assert "1 built, 2 up to date (skipped), 0 failed" in out.stderr
    rows = {
        line.split("│")[1].strip(): line.split("│")[2].strip()
        for line in out.stdout.splitlines()
        if line.count("│") > 3
    }
    assert rows == {"box": "skipped", "bracket": "built", "cylinder": "skipped"}
    assert books(tmp_path) == books(local_books)


def test_cli_build_locally_reports_a_broken_mesh_and_exits_1(catalogue, local_books, tmp_path):
    meshes = copy_of(catalogue, tmp_path / "meshes")
    (meshes / "broken.obj").write_text("v 0 0 0\nf 1 1 1\n")
    out = run("build", str(meshes), "-o", str(tmp_path / "books"), "--views", "300", "--retries", "1")
    assert out.returncode == 1
    assert "3 built, 0 up to date (skipped), 1 failed" in out.stderr
    assert "broken.obj: mesh has zero surface area" in out.stderr and "(2 attempts)" in out.stderr
    assert "Traceback" not in out.stderr
    assert books(tmp_path / "books") == books(local_books)


def test_cli_eval_through_ray_gives_the_local_table(ray_cluster, catalogue):
    def tables(out) -> tuple[list[list[str]], list[list[str]]]:
        """The accuracy table's rows (object … AUC ADD(-S); not the latencies and
        build times) and the confidence table's rows."""
        assert out.returncode == 0, out.stderr
        accuracy, confidence = out.stdout.split("confidence at stress")

        def rows(text: str) -> list[list[str]]:
            return [
                [c.strip() for c in line.strip("│ ").split("│")] for line in text.splitlines() if line.count("│") > 5
            ]

        return [row[:7] for row in rows(accuracy)], rows(confidence)

    args = ("eval", str(catalogue / "box.stl"), str(catalogue / "bracket.obj"), "--views", "3", "--seed", "2")
    local, local_confidence = tables(run(*args))
    on_ray, ray_confidence = tables(run(*args, "--ray-address", ray_cluster.get_runtime_context().gcs_address))
    assert [row[0] for row in local] == ["box", "bracket", "all"]
    assert on_ray == local and ray_confidence == local_confidence
    assert all(row[3].endswith("%") for row in local)
    assert [row[0] for row in local_confidence] == ["edgepose"]


def test_local_executor_runs_jobs_in_order(catalogue, tmp_path):
    jobs = [
        (m.stem, {"mesh": str(m), "out_dir": str(tmp_path), "settings": BuildSettings(views=64)})
        for m in find_meshes([catalogue])
    ]
    assert [r.name for r in LocalExecutor().map(build_object, jobs)] == ["box", "bracket", "cylinder"]


def test_cli_eval_reports_a_broken_mesh_by_its_file(tmp_path):
    (tmp_path / "broken.obj").write_text("v 0 0 0\nf 1 1 1\n")
    out = run("eval", str(tmp_path / "broken.obj"), "--views", "1")
    assert out.returncode == 1 and "Traceback" not in out.stderr
    assert f"error: {tmp_path / 'broken.obj'}: " in out.stderr and "zero surface area" in out.stderr
    assert "(3 attempts)" in out.stderr and "ADD-S" not in out.stdout
