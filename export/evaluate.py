"""Quality and latency of the exported networks on the unseen YCB objects.

    .venv/bin/python -m export.evaluate [--models python/edgepose/models] [--queries 100]

Queries are rendered depth views (edgepose.eval.render_view: 1 mm noise,
1 mm quantisation, 2 % dropout, random pose 0.45–0.9 m away), made ready and
searched by ``estimate``'s own stages (``edgepose.stages.prepare_query`` and
``retrieve``, default settings). For each query:

* retrieval: the top-K codes (cosine) over the 2,100-view codebook succeed when
  one candidate's direction lies within 15° of the true view direction; for the
  symmetric objects (those edgepose detects a symmetry in: can, box, mustard
  bottle) a candidate also counts when its implied
  rotation (with the IRR angle) passes ADD-S < 0.1 d;
* IRR: the angle error when the candidate is the map of the true viewpoint.

Latency: onnxruntime on 1 thread, medians.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import edgepose
import numpy as np
from edgepose.encoder import MODELS_DIR, Encoder
from edgepose.eval import add_s, render_view
from edgepose.model import read_mesh
from edgepose.stages import prepare_query, retrieve
from edgepose.views import rotation_about_z

YCB = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ycb"
TOP_K = 16
WITHIN_DEG = 15.0


def angle_deg(a: float, b: float) -> float:
    return abs(np.degrees(np.angle(np.exp(1j * (a - b)))))


def evaluate_object(encoder: Encoder, path: Path, queries: int, seed: int) -> dict:
    mesh = read_mesh(path)
    codebook = edgepose.build_codebook(mesh, encoder=encoder)
    model, views = codebook.model, codebook.viewpoints
    symmetric = codebook.symmetry.symmetric
    top1 = top_k = 0
    irr_errors = []
    for q in range(queries):
        view = render_view(mesh, seed=seed * 100_000 + q)
        query = prepare_query(view.cloud, codebook)
        r_true = query.r_corr @ view.T_cam_obj[:3, :3]  # object → corrected view
        direction = -r_true[2]  # object frame, towards the camera
        candidates, _, angles, _ = retrieve(query, codebook, encoder, TOP_K)
        near = np.degrees(np.arccos(np.clip(views.directions[candidates] @ direction, -1, 1))) <= WITHIN_DEG
        top1 += bool(near[0])
        ok = bool(near.any())
        if symmetric and not ok:
            for v, theta in zip(candidates, angles):
                pose, truth = np.eye(4), np.eye(4)
                pose[:3, :3] = rotation_about_z(theta) @ views.rotations[v]
                truth[:3, :3] = r_true
                if add_s(model.points, pose, truth) < 0.1 * model.diameter:
                    ok = True
                    break
        top_k += ok
        # IRR given the true viewpoint's map.
        r_view = edgepose.view_rotation(direction)
        true_map = edgepose.compute_maps(model, edgepose.Viewpoints(direction[None], r_view[None])).points
        _, true_spectrum = encoder.encode(true_map)
        _, spectrum = encoder.encode(query.map[None])
        rel = r_true @ r_view.T
        theta = encoder.in_plane_angles(spectrum[0], true_spectrum)[0]
        irr_errors.append(angle_deg(theta, np.arctan2(rel[1, 0], rel[0, 0])))
    return {
        "object": path.stem,
        "symmetric": symmetric,
        "queries": queries,
        "top1_within_15deg": top1 / queries,
        f"top{TOP_K}_success": top_k / queries,
        "irr_median_error_deg": float(np.median(irr_errors)),
        "irr_p90_error_deg": float(np.percentile(irr_errors, 90)),
    }


def latency(encoder: Encoder) -> dict:
    rng = np.random.default_rng(0)
    one = (rng.normal(size=(1, encoder.map_points, 3)) * 0.4).astype(np.float32)
    book = (rng.normal(size=(2100, encoder.map_points, 3)) * 0.4).astype(np.float32)
    spectra = rng.normal(size=(17, encoder.spectrum_size)).astype(np.float32)

    def median_ms(fn, n: int) -> float:
        fn()
        times = []
        for _ in range(n):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return statistics.median(times) * 1e3

    return {
        "encoder_one_map_ms": median_ms(lambda: encoder.encode(one), 200),
        "irr_16_candidates_ms": median_ms(lambda: encoder.in_plane_angles(spectra[0], spectra[1:]), 500),
        "encode_2100_maps_ms": median_ms(lambda: encoder.encode(book), 3),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", type=Path, default=MODELS_DIR)
    parser.add_argument("--queries", type=int, default=100)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = parser.parse_args()

    encoder = Encoder(args.models, threads=1)
    rows = [evaluate_object(encoder, p, args.queries, args.seed) for p in sorted(YCB.glob("*.ply"))]
    print(f"{'object':<16} {'sym':>4} {'top-1 ≤15°':>11} {'top-16':>8} {'IRR median':>11} {'IRR p90':>8}")
    for r in rows:
        print(
            f"{r['object']:<16} {'yes' if r['symmetric'] else 'no':>4} {r['top1_within_15deg']:>11.1%} "
            f"{r[f'top{TOP_K}_success']:>8.1%} {r['irr_median_error_deg']:>10.2f}° {r['irr_p90_error_deg']:>7.1f}°"
        )
    overall = {
        "top1_within_15deg": float(np.mean([r["top1_within_15deg"] for r in rows])),
        f"top{TOP_K}_success": float(np.mean([r[f"top{TOP_K}_success"] for r in rows])),
        f"top{TOP_K}_success_asymmetric": float(
            np.mean([r[f"top{TOP_K}_success"] for r in rows if not r["symmetric"]])
        ),
        "irr_median_error_deg": float(np.median([r["irr_median_error_deg"] for r in rows])),
    }
    print("all objects   " + "  ".join(f"{k} {v:.3f}" for k, v in overall.items()))
    timing = latency(encoder)
    print("latency (1 thread, median)  " + "  ".join(f"{k} {v:.2f}" for k, v in timing.items()))
    if args.json:
        args.json.write_text(json.dumps({"objects": rows, "overall": overall, "latency": timing}, indent=2) + "\n")


if __name__ == "__main__":
    main()
