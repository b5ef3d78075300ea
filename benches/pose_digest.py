"""Bit-identity check for restructuring: every number ``estimate`` and
``build_codebook`` produce on a fixed set of benchmark views, written to an
``.npz`` and compared exactly against an earlier run.

    .venv/bin/python benches/pose_digest.py --out /tmp/before.npz       # on the old commit
    .venv/bin/python benches/pose_digest.py --check /tmp/before.npz     # on the new one

Views: the five shared YCB meshes, ``--views`` seeds at each of ``--stress``
levels (default clean, visible70, spill5, noise_far), and with ``--real``
every target of the real ycbv frames (annotated masks, from the cloud
alone and given the frame). Compared, exactly (no
tolerance): each codebook's codes, spectra and centroids, and per view the
pose matrix, fit, score, chosen view, candidates, candidate fits, inlier
fraction, free-space violation, kept points, confidence, searches,
evidence and alternatives (matrices and margins). Run with
``RAYON_NUM_THREADS=1`` on both sides if a reduction order could depend on
threads. Exits 1 when anything differs and names the first difference.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

import edgepose
import numpy as np
from edgepose.eval.benchmark import load_object

REPO = Path(__file__).resolve().parents[1]
YCB = REPO.parent / "shared" / "data" / "ycb"
REAL = REPO.parent / "shared" / "data" / "ycbv_real"
DEFAULT_STRESS = "clean,visible70,spill5,noise_far"


def digest(views: int, stress: list[str]) -> dict[str, np.ndarray]:
    """Every compared array, by a name that says where it came from."""
    arrays: dict[str, np.ndarray] = {}
    for mesh_path in sorted(YCB.glob("*.ply")):
        name = mesh_path.stem
        codebook = None
        for level in stress:
            bench = load_object(mesh_path, seeds=list(range(views)), name=name, stress=level)
            if codebook is None:
                codebook = edgepose.build_codebook(bench.mesh)
                arrays[f"{name}/codes"] = codebook.codes
                arrays[f"{name}/spectra"] = codebook.spectra
                arrays[f"{name}/centroids"] = codebook.centroids
            for i, cloud in enumerate(bench.clouds):
                pose = edgepose.estimate(cloud, codebook)
                arrays.update(pose_arrays(f"{name}/{level}/{i}", pose))
        print(f"{name}: done", file=sys.stderr)
    return arrays


def pose_arrays(key: str, pose: edgepose.Pose) -> dict[str, np.ndarray]:
    """Every number of one pose, by name under ``key``."""
    return {
        f"{key}/matrix": pose.matrix,
        f"{key}/numbers": np.array(
            [
                pose.fit,
                pose.score,
                pose.view,
                pose.inlier_fraction,
                pose.free_space_violation,
                pose.kept_points,
                pose.confidence,
                pose.searches,
            ],
            dtype=np.float64,
        ),
        f"{key}/evidence": np.array([pose.evidence[k] for k in sorted(pose.evidence)]),
        f"{key}/candidates": np.asarray(pose.candidates),
        f"{key}/candidate_fit": np.asarray(pose.candidate_fit),
        f"{key}/alternatives": np.array(
            [[*a.matrix.ravel(), a.margin] for a in pose.alternatives], dtype=np.float64
        ).reshape(-1, 17),
    }


def real_digest() -> dict[str, np.ndarray]:
    """Every number of ``estimate`` on each real target of ``../shared/data/ycbv_real``
    (annotated masks), from the cloud alone and given the frame."""
    from edgepose.eval.bop import BopDataset
    from edgepose.eval.bop_run import bop_codebooks
    from edgepose.eval.real import estimate_targets

    dataset = BopDataset(REAL)
    targets = dataset.targets()
    books = bop_codebooks(dataset, {t.obj_id for t in targets}, REPO / "benches" / ".cache" / "ycbv_real_codebooks")
    arrays = {}
    for with_frame in (False, True):
        for r in estimate_targets(dataset, targets, books, 0, with_frame=with_frame):
            arrays.update(pose_arrays(f"real/{r.method}/{r.scene_id}/{r.im_id}/{r.obj_id}", r.pose))
    print("real frames: done", file=sys.stderr)
    return arrays


def fingerprint(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for key in sorted(arrays):
        h.update(key.encode())
        h.update(np.ascontiguousarray(arrays[key]).tobytes())
    return h.hexdigest()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--stress", default=DEFAULT_STRESS)
    parser.add_argument("--real", action="store_true", help="also every real target of ../shared/data/ycbv_real")
    parser.add_argument("--out", type=Path, help="write the arrays here")
    parser.add_argument("--check", type=Path, help="compare exactly against this earlier --out")
    args = parser.parse_args()
    if not YCB.is_dir():
        sys.exit(f"needs the shared YCB meshes in {YCB}")
    arrays = digest(args.views, args.stress.split(","))
    if args.real:
        arrays.update(real_digest())
    print(f"{len(arrays)} arrays, sha256 {fingerprint(arrays)}")
    if args.out:
        np.savez(args.out, **arrays)
    if args.check:
        before = dict(np.load(args.check))
        if sorted(before) != sorted(arrays):
            sys.exit(f"different arrays: {sorted(set(before) ^ set(arrays))[:5]}")
        for key in sorted(arrays):
            if before[key].shape != arrays[key].shape or not np.array_equal(before[key], arrays[key]):
                sys.exit(f"{key} differs:\n before {before[key]!r}\n now    {arrays[key]!r}")
        print(f"bit-identical to {args.check}: {len(arrays)} arrays")


if __name__ == "__main__":
    main()
