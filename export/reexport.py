"""Export already-trained networks again with the current graph, without
retraining: read the weights out of shipped ONNX files into the torch
modules, then export and parity-check as training does.

    .venv/bin/python -m export.reexport [--source python/edgepose/models] [--out python/edgepose/models]

Used when a change moves work out of the graph but keeps the network's
arithmetic (the neighbour grouping moved into the Rust core this way); the
manifest keeps the original training record. When the new encoder gives
the source's codes and spectra bit for bit on a set of test maps, the
manifest keeps the source's fingerprint too, so codebooks built before
stay valid; otherwise they must be rebuilt (it says so).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from export.network import CENTRES, HARMONICS, MAP_POINTS, NEIGHBOURS, Encoder, InPlaneRotation, neighbour_groups
from export.train import MODELS_DIR, export_onnx, write_manifest


def weights_from_onnx(path: Path) -> dict[str, np.ndarray]:
    """Named weights of an exported graph; MatMul weights that the exporter
    renamed (and stored transposed) are keyed by their shape."""
    import onnx
    from onnx import numpy_helper

    return {init.name: numpy_helper.to_array(init) for init in onnx.load(str(path)).graph.initializer}


def load_into(module: torch.nn.Module, weights: dict[str, np.ndarray]) -> None:
    """Fill ``module``'s parameters from ``weights``: by name, else the one
    unnamed (transposed) matrix of matching shape."""
    unnamed_weights = [w for name, w in weights.items() if name.startswith("onnx::")]
    unnamed = {tuple(w.shape): w for w in unnamed_weights}
    if len(unnamed) != len(unnamed_weights):
        raise ValueError("two unnamed weight matrices share a shape: cannot tell which layer each belongs to")
    state = {}
    for name, param in module.state_dict().items():
        if name in weights:
            value = weights[name]
        else:
            value = unnamed.pop(tuple(param.shape[::-1])).T
        if tuple(value.shape) != tuple(param.shape):
            raise ValueError(f"{name}: stored shape {value.shape}, network has {tuple(param.shape)}")
        state[name] = torch.from_numpy(np.array(value))
    module.load_state_dict(state)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--source", type=Path, default=MODELS_DIR)
    parser.add_argument("--out", type=Path, default=MODELS_DIR)
    args = parser.parse_args(argv)
    source = json.loads((args.source / "manifest.json").read_text())
    encoder, irr = Encoder(), InPlaneRotation()
    load_into(encoder, weights_from_onnx(args.source / "encoder.onnx"))
    load_into(irr, weights_from_onnx(args.source / "irr.onnx"))
    before = parity_codes(args.source)
    hashes = export_onnx(encoder, irr, args.out)
    # Same weights, same outputs: the confidence model fitted for them still holds.
    manifest = write_manifest(args.out, hashes, encoder, irr, source["training"], source.get("confidence"))
    same = all(np.array_equal(a, b) for a, b in zip(before, parity_codes(args.out)))
    if same:  # codebooks built with the source's encoder stay valid
        fingerprint = source.get("fingerprint", source["files"]["encoder.onnx"])
        write_manifest(args.out, hashes, encoder, irr, source["training"], source.get("confidence"), fingerprint)
    print(f"re-exported to {args.out}: {manifest['parameters']['total']} parameters", flush=True)
    if not same:
        print("the codes differ from the source's in the last bits: rebuild every codebook", flush=True)
    return 0


def parity_codes(models_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """Codes and spectra of the encoder in ``models_dir`` for fixed random
    maps of several sizes and batch shapes (none of them a benchmark object).
    The graph is fed by its inputs' names, so an encoder exported before its
    features moved into the core (it takes maps and neighbour groups) can be
    checked against one exported now."""
    import onnxruntime as ort
    from edgepose import _core

    rng = np.random.default_rng(20261202)
    maps = np.concatenate(
        [(rng.normal(size=(16, MAP_POINTS, 3)) * scale).astype(np.float32) for scale in (0.05, 0.4, 1.0, 3.0)]
    )
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(str(models_dir / "encoder.onnx"), options, providers=["CPUExecutionProvider"])
    names = tuple(i.name for i in session.get_inputs())

    def encode(batch: np.ndarray) -> list[np.ndarray]:
        if names == ("maps", "neighbours"):
            groups = neighbour_groups(torch.from_numpy(batch)).numpy()
            return session.run(None, {"maps": batch, "neighbours": groups})
        return session.run(None, dict(zip(names, _core.map_features(batch, CENTRES, NEIGHBOURS, HARMONICS))))

    one = [encode(m[None]) for m in maps[:8]]
    whole = encode(maps)
    return (
        np.concatenate([np.concatenate([c for c, _ in one]), whole[0]]),
        np.concatenate([np.concatenate([s for _, s in one]), whole[1]]),
    )


if __name__ == "__main__":
    sys.exit(main())
