"""The two shipped networks, run with onnxruntime (no torch at run time).

* ``encode(maps)`` → unit codes (compared by cosine to pick viewpoints) and
  angular spectra (stored per view in a codebook);
* ``in_plane_angles(observed, candidates)`` → the turn about the optical axis
  carrying each candidate map onto the observed one (the IRR head).

The models live in ``edgepose/models/`` with a manifest of their sha256 and
the *fingerprint* a codebook records, so codes made by one encoder are never
compared with another's: the encoder file's hash, or the hash of the file a
re-export replaced when it gives the same codes bit for bit.
"""

from __future__ import annotations

import hashlib
import json
from functools import lru_cache
from pathlib import Path

import numpy as np

from edgepose import _core
from edgepose.confidence import ConfidenceModel
from edgepose.errors import EdgePoseError
from edgepose.workers import each

MODELS_DIR = Path(__file__).resolve().parent / "models"
#: The encoder graph's inputs, in order: the maps' features the core
#: computes (``_core.map_features``; ``export/network.py``, ``map_features``).
ENCODER_INPUTS = ("edge", "own", "cos_m", "sin_m")


class ModelFilesError(EdgePoseError):
    """Shipped network files missing, altered, or unreadable."""


class Encoder:
    """onnxruntime sessions of ``encoder.onnx`` and ``irr.onnx``.

    ``threads``: how many chunks of a batch of maps :meth:`encode` runs at
    once, each onnxruntime call on one core (1 suits a robot sharing its
    CPU). One map's layers are too small for one call to spread over
    cores well; chunks side by side use them fully. Sessions are safe to
    call from several threads at once.
    """

    def __init__(self, models_dir: Path | str = MODELS_DIR, threads: int = 1) -> None:
        import onnxruntime as ort

        models_dir = Path(models_dir)
        try:
            manifest = json.loads((models_dir / "manifest.json").read_text())
            blobs = {name: (models_dir / name).read_bytes() for name in ("encoder.onnx", "irr.onnx")}
        except (OSError, ValueError) as e:
            raise ModelFilesError(f"cannot read network files in {models_dir}: {e}") from None
        try:
            for name, blob in blobs.items():
                digest = hashlib.sha256(blob).hexdigest()
                if digest != manifest["files"].get(name):
                    raise ModelFilesError(f"{models_dir / name}: sha256 {digest[:12]}… differs from its manifest")
            # The codes' name: the encoder file's sha256 when exported, kept
            # by a re-export that gives the same codes bit for bit.
            self.fingerprint: str = manifest.get("fingerprint", manifest["files"]["encoder.onnx"])
            self.map_points: int = int(manifest["inputs"]["map_points"])
            self.code_size: int = int(manifest["inputs"]["code_size"])
            self.spectrum_size: int = int(manifest["inputs"]["spectrum_size"])
            # Each map's local regions: its first `centres` points and their nearest neighbours.
            self.centres: int = int(manifest["inputs"]["centres"])
            self.neighbours: int = int(manifest["inputs"]["neighbours"])
            # Harmonics of each centre's polar angle the spectrum is taken over.
            self.harmonics: int = int(manifest["inputs"]["harmonics"])
            # Pose.confidence's calibrated model, fitted for these networks (None: not shipped).
            self.confidence: ConfidenceModel | None = (
                ConfidenceModel.from_manifest(manifest["confidence"]) if "confidence" in manifest else None
            )
            # ... and the one for poses checked against the frame's depth too
            # (its scene terms); the model above where none was fitted.
            scene = manifest.get("confidence", {}).get("with_scene")
            self.scene_confidence: ConfidenceModel | None = (
                ConfidenceModel.from_manifest(scene) if scene is not None else self.confidence
            )
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise ModelFilesError(f"{models_dir / 'manifest.json'}: malformed ({type(e).__name__}: {e})") from None
        if threads < 1:
            raise ValueError(f"threads must be at least 1, got {threads}")
        self.threads = threads
        options, one_map = ort.SessionOptions(), ort.SessionOptions()
        for each_call in (options, one_map):
            each_call.intra_op_num_threads = 1
            each_call.inter_op_num_threads = 1
        # One map a call (an estimate's, a codebook build's): the batch fixed at 1
        # lets onnxruntime fold the graph's shape arithmetic away; the same
        # kernels, the same codes bit for bit.
        one_map.add_free_dimension_override_by_name("batch", 1)
        providers = ["CPUExecutionProvider"]
        try:
            self._encoder = ort.InferenceSession(blobs["encoder.onnx"], options, providers=providers)
            self._encoder_one_map = ort.InferenceSession(blobs["encoder.onnx"], one_map, providers=providers)
            self._irr = ort.InferenceSession(blobs["irr.onnx"], options, providers=providers)
        except Exception as e:  # onnxruntime raises its own untyped failures
            raise ModelFilesError(f"onnxruntime cannot load the networks in {models_dir}: {e}") from None
        inputs = tuple(i.name for i in self._encoder.get_inputs())
        if inputs != ENCODER_INPUTS:
            raise ModelFilesError(
                f"{models_dir / 'encoder.onnx'} takes inputs {list(inputs)}, this edgepose gives "
                f"{list(ENCODER_INPUTS)}: re-export it (python -m export.reexport --source {models_dir})"
            )

    def judge(self, with_scene: bool) -> ConfidenceModel | None:
        """The confidence model for a pose checked against the frame's depth
        too (``with_scene``: its scene terms) or from the cloud alone; None
        when these networks ship none."""
        return self.scene_confidence if with_scene else self.confidence

    def encode(self, maps: np.ndarray, batch: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(B, M, 3) maps → codes (B, code_size) unit float32, spectra (B, spectrum_size) float32.
        Chunks of at most ``batch`` maps run on ``threads`` threads (one map
        a call keeps a call's layers in the core's cache); each map's result
        is the same whatever the chunks."""
        maps = np.ascontiguousarray(maps, dtype=np.float32)
        if maps.ndim != 3 or maps.shape[1:] != (self.map_points, 3):
            raise ValueError(f"maps must have shape (B, {self.map_points}, 3), got {maps.shape}")
        if not len(maps):
            return np.zeros((0, self.code_size), np.float32), np.zeros((0, self.spectrum_size), np.float32)
        size = max(1, min(batch, -(-len(maps) // self.threads)))
        chunks = [maps[start : start + size] for start in range(0, len(maps), size)]

        def run(i: int) -> list[np.ndarray]:
            features = _core.map_features(chunks[i], self.centres, self.neighbours, self.harmonics)
            session = self._encoder_one_map if len(chunks[i]) == 1 else self._encoder
            return session.run(None, dict(zip(ENCODER_INPUTS, features)))

        if len(chunks) == 1:  # a query's map: its arrays as they come
            codes, spectra = run(0)
            return codes, spectra
        codes, spectra = zip(*each(run, len(chunks), self.threads))
        return np.concatenate(codes), np.concatenate(spectra)

    def in_plane_angles(self, observed: np.ndarray, candidates: np.ndarray) -> np.ndarray:
        """Angles θ (radians, (K,)) turning each candidate map onto the observed
        one about the optical axis: ``observed ≈ Rz(θ) · candidate``."""
        observed = np.ascontiguousarray(observed, dtype=np.float32).reshape(1, self.spectrum_size)
        candidates = np.ascontiguousarray(candidates, dtype=np.float32).reshape(-1, self.spectrum_size)
        (cos_sin,) = self._irr.run(None, {"observed": observed, "candidates": candidates})
        return np.arctan2(cos_sin[:, 1], cos_sin[:, 0])


@lru_cache(maxsize=4)
def default_encoder(threads: int = 1) -> Encoder:
    """The shipped networks, loaded once per process and thread count."""
    return Encoder(threads=threads)
