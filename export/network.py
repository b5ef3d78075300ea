"""The two learned heads of edgepose, in torch (training and export only).

A map is (N, 3) points in a view frame (z along the optical axis), centred,
in unit-sphere scale. The camera may have turned by any angle θ about z, so:

* the **backbone** computes per-point features that do not change under such
  a turn, by construction: each centre point sees its neighbours' offsets in
  its own radial frame (rotated by −φ, its polar angle), plus its radius and
  depth (:func:`map_features`). Those features are the graph's inputs: the
  Rust core computes them at run time, groups (each centre's kNN) included
  (inside ONNX, a top-k and dozens of small operations were slow:
  ``export/README.md``); :func:`neighbour_groups` and :func:`map_features`
  during training.
* the **code head** max-pools those features into a unit code: identical for
  every in-plane turn, and trained (triplet loss on cosine, margin 0.1) to
  differ between viewpoints.
* the **spectrum** is the angular Fourier transform of learned per-point
  weights: ``S[c, m] = mean_i w_c(i) · e^{i m φ_i}``. Turning the map by θ
  multiplies ``S[c, m]`` by ``e^{i m θ}``. The codebook stores it per view.
* the **IRR head** correlates an observed spectrum with a candidate's over a
  grid of angles (learned weight per harmonic, learned sharpness) and returns
  the soft-argmax angle as (cos θ, sin θ): the turn that carries the
  candidate's map onto the observed one.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

MAP_POINTS = 512
CENTRES = 128
NEIGHBOURS = 16
CODE_SIZE = 64
CHANNELS = 8
HARMONICS = 8
SPECTRUM_SIZE = CHANNELS * HARMONICS * 2
ANGLE_STEPS = 360


def mlp(*sizes: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        layers += [nn.Linear(a, b), nn.ReLU()]
    return nn.Sequential(*layers)


class Encoder(nn.Module):
    """maps (B, N, 3) → code (B, CODE_SIZE) unit vectors, spectrum (B, SPECTRUM_SIZE).

    The exported graph is :meth:`forward`, from the maps' features
    (:func:`map_features`; at run time the Rust core computes the same
    ones, bit for bit); training calls :meth:`encode` on maps."""

    def __init__(self) -> None:
        super().__init__()
        self.local = mlp(6, 32, 64)
        self.point = mlp(64 + 2, 128, 256)
        self.code = nn.Sequential(nn.Linear(256, 256), nn.ReLU(), nn.Linear(256, CODE_SIZE))
        self.weights = nn.Linear(256, CHANNELS)

    def encode(self, maps: torch.Tensor, neighbours: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``maps`` (B, N, 3) float; ``neighbours`` (B, CENTRES, NEIGHBOURS)
        int64: each centre's nearest map points (:func:`neighbour_groups`)."""
        return self(*map_features(maps, neighbours))

    def forward(
        self, edge: torch.Tensor, own: torch.Tensor, cos_m: torch.Tensor, sin_m: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The maps' features (:func:`map_features`) → code, spectrum."""
        b = edge.shape[0]
        # The layers see rows of one matrix (a 2-D input exports as Gemm,
        # which onnxruntime fuses with its bias and ReLU: the same numbers).
        local = self.local(edge.reshape(-1, edge.shape[-1]))
        local = local.reshape(b, CENTRES, NEIGHBOURS, -1).amax(dim=2)
        point_in = torch.cat([local, own], dim=-1)
        features = self.point(point_in.reshape(-1, point_in.shape[-1])).reshape(b, CENTRES, -1)

        # The maximum over the centres, as a global max-pool over them laid
        # out last, and the harmonics' sums below, as matrix products: the
        # same numbers as amax(dim=1) and einsum, which onnxruntime runs
        # about half as fast (export/README.md, "Figures").
        pooled = F.adaptive_max_pool1d(features.transpose(1, 2), 1).reshape(b, -1)
        code = F.normalize(self.code(pooled), dim=-1)

        w = self.weights(features.reshape(b * CENTRES, -1)).reshape(b, CENTRES, CHANNELS).transpose(1, 2)
        real = torch.matmul(w, cos_m) / CENTRES
        imag = torch.matmul(w, sin_m) / CENTRES
        spectrum = F.normalize(torch.stack([real, imag], dim=-1).reshape(b, SPECTRUM_SIZE), dim=-1)
        return code, spectrum


def map_features(
    maps: torch.Tensor, neighbours: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """What the encoder's layers see of maps (B, N, 3) with their neighbour
    groups (B, CENTRES, NEIGHBOURS), unchanged by a turn about z:

    * ``edge`` (B, CENTRES, NEIGHBOURS, 6): each neighbour's offset from its
      centre in the centre's radial frame (rotated by −φ, its polar angle),
      its distance, and the centre's radius and depth, all × 4 (neighbour
      offsets are ~0.1 in unit scale);
    * ``own`` (B, CENTRES, 2): each centre's radius and depth;
    * ``cos_m``, ``sin_m`` (B, CENTRES, HARMONICS): cos(mφ), sin(mφ).

    The Rust core's ``map_features`` computes the same f32 operations in
    the same order."""
    b, n, _ = maps.shape
    # Maps are in farthest-point order, so the first CENTRES points are an
    # even subset: use them as group centres.
    centres = maps[:, :CENTRES, :]
    x, y, z = centres[..., 0], centres[..., 1], centres[..., 2]
    r = torch.sqrt(x * x + y * y + 1e-8)
    cos_phi, sin_phi = x / r, y / r

    offset = torch.arange(b, device=maps.device).view(b, 1, 1) * n
    grouped = maps.reshape(b * n, 3)[(neighbours + offset).reshape(-1)]
    d = grouped.reshape(b, CENTRES, NEIGHBOURS, 3) - centres.unsqueeze(2)

    c, s = cos_phi.unsqueeze(-1), sin_phi.unsqueeze(-1)
    dx = c * d[..., 0] + s * d[..., 1]
    dy = -s * d[..., 0] + c * d[..., 1]
    dz = d[..., 2]
    dist = torch.sqrt((d * d).sum(-1) + 1e-12)
    own = torch.stack([r, z], dim=-1)
    edge = torch.cat([torch.stack([dx, dy, dz, dist], dim=-1), own.unsqueeze(2).expand(-1, -1, NEIGHBOURS, -1)], -1)
    cos_m, sin_m = harmonics(cos_phi, sin_phi)
    return edge * 4.0, own, cos_m, sin_m


def neighbour_groups(maps: torch.Tensor) -> torch.Tensor:
    """(B, CENTRES, NEIGHBOURS) int64: the NEIGHBOURS nearest map points of
    each of the first CENTRES points of each map (B, N, 3). Training's
    counterpart of the Rust core's groups (``map_features``)."""
    centres = maps[:, :CENTRES, :]
    sq = ((centres.unsqueeze(2) - maps.unsqueeze(1)) ** 2).sum(-1)
    return torch.topk(sq, NEIGHBOURS, dim=2, largest=False).indices


def harmonics(cos_phi: torch.Tensor, sin_phi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """cos(mφ), sin(mφ) for m = 1..HARMONICS by the angle-addition recurrence
    (no atan2, so it exports to any ONNX opset)."""
    cos_list, sin_list = [cos_phi], [sin_phi]
    for _ in range(HARMONICS - 1):
        c, s = cos_list[-1], sin_list[-1]
        cos_list.append(c * cos_phi - s * sin_phi)
        sin_list.append(s * cos_phi + c * sin_phi)
    return torch.stack(cos_list, dim=-1), torch.stack(sin_list, dim=-1)


class InPlaneRotation(nn.Module):
    """(observed spectrum (1 or K, S), candidate spectra (K, S)) → (K, 2) = (cos θ, sin θ):
    the turn about the optical axis carrying each candidate map onto the observed map."""

    def __init__(self) -> None:
        super().__init__()
        self.harmonic_weight = nn.Parameter(torch.ones(HARMONICS))
        self.log_sharpness = nn.Parameter(torch.tensor(math.log(40.0)))
        angles = torch.arange(ANGLE_STEPS, dtype=torch.float32) * (2 * math.pi / ANGLE_STEPS)
        m = torch.arange(1, HARMONICS + 1, dtype=torch.float32)
        self.register_buffer("cos_table", torch.cos(m[:, None] * angles[None, :]), persistent=False)
        self.register_buffer("sin_table", torch.sin(m[:, None] * angles[None, :]), persistent=False)
        self.register_buffer("grid", torch.stack([torch.cos(angles), torch.sin(angles)], -1), persistent=False)

    def forward(self, observed: torch.Tensor, candidates: torch.Tensor) -> torch.Tensor:
        q = observed.reshape(-1, CHANNELS, HARMONICS, 2)
        p = candidates.reshape(-1, CHANNELS, HARMONICS, 2)
        # Q·conj(P) per channel and harmonic, summed over channels.
        a = (q[..., 0] * p[..., 0] + q[..., 1] * p[..., 1]).sum(1)  # (K, M)
        bb = (q[..., 1] * p[..., 0] - q[..., 0] * p[..., 1]).sum(1)
        a, bb = a * self.harmonic_weight, bb * self.harmonic_weight
        # Re(Q conj(P) e^{-imθ}) over the angle grid: peaks at the true turn.
        score = a @ self.cos_table + bb @ self.sin_table  # (K, ANGLE_STEPS)
        weights = torch.softmax(score * torch.exp(self.log_sharpness), dim=-1)
        return F.normalize(weights @ self.grid, dim=-1)


def parameter_count(*modules: nn.Module) -> int:
    return sum(p.numel() for m in modules for p in m.parameters())
