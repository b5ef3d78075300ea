"""Object catalogues: one codebook per mesh of a folder, built (or evaluated)
one object at a time, on this machine or as Ray tasks on a cluster.

One object is one job, :func:`build_object` or :func:`evaluate_object`; the
same function runs in both executors, so a codebook built by a Ray worker is
byte-for-byte the one a local build writes (saved files hold no timestamps).
A job never raises: it returns an :class:`ObjectResult` (built, skipped,
evaluated or failed, with the error), retrying a failing object a bounded
number of times first.

Resuming: a codebook whose recorded mesh sha256, encoder fingerprint, view
count, model point count and symmetry search
(:data:`edgepose.symmetry.SEARCH_FINGERPRINT`) match the current ones is
*up to date* and skipped, decided from the codebook file alone. Saves are
atomic, so a run killed at any moment leaves whole codebooks only, and
rerunning it builds just what is missing or stale.

Executors: :class:`LocalExecutor` (one object after another, each with every
core, as ``edgepose build`` always did) and :class:`RayExecutor` (one Ray task
per object, ``cpus_per_task`` cores each; results stream back as tasks
finish). Ray is imported only by the latter (``pip install 'edgepose[dist]'``).
On a cluster every node must see the catalogue and the output folder at the
same path (a shared file system) and have edgepose installed.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from edgepose.errors import EdgePoseError
from edgepose.model import DEFAULT_MODEL_POINTS
from edgepose.settings import usable_cores
from edgepose.views import DEFAULT_VIEWS

#: Mesh files picked up from a catalogue folder.
MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".glb", ".gltf")
#: Attempts after the first for an object whose job raised (a bad mesh fails
#: again quickly; a full disk or a flaky network file system may not).
DEFAULT_RETRIES = 2
#: Ray's own re-runs of a task whose worker process or node died.
DEFAULT_SYSTEM_RETRIES = 3
#: CPUs each Ray task reserves (and threads it uses).
DEFAULT_CPUS_PER_TASK = 1


class CatalogError(EdgePoseError):
    """A catalogue that cannot be run: missing paths, no meshes, name clashes."""


@dataclass(frozen=True)
class BuildSettings:
    """How each codebook of a catalogue is built (see :func:`edgepose.build_codebook`)."""

    views: int = DEFAULT_VIEWS
    n_points: int = DEFAULT_MODEL_POINTS
    scale: float | None = None
    """Mesh units → metres; None detects millimetres."""


@dataclass
class ObjectResult:
    """What became of one object of a catalogue run."""

    name: str
    status: str
    """``built``, ``skipped`` (up to date), ``evaluated`` or ``failed``."""
    seconds: float
    """Wall-clock time of the job, retries included."""
    codebook: str = ""
    """Path of the object's codebook (build only)."""
    bytes: int = 0
    """Size of that codebook file."""
    views: int = 0
    error: str = ""
    attempts: int = 1
    runs: dict[str, Any] = field(default_factory=dict)
    """eval only: method name → :class:`edgepose.eval.benchmark.MethodRun` of this object."""
    symmetric: bool = False
    """eval only: judged with ADD-S in ADD(-S)."""

    @property
    def failed(self) -> bool:
        return self.status == "failed"


# ----------------------------------------------------------------- the catalogue


def find_meshes(paths: Iterable[str | os.PathLike]) -> list[Path]:
    """Mesh files given directly or found in folders (not recursive), folders'
    files sorted by name. Two meshes with the same stem would write the same
    codebook, so they are refused."""
    files: list[Path] = []
    for path in map(Path, paths):
        if path.is_dir():
            found = sorted(p for p in path.iterdir() if p.suffix.lower() in MESH_SUFFIXES and p.is_file())
            if not found:
                raise CatalogError(f"{path}: no mesh files ({' '.join(MESH_SUFFIXES)})")
            files.extend(found)
        elif path.is_file():
            files.append(path)
        else:
            raise CatalogError(f"{path}: no such file or folder")
    stems = [f.stem for f in files]
    clashes = sorted({s for s in stems if stems.count(s) > 1})
    if clashes:
        raise CatalogError(f"two meshes would write the same codebook: {', '.join(clashes)}")
    return files


def codebook_path(out_dir: str | os.PathLike, mesh: str | os.PathLike) -> Path:
    """Where a mesh's codebook goes: ``out_dir/<mesh stem>.codebook``."""
    return Path(out_dir) / f"{Path(mesh).stem}.codebook"


def is_up_to_date(codebook: str | os.PathLike, mesh_sha256: str, settings: BuildSettings, encoder=None) -> bool:
    """Whether ``codebook`` is a valid codebook (checksum verified) of the mesh
    whose sha256 is ``mesh_sha256``, made by ``encoder`` (the shipped one by
    default) with ``settings``' views and model points, its symmetries found
    by this edgepose's search. A missing, corrupt, stale or other-encoder
    codebook is not, nor one whose symmetries and near turns an older search
    found (it still works, without what the new search finds). A changed
    ``settings.scale`` is not detected (the codebook records the resulting
    size, not the option)."""
    from edgepose.codebook import Codebook, CodebookError
    from edgepose.symmetry import SEARCH_FINGERPRINT

    try:
        book = Codebook._load(codebook, encoder)  # no warning: a stale codebook is rebuilt here
    except CodebookError:
        return False
    return (
        book.source_sha256 == mesh_sha256
        and len(book) == settings.views
        and len(book.model.points) == settings.n_points
        and book.symmetry_search == SEARCH_FINGERPRINT
    )


# ----------------------------------------------------------------- one object


def build_object(
    mesh: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: BuildSettings = BuildSettings(),
    *,
    threads: int | None = None,
    force: bool = False,
    retries: int = DEFAULT_RETRIES,
) -> ObjectResult:
    """Build one mesh's codebook into ``out_dir`` unless an up-to-date one is
    there (``force`` rebuilds anyway). ``threads``: onnxruntime threads (default
    every core; the Rust map work uses the core's worker threads, as many as
    RAYON_NUM_THREADS says).
    Never raises: errors are retried ``retries`` times, then reported."""
    from edgepose.codebook import build_codebook, file_sha256
    from edgepose.encoder import default_encoder

    mesh, target = Path(mesh), codebook_path(out_dir, mesh)

    def job() -> ObjectResult:
        encoder = default_encoder(threads=threads or usable_cores())
        digest = file_sha256(mesh)
        if not force and is_up_to_date(target, digest, settings, encoder):
            return ObjectResult(mesh.stem, "skipped", 0.0, str(target), target.stat().st_size, settings.views)
        book = build_codebook(
            mesh, views=settings.views, n_points=settings.n_points, scale=settings.scale, encoder=encoder
        )
        book.save(target)
        return ObjectResult(mesh.stem, "built", 0.0, str(target), target.stat().st_size, len(book))

    return _attempt(mesh, job, retries)


def evaluate_object(
    mesh: str | os.PathLike,
    seeds: list[int],
    methods: list[str],
    *,
    symmetric: bool | None = None,
    occluders: int = 0,
    stress: str = "clean",
    retries: int = DEFAULT_RETRIES,
) -> ObjectResult:
    """Render one view of a mesh per seed (at the ``stress`` level of
    :data:`edgepose.eval.STRESS_LEVELS`) and run each pose method (names of
    :data:`edgepose.eval.methods.METHODS`) on them
    (:func:`edgepose.eval.benchmark.run_method`); the result's ``runs`` hold
    the per-view scores. Never raises (see :func:`build_object`)."""
    from edgepose.eval.benchmark import load_object, run_method
    from edgepose.eval.methods import create_method

    mesh = Path(mesh)

    def job() -> ObjectResult:
        obj = load_object(mesh, seeds, symmetric=symmetric, occluders=occluders, stress=stress)
        runs = {}
        for name in methods:
            runs[name] = run_method(create_method(name), [obj])
        return ObjectResult(mesh.stem, "evaluated", 0.0, views=len(seeds), runs=runs, symmetric=obj.symmetric)

    return _attempt(mesh, job, retries)


def _attempt(mesh: Path, job: Callable[[], ObjectResult], retries: int) -> ObjectResult:
    """Run ``job`` up to ``1 + retries`` times; the last error (naming the mesh
    file) becomes a failed result."""
    t0 = time.perf_counter()
    attempts, error = 0, ""
    while attempts <= max(retries, 0):
        attempts += 1
        try:
            result = job()
        except Exception as e:  # one object's failure is a result, never the end of the run
            error = str(e) if isinstance(e, EdgePoseError) else f"{type(e).__name__}: {e}"
            error = error if str(mesh) in error else f"{mesh}: {error}"
            continue
        result.seconds, result.attempts = time.perf_counter() - t0, attempts
        return result
    return ObjectResult(mesh.stem, "failed", time.perf_counter() - t0, error=error, attempts=attempts)


# ----------------------------------------------------------------- executors


class LocalExecutor:
    """One object after another in this process, each with every core."""

    threads = usable_cores()

    def map(self, function: Callable[..., ObjectResult], jobs: list[tuple[str, dict]]) -> Iterator[ObjectResult]:
        """``function(**kwargs)`` for each ``(name, kwargs)`` job, in order."""
        for _, kwargs in jobs:
            yield function(**kwargs)


class RayExecutor:
    """One Ray task per object, results yielded as the tasks finish.

    ``address``: a running cluster (``"auto"``, ``"ray://host:10001"``, ``"host:6379"``),
    or None: the cluster in ``RAY_ADDRESS`` if set, else a Ray instance started
    on this machine (``num_cpus`` of its cores, default all) and stopped at the end.
    Each task reserves ``cpus_per_task`` CPUs and uses that many threads for
    onnxruntime and the Rust core (RAYON_NUM_THREADS, OMP_NUM_THREADS), so
    tasks sharing a node do not oversubscribe it. A task whose worker or node
    dies is re-run by Ray up to ``system_retries`` times, then reported failed.
    """

    def __init__(
        self,
        address: str | None = None,
        *,
        cpus_per_task: int = DEFAULT_CPUS_PER_TASK,
        num_cpus: int | None = None,
        system_retries: int = DEFAULT_SYSTEM_RETRIES,
    ) -> None:
        if cpus_per_task < 1:
            raise CatalogError(f"cpus per task must be at least 1, got {cpus_per_task}")
        self.address, self.cpus_per_task, self.num_cpus = address, cpus_per_task, num_cpus
        self.system_retries = system_retries
        self.threads = cpus_per_task

    def map(self, function: Callable[..., ObjectResult], jobs: list[tuple[str, dict]]) -> Iterator[ObjectResult]:
        """``function(**kwargs)`` for each ``(name, kwargs)`` job, as Ray tasks,
        in the order they finish."""
        try:
            import ray
        except ImportError:
            raise CatalogError("--ray needs Ray: pip install 'edgepose[dist]'") from None

        started = self._connect(ray)
        try:
            threads = str(self.cpus_per_task)
            task = ray.remote(function).options(
                num_cpus=self.cpus_per_task,
                max_retries=self.system_retries,
                retry_exceptions=False,  # jobs return their errors; _attempt retries them
                runtime_env={"env_vars": {"RAYON_NUM_THREADS": threads, "OMP_NUM_THREADS": threads}},
            )
            queue = list(reversed(jobs))
            pending: dict[Any, str] = {}
            while queue or pending:
                # Submit a bounded window, so a 10,000-object catalogue does not
                # put 10,000 tasks (and their results) in flight at once; the
                # window follows the cluster's size as nodes join.
                window = max(4, 2 * int(ray.cluster_resources().get("CPU", 1)) // self.cpus_per_task)
                while queue and len(pending) < window:
                    name, kwargs = queue.pop()
                    pending[task.remote(**kwargs)] = name
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    name = pending.pop(ref)
                    try:
                        yield ray.get(ref)
                    except ray.exceptions.RayError as e:  # the task's worker or node died, retries spent
                        yield ObjectResult(
                            name,
                            "failed",
                            0.0,
                            error=f"{name}: {type(e).__name__}: {e}",
                            attempts=1 + self.system_retries,
                        )
        finally:
            if started:
                ray.shutdown()

    def _connect(self, ray) -> bool:
        """Join or start Ray; True when this call started it (and so stops it)."""
        if ray.is_initialized():
            return False
        import logging

        local = self.address is None and not os.environ.get("RAY_ADDRESS")
        ray.init(
            address=self.address,
            num_cpus=self.num_cpus if local else None,
            include_dashboard=False if local else None,
            log_to_driver=False,
            logging_level=logging.WARNING,
        )
        return True


# ----------------------------------------------------------------- catalogue runs


def build_catalog(
    meshes: list[Path],
    out_dir: str | os.PathLike,
    settings: BuildSettings = BuildSettings(),
    *,
    executor: LocalExecutor | RayExecutor | None = None,
    force: bool = False,
    retries: int = DEFAULT_RETRIES,
    on_result: Callable[[ObjectResult], None] | None = None,
) -> list[ObjectResult]:
    """Build (or skip, when up to date) every mesh's codebook into ``out_dir``;
    results in ``meshes``' order. ``on_result`` sees each as it arrives."""
    executor = executor or LocalExecutor()
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    jobs = [
        (
            m.stem,
            {
                "mesh": str(m),
                "out_dir": str(out_dir),
                "settings": settings,
                "threads": executor.threads,
                "force": force,
                "retries": retries,
            },
        )
        for m in meshes
    ]
    return _collect(executor.map(build_object, jobs), [m.stem for m in meshes], on_result)


def evaluate_catalog(
    meshes: list[Path],
    seeds: Callable[[int], list[int]],
    methods: list[str],
    *,
    symmetric: Callable[[str], bool | None] = lambda name: None,
    occluders: int = 0,
    stress: str = "clean",
    executor: LocalExecutor | RayExecutor | None = None,
    retries: int = DEFAULT_RETRIES,
    on_result: Callable[[ObjectResult], None] | None = None,
) -> list[ObjectResult]:
    """Evaluate ``methods`` on each mesh (object k gets ``seeds(k)``); results in
    ``meshes``' order."""
    executor = executor or LocalExecutor()
    jobs = [
        (
            m.stem,
            {
                "mesh": str(m),
                "seeds": seeds(k),
                "methods": methods,
                "symmetric": symmetric(m.stem),
                "occluders": occluders,
                "stress": stress,
                "retries": retries,
            },
        )
        for k, m in enumerate(meshes)
    ]
    return _collect(executor.map(evaluate_object, jobs), [m.stem for m in meshes], on_result)


def _collect(results: Iterator[ObjectResult], names: list[str], on_result) -> list[ObjectResult]:
    by_name = {}
    for result in results:
        by_name[result.name] = result
        if on_result is not None:
            on_result(result)
    return [by_name[name] for name in names]
