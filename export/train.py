"""Train the encoder and IRR head, then export them to ONNX.

    .venv/bin/python -m export.train                    # full run (CPU, see export/README.md)
    .venv/bin/python -m export.train --resume           # continue from the last checkpoint
    .venv/bin/python -m export.train --tiny --out /tmp/m  # seconds: a smoke run for tests

Losses (../shared/paper.txt, "Method"): a triplet loss on cosine similarity
with margin 0.1 (an observed map and the codebook map of its viewpoint are
positives; codebook maps of viewpoints more than NEGATIVE_MIN_DEG away are
negatives) and, for the IRR head, 1 − cos(θ̂ − θ).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import queue
import sys
import threading
import time
from pathlib import Path

import numpy as np
import torch
from edgepose.encoder import ENCODER_INPUTS

from export import data, shapes
from export.network import (
    CENTRES,
    CODE_SIZE,
    HARMONICS,
    MAP_POINTS,
    NEIGHBOURS,
    SPECTRUM_SIZE,
    Encoder,
    InPlaneRotation,
    neighbour_groups,
    parameter_count,
)

ROOT = Path(__file__).resolve().parents[1]
MODELS_DIR = ROOT / "python" / "edgepose" / "models"
CACHE_DIR = ROOT / "export" / ".cache"
MARGIN = 0.1
NEGATIVE_MIN_DEG = 20.0
OPSET = 17


def losses(encoder: Encoder, irr: InPlaneRotation, batch: data.Batch) -> dict[str, torch.Tensor]:
    observed = torch.from_numpy(batch.observed)
    codebook = torch.from_numpy(batch.codebook)
    code_o, spec_o = encoder.encode(observed, neighbour_groups(observed))
    code_b, spec_b = encoder.encode(codebook, neighbour_groups(codebook))

    sim = code_o @ code_b.T  # (B, B) cosine similarities
    positive = sim.diagonal().unsqueeze(1)
    d = torch.from_numpy(batch.directions)
    angle = torch.rad2deg(torch.arccos((d @ d.T).clamp(-1, 1)))
    same_shape = torch.from_numpy(batch.shape_ids[:, None] == batch.shape_ids[None, :])
    negative = (~same_shape) | (angle > NEGATIVE_MIN_DEG)
    violation = torch.relu(MARGIN + sim - positive)[negative]
    active = violation > 0
    code_loss = violation[active].mean() if active.any() else violation.sum() * 0

    pred = irr(spec_o, spec_b)
    truth = torch.from_numpy(np.stack([np.cos(batch.angles), np.sin(batch.angles)], -1)).float()
    irr_loss = (1 - (pred * truth).sum(-1)).mean()
    err = torch.rad2deg(torch.arccos((pred * truth).sum(-1).clamp(-1, 1)))
    return {
        "loss": code_loss + irr_loss,
        "code": code_loss.detach(),
        "irr": irr_loss.detach(),
        "active": active.float().mean(),
        "irr_median_deg": err.median().detach(),
        "top1": (sim.argmax(1) == torch.arange(len(sim))).float().mean(),
    }


def batches(models, seed: int, start_step: int, shapes_per_batch: int, views: int, depth: int = 3):
    """Batches on a background thread (the Rust map work releases the GIL)."""
    q: queue.Queue = queue.Queue(maxsize=depth)

    def work() -> None:
        step = start_step
        while True:
            rng = np.random.default_rng([seed, step])  # resumable: a step's batch depends only on it
            q.put(data.sample_batch(models, rng, shapes_per_batch, views))
            step += 1

    threading.Thread(target=work, daemon=True).start()
    while True:
        yield q.get()


def export_onnx(encoder: Encoder, irr: InPlaneRotation, out: Path) -> dict[str, str]:
    """Writes encoder.onnx and irr.onnx (dynamic batch, self-contained) and
    checks onnxruntime against torch on random inputs; the encoder's
    inputs (the maps' features) come from the Rust core, as at run time."""
    import onnxruntime as ort
    from edgepose import _core

    out.mkdir(parents=True, exist_ok=True)
    encoder.eval(), irr.eval()
    maps = torch.randn(4, MAP_POINTS, 3) * 0.4
    features = _core.map_features(maps.numpy(), CENTRES, NEIGHBOURS, HARMONICS)
    torch.onnx.export(
        encoder,
        tuple(torch.from_numpy(f) for f in features),
        out / "encoder.onnx",
        input_names=list(ENCODER_INPUTS),
        output_names=["code", "spectrum"],
        dynamic_axes={name: {0: "batch"} for name in (*ENCODER_INPUTS, "code", "spectrum")},
        opset_version=OPSET,
        dynamo=False,
    )
    observed, candidates = torch.randn(1, SPECTRUM_SIZE), torch.randn(16, SPECTRUM_SIZE)
    torch.onnx.export(
        irr,
        (observed, candidates),
        out / "irr.onnx",
        input_names=["observed", "candidates"],
        output_names=["cos_sin"],
        dynamic_axes={"observed": {0: "one"}, "candidates": {0: "k"}, "cos_sin": {0: "k"}},
        opset_version=OPSET,
        dynamo=False,
    )
    with torch.no_grad():
        code, spectrum = encoder.encode(maps, neighbour_groups(maps))
        angle = irr(observed, candidates)
    enc = ort.InferenceSession(str(out / "encoder.onnx"), providers=["CPUExecutionProvider"])
    ort_code, ort_spec = enc.run(None, dict(zip(ENCODER_INPUTS, features)))
    rot = ort.InferenceSession(str(out / "irr.onnx"), providers=["CPUExecutionProvider"])
    (ort_angle,) = rot.run(None, {"observed": observed.numpy(), "candidates": candidates.numpy()})
    worst = max(
        np.abs(ort_code - code.numpy()).max(),
        np.abs(ort_spec - spectrum.numpy()).max(),
        np.abs(ort_angle - angle.numpy()).max(),
    )
    if worst > 1e-4:
        raise RuntimeError(f"onnxruntime differs from torch by {worst:.2e}")
    return {name: hashlib.sha256((out / name).read_bytes()).hexdigest() for name in ("encoder.onnx", "irr.onnx")}


def write_manifest(
    out: Path,
    hashes: dict[str, str],
    encoder: Encoder,
    irr: InPlaneRotation,
    training: dict,
    confidence: dict | None = None,
    fingerprint: str | None = None,
) -> dict:
    """``manifest.json`` beside the exported networks: hashes, sizes, the
    inputs the runtime must prepare, how the weights were trained and, when
    given, ``Pose.confidence``'s model fitted for these networks
    (``python -m export.confidence --write``). ``fingerprint`` names the
    codes the encoder gives (what a codebook records): the new encoder
    file's sha256 unless a re-export gives an earlier file's codes bit for
    bit (:mod:`export.reexport`)."""
    manifest = {
        "format": 3,
        "files": hashes,
        "fingerprint": fingerprint or hashes["encoder.onnx"],
        "parameters": {
            "encoder": parameter_count(encoder),
            "irr": parameter_count(irr),
            "total": parameter_count(encoder, irr),
        },
        "inputs": {
            "map_points": MAP_POINTS,
            "centres": CENTRES,
            "neighbours": NEIGHBOURS,
            "harmonics": HARMONICS,
            "code_size": CODE_SIZE,
            "spectrum_size": SPECTRUM_SIZE,
        },
        "training": training,
    }
    if confidence is not None:
        manifest["confidence"] = confidence
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return manifest


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=900)
    parser.add_argument("--shapes-per-batch", type=int, default=12)
    parser.add_argument("--views-per-shape", type=int, default=8)
    parser.add_argument("--procedural", type=int, default=300, help="procedural shapes added to the shared ones")
    parser.add_argument("--lr", type=float, default=2e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=MODELS_DIR)
    parser.add_argument("--cache", type=Path, default=CACHE_DIR)
    parser.add_argument("--resume", action="store_true", help="continue from <cache>/checkpoint.pt")
    parser.add_argument("--tiny", action="store_true", help="smoke run: 12 shapes, 3 steps")
    parser.add_argument("--init", type=Path, help="fine-tune: start from the networks exported in this folder")
    args = parser.parse_args(argv)
    if args.tiny:
        args.steps, args.shapes_per_batch, args.views_per_shape, args.procedural = 3, 4, 4, 2

    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    started = time.perf_counter()
    model_cache = args.cache / ("models_tiny.npz" if args.tiny else f"models_p{args.procedural}_s{args.seed}.npz")
    if model_cache.exists():
        models = shapes.load_models(model_cache)
    else:
        models = shapes.build_models(args.procedural, args.seed, limit=10 if args.tiny else None)
        shapes.save_models(models, model_cache)
    print(f"{len(models)} training shapes ({time.perf_counter() - started:.0f} s)", flush=True)

    encoder, irr = Encoder(), InPlaneRotation()
    params = list(encoder.parameters()) + list(irr.parameters())
    optimizer = torch.optim.AdamW(params, lr=args.lr, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimizer, max_lr=args.lr, total_steps=args.steps, pct_start=0.05)
    if args.init is not None:
        from export.reexport import load_into, weights_from_onnx

        load_into(encoder, weights_from_onnx(args.init / "encoder.onnx"))
        load_into(irr, weights_from_onnx(args.init / "irr.onnx"))
        print(f"starting from the networks in {args.init}", flush=True)
    step = 0
    checkpoint = args.cache / "checkpoint.pt"
    if args.resume and checkpoint.exists():
        state = torch.load(checkpoint)
        encoder.load_state_dict(state["encoder"]), irr.load_state_dict(state["irr"])
        optimizer.load_state_dict(state["optimizer"]), schedule.load_state_dict(state["schedule"])
        step = state["step"]
        print(f"resumed at step {step}", flush=True)

    stream = batches(models, args.seed, step, args.shapes_per_batch, args.views_per_shape)
    log: dict[str, float] = {}
    t0 = time.perf_counter()
    while step < args.steps:
        encoder.train(), irr.train()
        out = losses(encoder, irr, next(stream))
        optimizer.zero_grad()
        out["loss"].backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        optimizer.step()
        schedule.step()
        step += 1
        for k, v in out.items():
            log[k] = log.get(k, 0.0) + float(v.detach())
        if step % 25 == 0 or step == args.steps:
            n = 25 if step % 25 == 0 else step % 25
            rate = (time.perf_counter() - t0) / n
            print(
                f"step {step:5d}  " + "  ".join(f"{k} {v / n:.3f}" for k, v in log.items()) + f"  {rate:.2f} s/step",
                flush=True,
            )
            log, t0 = {}, time.perf_counter()
        if step % 100 == 0 or step == args.steps:
            args.cache.mkdir(parents=True, exist_ok=True)
            torch.save(
                {
                    "encoder": encoder.state_dict(),
                    "irr": irr.state_dict(),
                    "optimizer": optimizer.state_dict(),
                    "schedule": schedule.state_dict(),
                    "step": step,
                },
                checkpoint,
            )

    hashes = export_onnx(encoder, irr, args.out)
    training = {
        "command": "python -m export.train " + " ".join(argv if argv is not None else sys.argv[1:]),
        "steps": args.steps,
        "shapes_per_batch": args.shapes_per_batch,
        "views_per_shape": args.views_per_shape,
        "shapes": len(models),
        "data": "shared/data/train_shapes (1,000 blobs + 26 CAD parts) + procedural; never YCB",
        "seed": args.seed,
        "seconds": round(time.perf_counter() - started),
        "initialised_from": None if args.init is None else "the previously shipped networks (fine-tune)",
    }
    manifest = write_manifest(args.out, hashes, encoder, irr, training)
    print(f"exported to {args.out}: {manifest['parameters']['total']} parameters", flush=True)
    print("new networks: refit Pose.confidence with `python -m export.confidence --write`", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
