"""What the confidence costs an estimate, with the flip rival handed to one
of the Rust core's threads before the final ICP polish and found after the
polish in the caller's thread (``EstimateSettings.refine.flip_rival_beside_polish``
on and off), in one process; or, with ``--setting refine.coarse_icp_on_two_cores``
(``retrieve.candidates_on_two_cores``), what sharing the first search's
coarse ICPs (the candidates' alignment and scores) with a second core
saves; or,
with ``--setting refine.tie_polish_within``, what polishing near ties costs (its
default against 0, which turns it off).

    .venv/bin/python benches/bench_confidence_cost.py [--repeats 9] [--setting NAME] [--levels L1,L2]

Views: eight training CAD parts (never YCB; six of them ``bench_pose.py
--tune``'s, plus two near-symmetric ones, where the flip margin matters),
each scaled to a diameter drawn in 8–25 cm, 3 views at each of
``--levels`` (default clean, visible40, spill5, occluded30_spill5), seeds
from 777900.
Each view is estimated ``--repeats`` times in each mode, the modes
interleaved; per view the median of each is kept. Printed: the median over
views of the total, of the ``refine_hypotheses`` and ``confidence`` laps,
of :func:`edgepose.stages.polished` (the rival search started, then the
polish), of its two parts (``rival start``: :class:`edgepose.stages.RivalSearch`
made, and handed to a core thread when on; ``polish``: :func:`edgepose.stages.polish`),
and of getting the rival (:meth:`edgepose.stages.RivalSearch.get`, inside
the confidence lap: the wait, if any, when on; the search itself when
off); the per-view paired difference of the totals, over all views and at
each level; and the confidence's
own cost per estimate in each mode, per view: rival start + confidence
lap, plus, when on, the polish's time on minus off (what the rival
running beside it costs the polish); and the rival search alone, called
back to back on each view's pose (warm caches), against the same search
inside an estimate ("off" mode's ``rival get``): the work, and what
running it cold, after the rest of the estimate, adds. Both two-core modes give the same
poses and confidences (checked); the near-tie polish may change a pose
(counted, with the estimates in which it polished a tie, and the time
spent in :func:`edgepose.stages.pick_hypothesis`, which scores the
hypotheses and polishes a tie). The machine is noisy: compare
the modes, not runs.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator
from pathlib import Path

import edgepose
import numpy as np
import trimesh
from edgepose import stages
from edgepose.encoder import Encoder, default_encoder
from edgepose.eval.benchmark import load_object
from edgepose.model import load_model, read_mesh
from edgepose.settings import DEFAULT_SETTINGS
from edgepose.stages import refine

CAD = Path(__file__).resolve().parents[2] / "shared" / "data" / "train_shapes" / "cad"
PARTS = [
    "bunny.ply",
    "fandisk.obj",
    "teapot.stl",
    "suzanne.ply",
    "idler_riser.STL",
    "busted.STL",
    "box.STL",
    "angle_block.STL",
]
LEVELS = "clean,visible40,spill5,occluded30_spill5"
SEED_BASE = 777_900
#: The settings that put work on a second core; each is compared on and off,
#: and must give the same poses ...
TWO_CORE_SETTINGS = [
    "refine.flip_rival_beside_polish",
    "refine.coarse_icp_on_two_cores",
    "retrieve.candidates_on_two_cores",
]
#: ... and those compared at their default ("on") and their "off" value.
COMPARED_AGAINST = {
    **{name: (True, False) for name in TWO_CORE_SETTINGS},
    "refine.tie_polish_within": (DEFAULT_SETTINGS.refine.tie_polish_within, 0.0),
}


class Clock:
    """Seconds spent in a wrapped function, summed per estimate."""

    def __init__(self) -> None:
        self.spent = 0.0

    def wrap(self, owner: object, name: str) -> None:
        real = getattr(owner, name)

        def timed(*args, **kwargs):
            started = time.perf_counter()
            try:
                return real(*args, **kwargs)
            finally:
                self.spent += time.perf_counter() - started

        setattr(owner, name, timed)


def tuning_parts(encoder: Encoder) -> Iterator[tuple[int, str, trimesh.Trimesh, edgepose.Codebook]]:
    """(index, file name, mesh in metres, codebook) of each of ``PARTS``,
    scaled to a diameter drawn in 8–25 cm from ``SEED_BASE`` + index."""
    for k, part in enumerate(PARTS):
        mesh = read_mesh(CAD / part, scale=1.0)
        mesh.apply_scale(1.0 / float(np.linalg.norm(mesh.extents)))
        target = np.random.default_rng(SEED_BASE + k).uniform(0.08, 0.25)
        mesh.apply_scale(target / load_model(mesh, scale=1.0).diameter)
        yield k, part, mesh, edgepose.build_codebook(mesh, encoder=encoder)


#: Back-to-back calls of the rival search per view for its warm time.
WARM_CALLS = 20


def warm_search(cloud: np.ndarray, codebook: edgepose.Codebook, pose: edgepose.Pose, settings) -> float:
    """Median seconds of the search for ``pose``'s turned rival (found from
    ``cloud``), ``WARM_CALLS`` searches back to back, each timed as the
    estimate's "rival get" is: the search, not its setup ("rival start")."""
    query = stages.prepare_query(cloud, codebook, settings)
    R, t = pose.R, pose.t + pose.R @ codebook.model.centre  # object frame -> model frame
    stages.flip_rival(query, codebook, R, t, settings)
    seconds = []
    for _ in range(WARM_CALLS):
        search = refine.RivalSearch(query, codebook, R, t, settings, beside=False)
        started = time.perf_counter()
        search.get()
        seconds.append(time.perf_counter() - started)
    return float(np.median(seconds))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=9, help="estimates of each view in each mode")
    parser.add_argument(
        "--setting",
        choices=list(COMPARED_AGAINST),
        default=TWO_CORE_SETTINGS[0],
        help="the setting compared on and off",
    )
    parser.add_argument("--levels", default=LEVELS, help="stress levels, comma-separated")
    args = parser.parse_args()
    on, off = COMPARED_AGAINST[args.setting]
    modes = {"on": DEFAULT_SETTINGS.with_(**{args.setting: on}), "off": DEFAULT_SETTINGS.with_(**{args.setting: off})}
    encoder = default_encoder()
    views = []
    for k, part, mesh, codebook in tuning_parts(encoder):
        for level in args.levels.split(","):
            seeds = [SEED_BASE + k * 100 + i for i in range(3)]
            bench = load_object(mesh, seeds, name=part, symmetric=codebook.symmetry.symmetric, stress=level)
            views += [(level, codebook, cloud) for cloud in bench.clouds]
    clocks = {name: Clock() for name in ("polished", "rival start", "polish", "rival get", "pick")}
    clocks["polished"].wrap(refine, "polished")
    clocks["rival start"].wrap(refine.RivalSearch, "__init__")
    clocks["polish"].wrap(refine, "polish")
    clocks["rival get"].wrap(refine.RivalSearch, "get")
    clocks["pick"].wrap(refine, "pick_hypothesis")
    timed_pick = refine.pick_hypothesis
    tie_polished = [False]

    def watched(*args, **kwargs):  # notes whether a tie was polished (its polish handed on)
        picked = timed_pick(*args, **kwargs)
        tie_polished[0] |= picked is not None and picked.tie_polish is not None
        return picked

    refine.pick_hypothesis = watched
    per_view: dict[str, dict[str, list[float]]] = {m: {} for m in modes}
    warm: list[float] = []
    changed = tied = 0
    levels: list[str] = []
    for level, codebook, cloud in views:
        runs: dict[str, dict[str, list[float]]] = {m: {} for m in modes}
        poses = {}
        for r in range(args.repeats):
            for mode in list(modes) if r % 2 else list(modes)[::-1]:
                for clock in clocks.values():
                    clock.spent = 0.0
                tie_polished[0] = False
                pose = edgepose.estimate(cloud, codebook, encoder=encoder, settings=modes[mode])
                poses[mode] = pose
                if mode == "on":
                    polished_a_tie = tie_polished[0]
                measured = {
                    "total": pose.timings["total"],
                    "refine_hypotheses": pose.timings["refine_hypotheses"],
                    "confidence": pose.timings.get("confidence", 0.0),
                    **{name: clock.spent for name, clock in clocks.items()},
                }
                for key, seconds in measured.items():
                    runs[mode].setdefault(key, []).append(seconds)
        a, b = poses["on"], poses["off"]
        if not (np.array_equal(a.matrix, b.matrix) and a.confidence == b.confidence):
            if args.setting in TWO_CORE_SETTINGS:
                raise SystemExit(f"{args.setting} on and off gave different poses: no result may depend on the thread")
            changed += 1
        tied += polished_a_tie
        for mode in modes:
            for key, seconds in runs[mode].items():
                per_view[mode].setdefault(key, []).append(float(np.median(seconds)))
        levels.append(level)
        if args.setting == "refine.flip_rival_beside_polish":
            warm.append(warm_search(cloud, codebook, poses["off"], modes["off"]))
    print(f"{len(views)} views × {args.repeats} estimates per mode; medians over views, ms; {args.setting} on and off")
    print(f"{'':<18}" + "".join(f"{m:>10}" for m in modes))
    for key in per_view["on"]:
        print(f"{key:<18}" + "".join(f"{1e3 * np.median(per_view[m][key]):>10.3f}" for m in modes))
    paired = 1e3 * (np.array(per_view["on"]["total"]) - np.array(per_view["off"]["total"]))
    print(
        f"total, on minus off, per view: median {np.median(paired):+.3f} ms"
        f" (IQR {np.quantile(paired, 0.25):+.3f}..{np.quantile(paired, 0.75):+.3f}),"
        f" on faster on {np.mean(paired < 0):.0%} of views"
    )
    for level in dict.fromkeys(levels):
        at = np.array(levels) == level
        median, mean = np.median(paired[at]), np.mean(paired[at])
        print(f"  at {level}: median {median:+.3f} ms, mean {mean:+.3f} ms ({at.sum()} views)")
    print(f"  mean over views {np.mean(paired):+.3f} ms")
    if args.setting == "refine.tie_polish_within":
        print(f"on: a near tie polished in {tied} of {len(views)} views; poses changed (on against off): {changed}")
    if args.setting == "refine.flip_rival_beside_polish":
        own = {m: 1e3 * (np.array(per_view[m]["rival start"]) + np.array(per_view[m]["confidence"])) for m in modes}
        beside = 1e3 * (np.array(per_view["on"]["polish"]) - np.array(per_view["off"]["polish"]))
        print(
            f"the confidence's own cost per estimate, median over views: on {np.median(own['on'] + beside):.3f} ms"
            f" (rival start + confidence lap {np.median(own['on']):.3f}, polish on minus off {np.median(beside):+.3f}),"
            f" off {np.median(own['off']):.3f} ms"
        )
        print(
            f"the rival search alone, {WARM_CALLS} calls back to back per view (warm):"
            f" median {1e3 * np.median(warm):.3f} ms;"
            f" inside the estimate (off, rival get) {1e3 * np.median(per_view['off']['rival get']):.3f} ms"
        )


if __name__ == "__main__":
    main()
