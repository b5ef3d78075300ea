"""Export already-trained networks again with the current graph, without
retraining: read the weights out of shipped ONNX files into the torch
modules, then export and parity-check as training does.

    .venv/bin/python -m export.reexport [--source python/edgepose/models] [--out python/edgepose/models]

Used when a change moves work out of the graph but keeps the network's
arithmetic (the neighbour grouping moved into the Rust core this way); the
manifest keeps the original training record.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from export.network import Encoder, InPlaneRotation
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
    hashes = export_onnx(encoder, irr, args.out)
    # Same weights, same outputs: the confidence model fitted for them still holds.
    manifest = write_manifest(args.out, hashes, encoder, irr, source["training"], source.get("confidence"))
    print(f"re-exported to {args.out}: {manifest['parameters']['total']} parameters", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
