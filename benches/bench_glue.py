"""Where an estimate's time goes, stage by stage: inside the Rust core and
ONNX Runtime, or in the Python around their calls (the stage functions,
numpy on small arrays, the objects passed between stages). The share left
in Python says how much moving a stage's glue into the core could save.

    .venv/bin/python benches/bench_glue.py [--level clean] [--views 20] [--repeats 3] [--frame]

Views: ``bench_against.py``'s (the pose benchmark's five YCB meshes,
``--views`` per mesh at ``--level``), each estimated once to warm up and
then ``--repeats`` times, from the cloud alone (``--frame``: given the
depth frame too); codebooks built for the run. Every call into the core
(``edgepose._core``'s functions, a codebook's ``ModelIndex`` and the
flip-margin search it hands back, the confidence model's curves) and every
onnxruntime ``run`` is timed, and its time charged to the stage
(``Pose.timings``) it ran in; the rest of the stage's time is Python. The
timing adds about a microsecond a call (tens of calls an estimate),
charged to Python. Printed: per stage, ms per estimate (mean) in all, in
the core and onnxruntime, and in Python, and Python's share.
"""

from __future__ import annotations

import argparse
import functools
import pickle
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: Seconds spent in timed calls so far (one thread: ``estimate``).
NATIVE = [0.0]


def timed(call):
    """``call``, its time added to :data:`NATIVE` (calls inside it not twice)."""
    if getattr(call, "_timed", False):
        return call

    @functools.wraps(call)
    def run(*args, **kwargs):
        start = time.perf_counter()
        try:
            return call(*args, **kwargs)
        finally:
            NATIVE[0] += time.perf_counter() - start

    run._timed = True
    return run


class Timed:
    """An object of the core (a codebook's ``ModelIndex``, a confidence
    model's curves) whose methods are :func:`timed`; the objects that the
    methods named in ``handing`` return are wrapped too (the flip-margin
    search, whose ``result()`` waits for another core)."""

    def __init__(self, inner, handing: tuple[str, ...] = ()) -> None:
        self._inner, self._handing = inner, handing

    def __getattr__(self, name: str):
        found = getattr(self._inner, name)
        if not callable(found):
            return found
        if name in self._handing:
            return lambda *args, **kwargs: Timed(timed(found)(*args, **kwargs))
        return timed(found)


def instrument(codebooks: list, encoder) -> dict[str, list[float]]:
    """Times the core's functions, the codebooks' indexes and the encoder's
    sessions; returns, per stage name, the timed seconds of each lap."""
    from edgepose import _core, search

    for name in dir(_core):
        found = getattr(_core, name)
        if callable(found) and not name.startswith("_") and not isinstance(found, type):
            setattr(_core, name, timed(found))
    _core.DepthGrid = timed(_core.DepthGrid)
    for codebook in codebooks:
        object.__setattr__(codebook, "index", Timed(codebook.index, handing=("flip_margin",)))
    for model in {id(m): m for m in (encoder.confidence, encoder.scene_confidence) if m is not None}.values():
        object.__setattr__(model, "_curves", Timed(model._curves))
    for session in (encoder._encoder, encoder._encoder_one_map, encoder._irr):
        session.run = timed(session.run)
    laps: dict[str, list[float]] = {}
    start, lap = search.Laps.__init__, search.Laps.__call__

    def started(self) -> None:
        start(self)
        self.native = NATIVE[0]

    def ended(self, stage: str) -> None:
        lap(self, stage)
        laps.setdefault(stage, []).append(NATIVE[0] - self.native)
        self.native = NATIVE[0]

    search.Laps.__init__, search.Laps.__call__ = started, ended
    return laps


def main() -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import edgepose
    from bench_against import rendered
    from bench_pose import RENDERED_VIEWS
    from edgepose.encoder import default_encoder

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--level", default="clean", help="stress level (edgepose.eval.stress.STRESS_LEVELS)")
    parser.add_argument("--views", type=int, default=RENDERED_VIEWS, help="views per mesh")
    parser.add_argument("--repeats", type=int, default=3, help="timed estimates of each view")
    parser.add_argument("--frame", action="store_true", help="estimate given the depth frame too")
    args = parser.parse_args()
    work, books = [], []
    with tempfile.TemporaryDirectory() as folder:
        for name, mesh, clouds, frames in pickle.loads(rendered(args.level, args.views).read_bytes()):
            path = Path(folder) / f"{name}.npz"
            edgepose.build_codebook(mesh).save(path)
            books.append(edgepose.Codebook.load(path))
            for cloud, (depth, K) in zip(clouds, frames):
                work.append((cloud, books[-1], {"depth": depth, "K": K, "depth_scale": 1.0} if args.frame else {}))
    native = instrument(books, default_encoder())
    for cloud, codebook, scene in work:
        edgepose.estimate(cloud, codebook, **scene)
    for laps in native.values():
        laps.clear()
    spent: dict[str, float] = {}
    totals = []
    for _ in range(args.repeats):
        for cloud, codebook, scene in work:
            pose = edgepose.estimate(cloud, codebook, **scene)
            totals.append(pose.timings["total"])
            for stage, seconds in pose.timings.items():
                spent[stage] = spent.get(stage, 0.0) + seconds
    n = len(totals)
    source = "given the frame" if args.frame else "from clouds"
    print(f"{n} estimates ({len(work)} views × {args.repeats}), {args.level}, {source}")
    print(f"median estimate {1e3 * np.median(totals):.3f} ms; ms per estimate (mean):")
    print(f"  {'stage':<20}{'all':>8}{'native':>8}{'python':>8}{'share':>7}")
    rows = [(stage, spent[stage], sum(native.get(stage, []))) for stage in spent if stage != "total"]
    whole = sum(s for _, s, _ in rows), sum(c for _, _, c in rows)
    for stage, seconds, inside in [*rows, ("all stages", *whole)]:
        glue = seconds - inside
        print(
            f"  {stage:<20}{1e3 * seconds / n:>8.3f}{1e3 * inside / n:>8.3f}{1e3 * glue / n:>8.3f}"
            f"{100 * glue / max(seconds, 1e-12):>6.0f}%"
        )


if __name__ == "__main__":
    main()
