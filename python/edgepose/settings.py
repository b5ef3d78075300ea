"""Every tuning value of :func:`edgepose.estimate`, in one place.

Distances that depend on the object are given as fractions of its diameter
(``d``), so one setting serves a 5 cm part and a 30 cm box. Change a value
here (or pass ``settings=EstimateSettings(...)``) and every caller — the
CLI, the catalogue, the benchmarks — sees it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any


@dataclass(frozen=True)
class EstimateSettings:
    """Tuning of :func:`edgepose.estimate`. Tuned on training shapes and
    seeds disjoint from the reported benchmark (``benches/TUNING.md``)."""

    # --- prepare the query
    max_cloud_points: int = 2048
    """Larger clouds are subsampled (seeded) first: bounded time and memory;
    2,048 points cover an object densely for a 512-point map."""
    segment: bool = True
    """Drop statistical outliers and components split off by depth jumps
    (background a spilled mask picked up, flying pixels) before anything else."""
    min_component_fraction: float = 0.01
    """A segmented component apart from the largest is kept as part of the
    object when it has at least this fraction of the largest one's points ..."""
    max_component_offset: float = 0.8
    """... and its centroid lies within this many diameters of the largest one's."""
    shadow_spacings: float = 4.0
    """A segmented component counts as background when most of it lies in
    another's shadow: within this many point spacings of it in the image,
    and behind it (a mask's spill onto the table or wall behind)."""
    max_shadowed_fraction: float = 0.5
    """... "most" being at least this fraction of its points."""
    keypoints: int = 32
    """Observed keypoints (the map's first farthest-point samples) that verify candidates."""

    # --- retrieve and verify candidates
    k: int = 16
    """Codebook views retrieved by cosine similarity and verified."""
    align_iterations: int = 3
    """Iterations that move each candidate's translation so the keypoints land
    on the model (its centroid-based translation is off when part of the
    object is hidden); 0 keeps the centroid translation."""
    candidate_inlier_distance: float = 0.1
    """× d. A keypoint this close to a candidate's model is an inlier; farther
    ones cost this much (truncated). Candidates are only as good as the
    2,100-view grid and the in-plane angle, so this is loose."""
    free_space_tolerance: float = 0.03
    """× d. A camera-facing model point this far in front of the observed
    depth on its ray contradicts the view (free-space violation)."""
    candidate_free_space_weight: float = 0.5
    """Weight of the free-space violation fraction against the normalised
    truncated fit (fit / inlier distance) when ranking candidates."""
    free_space_model_stride: int = 4
    """Every n-th of the codebook's model points takes part in the free-space test."""

    # --- refine hypotheses
    hypotheses: int = 3
    """Distinct candidate poses refined by a coarse ICP; the best-scoring one
    wins. A near-symmetric object verifies almost equally well either way up;
    the fit after ICP and free space tell them apart."""
    distinct_deg: float = 20.0
    """Candidate rotations closer than this (degrees) to a kept one are the same hypothesis."""
    hypothesis_points: int = 256
    """Observed points used by the hypotheses' coarse ICP and their scoring."""
    hypothesis_iterations: int = 10
    hypothesis_inlier_distance: float = 0.02
    """× d. After ICP, an observed point this close to the model is an inlier."""
    hypothesis_inlier_ratio: float = 0.9
    """Refined hypotheses compete only when they explain at least this
    fraction of the best one's inliers ..."""
    hypothesis_free_space_margin: float = 0.05
    """... and violate free space by at most this much more than the least
    violating one; among those the lowest ICP RMSE wins (a turned-over
    near-symmetric object fits a few per cent worse)."""
    # --- a second, wider search when the first pose is doubtful
    retry_below_inlier_fraction: float = 0.95
    """A refined pose explaining fewer of the observed points than this
    (0–1) within ``doubt_inlier_distance`` is doubtful: on the tuning shapes
    correct poses rarely do (4–8 % of them clean or 70 % visible, 17 % at
    1–1.5 m with Kinect noise), wrong ones mostly do (72–100 %) ..."""
    doubt_inlier_distance: float = 0.04
    """× d. Looser than ``hypothesis_inlier_distance``: depth noise at range
    (σ 3 mm at 1.5 m) must not make a correct pose doubtful (at 0.02 d, 97 %
    of correct far views were searched again)."""
    retry_above_free_space: float = 0.03
    """... as is one violating free space more than this (correct: ≤ 0.02
    in 90 %). A doubtful pose is searched again with ``retry_k`` candidates
    and ``retry_hypotheses`` hypotheses (occlusion and spill push the right
    view down the cosine ranking), and the result that explains more points
    net of free-space violations wins. Trusted poses cost nothing extra."""
    retry_k: int = 128
    """Candidates of the second search (0 or ≤ k: no second search). On the
    tuning shapes (6 CAD parts × 8 views × 11 stress levels, 2026-11-24):
    64 candidates and 5 hypotheses 73.7 % of poses correct overall (p90
    19 ms), 128 and 8 77.8 % (70 % visible 70.8 → 75.0 %, 40 % visible 25.0
    → 31.2 %, 70 % visible + 5 px spill 54.2 → 64.6 %; p90 26 ms), 256 and
    12 80.5 % (p90 38 ms); the median stayed at 9.5 ms: only doubtful poses
    pay."""
    retry_hypotheses: int = 8
    """Hypotheses refined by the second search."""
    max_centre_offset: float = 1.25
    """× the model's radius (its farthest point from its centre). Every
    observed point of the object lies within one radius of the model's
    centre, so a refined pose whose centre is farther from the observed
    centroid than this (ICP drifting off, onto background) is not used."""
    icp_points: int = 1024
    """Observed points used by the final ICP polish of the winner."""
    icp_iterations: int = 20
    """Iterations of the final ICP polish (0: the coarse ICP result only)."""
    icp_max_distance: float = 0.1
    """× d. ICP ignores pairs farther apart than this."""
    min_icp_inliers: int = 16
    """An ICP result with fewer inlier pairs is not trusted."""
    subsample_seed: int = 1
    """Seed of the (deterministic) subsampling of the cloud for ICP."""

    def with_(self, **changes: Any) -> EstimateSettings:
        """A copy with some fields changed."""
        return replace(self, **changes)

    def as_dict(self) -> dict[str, object]:
        """Every field and its value (for reports)."""
        return asdict(self)


DEFAULT_SETTINGS = EstimateSettings()
#: ICP converges in tens of iterations; more is a caller's mistake, not a wish.
MAX_ICP_ITERATIONS = 1000
