"""Where the wrong poses go wrong: for each view of the tuning parts that
``estimate`` gets wrong (ADD(-S) ≥ 0.1 × diameter), how far the truth got
through the search.

    .venv/bin/python benches/bench_misses.py [--views 20] [--stress visible20,visible40,...]

Views: ``bench_pose.py --tune``'s six CAD parts and seeds (never YCB), at
each ``--stress`` level. Per level, of the wrong poses, printed:
- ``view top 16 / 64 / 256``: how many had a codebook view within 15° of the
  true camera direction among the cosine ranking's first 16 (the first
  search's candidates, ``k``), 64 or 256 views (the retrieval's recall);
- ``candidate < 0.3 d / < 0.1 d``: how many had a candidate pose (either
  search's: the views' poses, the point pairs' poses) within that ADD(-S)
  of the truth, before any ICP (ICP's reach is roughly the former);
- ``hypothesis``: how many had a right pose among the ICP-refined
  hypotheses (another was chosen);
- ``rival``: how many had the right pose as the pose's turned rival (the
  confidence's flip margin: a tie the view cannot break);
and, for scale, how many of the right poses had their view among the first
16. A wrong pose none of these reach is the search's miss, not a tie the
confidence could be asked to break.

The counts come from the stage functions ``estimate`` calls, wrapped (the
same poses as without).
"""

from __future__ import annotations

import argparse

import edgepose
import edgepose.pose as pose_module
import edgepose.search as search_module
import numpy as np
from bench_pose import load_sources
from edgepose import stages
from edgepose.codebook import Codebook
from edgepose.encoder import default_encoder
from edgepose.eval.benchmark import BenchObject, load_object
from edgepose.eval.metrics import CORRECT_FRACTION, add_or_s

#: A codebook view this close to the true camera direction (degrees) counts as the true view.
VIEW_WITHIN_DEG = 15.0
RANKS = (16, 64, 256)


class Seen:
    """What one ``estimate`` call passed through: retrievals, candidates, ICP caches, turned rivals."""

    def __init__(self) -> None:
        self.retrievals: list = []
        self.candidates: list = []
        self.icp_caches: list[dict] = []
        self.rivals: list = []

    def wrap(self) -> None:
        """Wraps the stage functions ``estimate`` calls so that each records here."""
        retrieve, best_pose, rival_get = pose_module.retrieve, search_module.best_pose, stages.RivalSearch.get

        def retrieved(*args, **kwargs):
            found = retrieve(*args, **kwargs)
            self.retrievals.append(found)
            return found

        def chose(query, codebook, found, refine, settings, icp_cache):
            self.candidates.append(found)
            self.icp_caches.append(icp_cache)
            return best_pose(query, codebook, found, refine, settings, icp_cache)

        def rival(search):
            found = rival_get(search)
            self.rivals.append(found)
            return found

        pose_module.retrieve, search_module.best_pose, stages.RivalSearch.get = retrieved, chose, rival

    def clear(self) -> None:
        for seen in (self.retrievals, self.candidates, self.icp_caches, self.rivals):
            seen.clear()


def object_frame(R: np.ndarray, t: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(4, 4) T_cam_obj of a model-frame pose (model frame = object frame shifted by ``centre``)."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t - R @ centre
    return T


def error(bench: BenchObject, T: np.ndarray, truth: np.ndarray) -> float:
    """ADD(-S) of ``T`` against ``truth`` over the object's diameter."""
    return add_or_s(bench.points, T, truth, bench.symmetric) / bench.diameter


def traced(T: np.ndarray, truth: np.ndarray, bench: BenchObject, codebook: Codebook, seen: Seen) -> dict:
    """How far the ``truth`` got through the search that gave pose ``T``
    (both T_cam_obj), from what ``seen`` recorded."""
    centre = codebook.model.centre
    # The true camera direction, model frame; the best rank of a codebook view near it.
    R, t = truth[:3, :3], truth[:3, 3] + truth[:3, :3] @ centre
    towards = -(R.T @ t) / np.linalg.norm(t)
    near = np.degrees(np.arccos(np.clip(codebook.viewpoints.directions @ towards, -1, 1))) < VIEW_WITHIN_DEG
    similarity = codebook.codes @ seen.retrievals[0].code
    rank = np.empty(len(similarity), dtype=int)
    rank[np.argsort(-similarity, kind="stable")] = np.arange(len(similarity))
    candidates = [
        error(bench, object_frame(Rc, tc, centre), truth)
        for found in seen.candidates
        for Rc, tc in zip(found.rotations, found.translations)
    ]
    hypotheses = [value for cache in seen.icp_caches for key, value in cache.items() if key[0] == "coarse"]
    rival = seen.rivals[-1] if seen.rivals else None
    return {
        "right": error(bench, T, truth) < CORRECT_FRACTION,
        "view_rank": int(rank[near].min()) if near.any() else len(rank),
        "candidate": min(candidates),
        "hypothesis": any(error(bench, object_frame(h[0], h[1], centre), truth) < CORRECT_FRACTION for h in hypotheses),
        "rival": rival is not None
        and len(rival.rotations) > 0
        and error(bench, object_frame(rival.rotations[0], rival.translations[0], centre), truth) < CORRECT_FRACTION,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=20, help="views per part and stress level")
    parser.add_argument("--stress", default="visible20,visible40,occluded30_spill5,partial")
    args = parser.parse_args()
    encoder = default_encoder()
    seen = Seen()
    seen.wrap()
    print(
        f"{'level':<18}{'views':>6}{'wrong':>6}"
        + "".join(f"{'view top ' + str(r):>13}" for r in RANKS)
        + f"{'cand < 0.3d':>12}{'cand < 0.1d':>12}{'hypothesis':>11}{'rival':>7}{'right: view top 16':>20}"
    )
    levels = args.stress.split(",")
    rows: dict[str, list[dict]] = {level: [] for level in levels}
    tune = argparse.Namespace(tune=True, meshes=None, objects=None, seed=0)
    for source in load_sources(tune, parser):
        codebook = edgepose.build_codebook(source.mesh, encoder=encoder)
        for level in levels:
            seeds = [source.seed_base + i for i in range(args.views)]
            bench = load_object(
                source.mesh, seeds, name=source.name, symmetric=codebook.symmetry.symmetric, stress=level
            )
            for cloud, truth in zip(bench.clouds, bench.poses):
                seen.clear()
                pose = edgepose.estimate(cloud, codebook, encoder=encoder)
                rows[level].append(traced(pose.matrix, truth, bench, codebook, seen))
    for level, found in rows.items():
        wrong = [r for r in found if not r["right"]]
        good = [r for r in found if r["right"]]
        print(
            f"{level:<18}{len(found):>6}{len(wrong):>6}"
            + "".join(f"{sum(r['view_rank'] < n for r in wrong):>13}" for n in RANKS)
            + f"{sum(r['candidate'] < 0.3 for r in wrong):>12}{sum(r['candidate'] < 0.1 for r in wrong):>12}"
            + f"{sum(r['hypothesis'] for r in wrong):>11}{sum(r['rival'] for r in wrong):>7}"
            + f"{sum(r['view_rank'] < RANKS[0] for r in good):>14} of {len(good)}"
        )


if __name__ == "__main__":
    main()
