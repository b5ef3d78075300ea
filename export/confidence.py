"""Fit ``Pose.confidence``'s calibrated model on training shapes, never YCB.

    .venv/bin/python -m export.confidence              # collect, cross-validate, print
    .venv/bin/python -m export.confidence --write      # ... and write it into models/manifest.json
    .venv/bin/python -m export.confidence --data F.npz # refit on evidence collected before
    .venv/bin/python -m export.confidence --frame --write  # the model for poses given the depth frame too

Objects: the shared training CAD parts, every 40th blob and procedural
compositions of primitives (``shapes.procedural_mesh``, symmetric ones
included), each scaled to a diameter drawn in 6–30 cm. Each is rendered at
every stress level (:data:`edgepose.eval.STRESS_LEVELS`: clean, occluded,
spilled and eroded masks, far and noisy), seeds from 555000 (disjoint from
the benchmark's and the tuning's), and once more as a mislabelled
detection: two clean views of another shape of about its size, estimated
with its codebook (no pose of them is correct; reported apart, as
``other_object``). ``estimate`` runs with default settings on each view;
its evidence (:data:`edgepose.confidence.FEATURES`) and whether the pose
is correct (ADD(-S) < 0.1 d, ADD-S when a symmetry is detected) are the
data. With ``--frame`` each view's whole depth frame is given too
(``estimate(cloud, codebook, depth=, K=)``): the evidence then holds the
scene terms (:data:`edgepose.confidence.SCENE_FEATURES`), and the model is
written as the manifest's ``confidence.with_scene``, the one
``Pose.confidence`` uses for such poses. A logistic regression (L2, Newton) is fitted on the
standardised, transformed evidence, each term entering as a piecewise-linear
curve (knots at :data:`KNOT_QUANTILES` of it). Reported: AUROC, expected calibration
error and the rates at the 0.5 threshold, by 4-fold cross-validation grouped
by object (no object is in its own fold's fit).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from edgepose.confidence import FEATURES, SCENE_FEATURES, STRICT_WRONG_ACCEPTED

from export.shapes import DIAMETER_RANGE, procedural_mesh, shared_mesh_paths

#: The evidence the model for clouds alone reads, and the one for poses given the depth frame too.
CLOUD_FEATURES = tuple(f for f in FEATURES if f not in SCENE_FEATURES)
FRAME_FEATURES = tuple(FEATURES)
SEED_BASE = 555_000
#: The level of the mislabelled views: another shape's cloud with the object's codebook.
OTHER_OBJECT = "other_object"
CACHE = Path(__file__).resolve().parent / ".cache"
#: L2 penalty of the logistic regression (on standardised inputs).
L2 = 1e-2
#: Where each term's knots lie: these quantiles of it over the fitting data.
#: Chosen by 4-fold cross-validation on the training evidence (stressed AUROC,
#: clouds / frame): linear 0.954 / 0.963, knots at 1/6..5/6 0.959 / 0.962,
#: at 0.1, 0.3, 0.5, 0.7, 0.9 0.961 / 0.970 (a gradient-boosted tree ensemble: 0.967 / 0.974).
KNOT_QUANTILES = (0.1, 0.3, 0.5, 0.7, 0.9)


def training_objects(procedural: int, blob_every: int) -> list[tuple[str, object]]:
    """(name, mesh source) of the fitting objects: CAD parts, some blobs, procedural shapes."""
    paths = shared_mesh_paths()
    cad = [p for p in paths if p.parent.name == "cad"]
    blobs = [p for p in paths if p.parent.name == "blobs"][::blob_every]
    objects: list[tuple[str, object]] = [(p.stem, p) for p in cad + blobs]
    rng = np.random.default_rng(SEED_BASE)
    objects += [(f"procedural_{i:02d}", procedural_mesh(rng)) for i in range(procedural)]
    return objects


def collect_object(job: tuple[int, str, object, int, list[str], int, bool]) -> dict[str, list]:
    """Evidence and correctness of ``estimate`` on one object at each stress
    level (given each view's depth frame too when the job's last item is true)."""
    import edgepose
    from edgepose.encoder import default_encoder
    from edgepose.eval import pose_errors
    from edgepose.eval.benchmark import load_object
    from edgepose.model import read_mesh

    k, name, source, views, levels, other_views, with_frame = job
    feature_names = FRAME_FEATURES if with_frame else CLOUD_FEATURES
    rows: dict[str, list] = {"object": [], "level": [], "correct": [], "evidence": [], "error": [], "error_s": []}
    try:
        mesh = read_mesh(source, scale=None) if isinstance(source, (str, Path)) else source
        mesh = mesh.copy()
        mesh.apply_translation(-mesh.bounding_box.centroid)
        target = np.random.default_rng(SEED_BASE + k).uniform(*DIAMETER_RANGE)
        mesh.apply_scale(target / np.linalg.norm(mesh.extents))
        codebook = edgepose.build_codebook(mesh, encoder=default_encoder())
    except Exception as e:  # an unusable training mesh (degenerate, flat) is skipped
        print(f"  skip {name}: {type(e).__name__}: {e}", flush=True)
        return rows
    symmetric = codebook.symmetry.symmetric
    seeds = [SEED_BASE + k * 1000 + i for i in range(views)]

    def estimated(obj):
        """(index, pose) of each view of ``obj`` that ``estimate`` gives a
        pose for (no pose, no confidence to judge)."""
        for i, (cloud, (depth, K)) in enumerate(zip(obj.clouds, obj.frames)):
            frame = dict(depth=depth, K=K, depth_scale=1.0) if with_frame else {}
            try:
                yield i, edgepose.estimate(cloud, codebook, **frame)
            except edgepose.EdgePoseError:
                continue

    def add(level: str, pose, correct: bool, error: float, error_s: float) -> None:
        evidence = [pose.evidence[f] for f in feature_names]
        row = dict(object=name, level=level, correct=correct, evidence=evidence, error=error, error_s=error_s)
        for key, value in row.items():
            rows[key].append(value)

    for level in levels:
        obj = load_object(mesh, seeds, name=name, symmetric=symmetric, stress=level)
        for i, pose in estimated(obj):
            e = pose_errors(obj.points, pose.matrix, obj.poses[i], obj.diameter, symmetric)
            add(level, pose, e.correct_add_or_s, e.add_or_s / obj.diameter, e.add_s / obj.diameter)
    # A mislabelled detection: another shape of about this size seen through
    # this object's codebook. No pose of it is correct.
    rng = np.random.default_rng(SEED_BASE + 500 + k)
    other = procedural_mesh(rng)
    other.apply_translation(-other.bounding_box.centroid)
    other.apply_scale(target * rng.uniform(0.8, 1.25) / np.linalg.norm(other.extents))
    for _, pose in estimated(load_object(other, seeds[:other_views], name=OTHER_OBJECT, symmetric=False)):
        add(OTHER_OBJECT, pose, False, np.nan, np.nan)
    ours = [c for c, level in zip(rows["correct"], rows["level"]) if level != OTHER_OBJECT]
    print(
        f"  {name}: {len(ours)} views, {np.mean(ours):.0%} correct"
        f" (+ {len(rows['correct']) - len(ours)} of another shape)",
        flush=True,
    )
    return rows


def fit_logistic(X: np.ndarray, y: np.ndarray, l2: float = L2, iterations: int = 50) -> tuple[np.ndarray, float]:
    """Weights and bias minimising the mean log-loss + ``l2``/2 · |w|² (Newton's method)."""
    n, f = X.shape
    A = np.hstack([X, np.ones((n, 1))])
    w = np.zeros(f + 1)
    penalty = np.diag([l2] * f + [0.0])
    for _ in range(iterations):
        p = 1 / (1 + np.exp(-np.clip(A @ w, -50, 50)))
        grad = A.T @ (p - y) / n + penalty @ w
        hess = (A * (p * (1 - p))[:, None]).T @ A / n + penalty + 1e-9 * np.eye(f + 1)
        step = np.linalg.solve(hess, grad)
        w -= step
        if np.abs(step).max() < 1e-10:
            break
    return w[:f], float(w[f])


def fit_model(evidence: np.ndarray, correct: np.ndarray, names: tuple[str, ...] = CLOUD_FEATURES):
    """A :class:`edgepose.confidence.ConfidenceModel` fitted on rows of evidence
    (columns: ``names``), with knots at :data:`KNOT_QUANTILES` of each term
    that takes more than 3 values (those strictly inside its range)."""
    from edgepose.confidence import ConfidenceModel, feature_vector

    terms = np.stack([feature_vector(dict(zip(names, row)), names) for row in evidence])
    knots = tuple(
        tuple(k for k in np.unique(np.quantile(column, KNOT_QUANTILES)).tolist() if column.min() < k < column.max())
        if len(np.unique(column)) > 3
        else ()
        for column in terms.T
    )
    X = ConfidenceModel.inputs(terms, knots)
    mean, scale = X.mean(axis=0), X.std(axis=0)
    scale[scale == 0] = 1.0
    weights, bias = fit_logistic((X - mean) / scale, correct.astype(float))
    return ConfidenceModel(names, knots, mean, scale, weights, bias)


def report(name: str, p: np.ndarray, y: np.ndarray) -> dict:
    from edgepose.eval.metrics import acceptance, auroc, calibration

    a = acceptance(p, y)
    row = {
        "views": int(len(y)),
        "correct": float(y.mean()),
        "auroc": auroc(p, y),
        "ece": calibration(p, y).ece,
        "wrong_accepted": a.wrong_accepted,
        "correct_kept": a.correct_kept,
    }
    print(
        f"{name:<10} {row['views']:>5} views  {row['correct']:6.1%} correct  AUROC {row['auroc']:.3f}  "
        f"ECE {row['ece']:.3f}  at 0.5: wrong accepted {row['wrong_accepted']:6.1%}, "
        f"correct kept {row['correct_kept']:6.1%}"
    )
    return row


#: The shares of wrong poses a stricter rule may let through: the fit reports
#: (and records) the lowest threshold, in steps of 0.01, that holds each; the
#: first is the strict rule's (``Pose.strict_threshold``).
STRICT_SHARES = (STRICT_WRONG_ACCEPTED, 0.10)


def strict_thresholds(p: np.ndarray, y: np.ndarray) -> list[dict]:
    """For each of :data:`STRICT_SHARES`: the lowest threshold (0.50–0.99)
    accepting at most that share of the wrong poses, and the shares it accepts and keeps."""
    from edgepose.eval.metrics import acceptance

    rows = []
    for target in STRICT_SHARES:
        for threshold in np.round(np.arange(0.5, 1.0, 0.01), 2):
            a = acceptance(p, y, float(threshold))
            if a.wrong_accepted <= target:
                rows.append(
                    {
                        "wrong_accepted_at_most": target,
                        "threshold": float(threshold),
                        "wrong_accepted": a.wrong_accepted,
                        "correct_kept": a.correct_kept,
                    }
                )
                print(
                    f"stressed: at most {target:.0%} of wrong poses accepted from confidence >= {threshold:.2f}: "
                    f"{a.wrong_accepted:.1%} accepted, {a.correct_kept:.1%} of correct kept"
                )
                break
    return rows


def acceptance_demand(p: np.ndarray, y: np.ndarray, threshold: float = 0.5) -> dict:
    """What accepting at most :data:`STRICT_WRONG_ACCEPTED` of the wrong
    poses at ``threshold`` asks of the accepted ones: how many are accepted,
    their mean confidence and share right now, and the share right they
    would need (as a calibrated model's mean confidence over them)."""
    accepted = p >= threshold
    wrong = int((~y).sum())
    row = {
        "accepted": int(accepted.sum()),
        "mean_confidence": float(p[accepted].mean()) if accepted.any() else float("nan"),
        "right": float(y[accepted].mean()) if accepted.any() else float("nan"),
        "right_needed": 1 - STRICT_WRONG_ACCEPTED * wrong / max(int(accepted.sum()), 1),
    }
    print(
        f"stressed: at {threshold} {row['accepted']} poses accepted, mean confidence {row['mean_confidence']:.3f}, "
        f"{row['right']:.1%} right; at most {STRICT_WRONG_ACCEPTED:.0%} of the {wrong} wrong ones accepted "
        f"would need {row['right_needed']:.1%} right"
    )
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--views", type=int, default=8, help="views per object and stress level")
    parser.add_argument(
        "--other-views",
        type=int,
        default=2,
        help="views per object of another shape (a mislabelled detection: ~2 %% of all)",
    )
    parser.add_argument("--procedural", type=int, default=16, help="procedural objects")
    parser.add_argument("--blob-every", type=int, default=40, help="every n-th blob")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--data", type=Path, default=None, help="evidence .npz collected before (skip collecting)")
    parser.add_argument("--save-data", type=Path, default=CACHE / "confidence_data.npz")
    parser.add_argument("--models", type=Path, default=None, help="models directory (default: the shipped one)")
    parser.add_argument("--write", action="store_true", help="write the fitted model into the manifest")
    parser.add_argument(
        "--frame", action="store_true", help="give estimate each view's depth frame too: the with_scene model"
    )
    args = parser.parse_args()
    features = FRAME_FEATURES if args.frame else CLOUD_FEATURES
    if args.save_data == parser.get_default("save_data") and args.frame:
        args.save_data = CACHE / "confidence_data_frame.npz"

    from edgepose.encoder import MODELS_DIR
    from edgepose.eval import STRESS_LEVELS

    t0 = time.perf_counter()
    if args.data:
        data = np.load(args.data)
        objects, levels, correct, evidence = data["object"], data["level"], data["correct"], data["evidence"]
        if list(data["features"]) != list(features):
            parser.error(f"{args.data} holds features {list(data['features'])}, not {list(features)}")
    else:
        meshes = training_objects(args.procedural, args.blob_every)
        jobs = [
            (k, name, src, args.views, list(STRESS_LEVELS), args.other_views, args.frame)
            for k, (name, src) in enumerate(meshes)
        ]
        print(f"collecting: {len(jobs)} objects × {len(STRESS_LEVELS)} levels × {args.views} views", flush=True)
        with ProcessPoolExecutor(args.workers) as pool:
            parts = list(pool.map(collect_object, jobs))
        objects = np.array([o for p in parts for o in p["object"]])
        levels = np.array([v for p in parts for v in p["level"]])
        correct = np.array([c for p in parts for c in p["correct"]], dtype=bool)
        evidence = np.array([e for p in parts for e in p["evidence"]], dtype=np.float64)
        error = np.array([e for p in parts for e in p["error"]], dtype=np.float64)
        error_s = np.array([e for p in parts for e in p["error_s"]], dtype=np.float64)
        args.save_data.parent.mkdir(parents=True, exist_ok=True)
        np.savez(
            args.save_data,
            object=objects,
            level=levels,
            correct=correct,
            evidence=evidence,
            error=error,
            error_s=error_s,
            features=features,
        )
        print(f"evidence saved to {args.save_data} ({time.perf_counter() - t0:.0f} s)")

    # Cross-validation grouped by object.
    names = np.unique(objects)
    fold_of = {n: i % 4 for i, n in enumerate(np.random.default_rng(0).permutation(names))}
    folds = np.array([fold_of[o] for o in objects])
    held_out = np.empty(len(correct))
    for f in range(4):
        model = fit_model(evidence[folds != f], correct[folds != f], features)
        held_out[folds == f] = [model.probability(dict(zip(features, row))) for row in evidence[folds == f]]
    print(f"\n4-fold cross-validation by object ({len(names)} objects):")
    # The benchmark's levels: the mislabelled views (all wrong) are reported apart.
    clean, other = levels == "clean", levels == OTHER_OBJECT
    stressed, benchmark = ~clean & ~other, ~other
    summary = {
        "all": report("all", held_out[benchmark], correct[benchmark]),
        "clean": report("clean", held_out[clean], correct[clean]),
        "stressed": report("stressed", held_out[stressed], correct[stressed]),
    }
    for level in dict.fromkeys(levels):
        if level != OTHER_OBJECT:
            report(str(level), held_out[levels == level], correct[levels == level])
    summary["stricter_thresholds"] = strict_thresholds(held_out[stressed], correct[stressed])
    acceptance_demand(held_out[stressed], correct[stressed])
    if other.any():
        summary[OTHER_OBJECT] = {"views": int(other.sum()), "trusted": float((held_out[other] >= 0.5).mean())}
        print(
            f"{OTHER_OBJECT:<10} {other.sum():>5} views (another shape, all wrong): trusted at 0.5 "
            f"{summary[OTHER_OBJECT]['trusted']:.1%}"
        )

    model = fit_model(evidence, correct, features)
    print("\nfitted on all:", json.dumps(model.to_manifest()["weights"]))
    if args.write:
        directory = args.models or MODELS_DIR
        manifest_path = directory / "manifest.json"
        manifest = json.loads(manifest_path.read_text())
        entry = {
            **model.to_manifest(),
            "fitted_on": {
                "command": f"python -m export.confidence{' --frame' if args.frame else ''} --write",
                "objects": int(len(names)),
                "views": int(len(correct)),
                "stress_levels": list(dict.fromkeys(str(v) for v in levels)),
                "data": "shared/data/train_shapes CAD parts, every 40th blob and procedural shapes, plus "
                f"{int(other.sum())} views of another shape through an object's codebook ({OTHER_OBJECT}); never YCB",
                "correct": "ADD(-S) < 0.1 d, ADD-S for objects with a detected symmetry",
                "cross_validation": summary,
            },
        }
        if args.frame:
            if "confidence" not in manifest:
                parser.error("fit the model for clouds alone first (without --frame): the frame's model goes beside it")
            manifest["confidence"]["with_scene"] = entry
        else:
            scene = manifest.get("confidence", {}).get("with_scene")
            manifest["confidence"] = entry if scene is None else {**entry, "with_scene": scene}
        manifest_path.write_text(json.dumps(manifest, indent=2) + "\n")
        print(f"written to {manifest_path}")


if __name__ == "__main__":
    main()
