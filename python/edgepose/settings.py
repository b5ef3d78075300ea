"""Every tuning value of :func:`edgepose.estimate`, in one place.

Distances that depend on the object are given as fractions of its diameter
(``d``), so one setting serves a 5 cm part and a 30 cm box. Change a value
here (or pass ``settings=EstimateSettings(...)``) and every caller — the
CLI, the catalogue, the benchmarks — sees it.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, replace
from typing import Any


def usable_cores() -> int:
    """The cores this process may run on: its CPU affinity where the OS
    has one (a robot stack pinning a process to two of eight cores, or
    ``taskset``), else every core. How many threads edgepose's parallel
    work starts by default (the encoder's, ``estimate_many``'s objects);
    the Rust core's pool counts the same way (and a container's CPU quota)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


@dataclass(frozen=True)
class EstimateSettings:
    """Tuning of :func:`edgepose.estimate`. Tuned on training shapes and
    seeds disjoint from the reported benchmark
    (``benches/bench_pose.py --tune`` writes their figures to ``benches/TUNING.md``)."""

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
    steep_faces: bool = True
    """Put back the faces segmentation cut away because they are seen nearly
    edge-on (sparse in space, dense in the image): dropped outliers and small
    fragments whose depth is a smooth ramp meeting the object's edge; a whole
    component dropped as spill stays out (``rust/src/segment.rs``)."""
    support_plane: bool = True
    """Given the depth frame (``estimate``, ``estimate_many``, a
    ``Tracker``'s frames): drop the cloud's points on the surface the
    object stands on or in front of (a table, a wall), found around the
    mask (:func:`edgepose.stages.on_support_plane`, ~0.1 ms). Spill onto a
    table that meets the object crosses no depth jump, so segmentation
    keeps it, and the pose then explains fewer of its points: a second
    search and a lower confidence (README, "On a table")."""
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
    depth on its ray contradicts the view (free-space violation) ..."""
    free_space_noise_sigmas: float = 3.0
    """... or, when more, this many standard deviations of the sensor's
    depth noise at the object's depth (``depth_noise``): a real sensor's
    noise must not read as a contradiction (0: the fraction of d alone)."""
    depth_noise: tuple[float, float, float] = (0.0012, 0.0019, 0.4)
    """``(a, b, c)``: the sensor's depth-noise std at depth z is
    ``a + b (z − c)²`` metres. The default is a structured-light camera's
    (Kinect v1, Asus Xtion; Nguyen, Izadi and Lovell 2012); a quieter
    sensor (a stereo or time-of-flight camera at short range) may lower it."""
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
    hypothesis_iterations: int = 7
    """Coarse ICP iterations per hypothesis. On the tuning shapes
    (2026-11-25, with ``icp_iterations=12``): 10: 97.3 % of poses correct;
    7: 97.5 %; 5: 96.2 %."""
    hypothesis_inlier_distance: float = 0.02
    """× d. After ICP, an observed point this close to the model is an inlier."""
    hypothesis_inlier_ratio: float = 0.9
    """Refined hypotheses compete only when they explain at least this
    fraction of the best one's inliers ..."""
    hypothesis_free_space_margin: float = 0.05
    """... and violate free space by at most this much more than the least
    violating one; among those the lowest ICP RMSE wins (a turned-over
    near-symmetric object fits a few per cent worse) ..."""
    tie_polish_within: float = 0.1
    """... unless rivals (different poses) among them come within this
    fraction of its RMSE: then each of those is polished too (the final ICP,
    ``icp_iterations`` on ``icp_points``) and the lowest polished RMSE wins.
    The coarse ICP's 256 points decide such near ties by noise on a small
    fragment. The winner's polish is the stage's final polish (not made
    twice). Cost (``benches/bench_confidence_cost.py --setting
    tie_polish_within``, 120 tuning-part views, ties polished in 34):
    +0.06 ms at the paired median (clean +0.04, 40 % visible +0.49),
    +0.55 ms on average. 0: never (the cheaper, less robust search).
    Tuning parts (6 × 20 views a level, 2026-11-27): all eleven levels 96.0
    → 96.9 % correct, none worse; visible20 83.3 → 86.7 %, visible40 90.8 →
    91.7 %, visible70 95.0 → 96.7 %, occluded30_spill5 and partial 95.8 →
    97.5 % (0.05: 85.8, 90.8, –, 97.5, 97.5 %; 0.2 as 0.1)."""
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
    in 90 %). A doubtful pose is searched again: ``pair_poses`` poses voted
    for by point pairs (and ``retry_k`` candidates down the cosine ranking)
    join the first search's candidates, ``retry_hypotheses`` of them are
    refined, and the result that explains more points net of free-space
    violations wins. Trusted poses cost nothing extra."""
    retry_above_scene_violation: float = 0.1
    """... as is one (with the frame's depth given) whose camera-facing model
    points off the observed silhouette stand in front of the scene's depth
    for more than this share of them (the pose leaves an occluder's shadow)."""
    retry_below_confidence: float = 0.8
    """... and so is one whose ``Pose.confidence`` is below this: a wrong
    pose can explain the few points of a mostly hidden object well, and
    then often explains only 75–90 % of them within 0.02 d where the truth
    explains 95–100 %, with a confidence of 0.5–0.8. On the tuning shapes
    (``bench_pose.py --tune --views 40``, 2026-11-29, 0.5 → 0.8 with the
    confidence refitted for it), from clouds: 40 % visible 88.3 → 90.8 %
    correct, 70 % visible 97.1 → 97.5 %, 20 % visible 84.6 → 85.4 %, no
    level worse; stressed 96.5 → 96.9 %. Interleaved on the same views
    (before the refit): second searches 55.8 → 58.4 % of them, median and
    p90 latency the same; 0.9 as 0.8 with more second searches; on other
    views of 8 parts (seeds 777950+) occluded levels 80.5 → 81.6 %. The
    price: the confidence ranks a little worse at the top (``export/README.md``,
    the 2026-11-29 fits). 0.5, the trust rule's threshold, before."""
    pair_poses: int = 8
    """Poses voted for by pairs of oriented points (``stages.pair_poses``)
    that join a doubtful pose's second search (0: none). Occlusion is what
    makes a pose doubtful, and it is what the map's code cannot see past:
    on the tuning shapes (6 CAD parts × 8 views × 11 stress levels,
    2026-11-25) the second search with these poses instead of 112 more
    cosine candidates took ADD(-S) from 77.8 to 95.6 % overall (40 %
    visible 31 → 85 %, 20 % visible 21 → 81 %, 70 % visible + 5 px spill
    65 → 98 %) and the p90 latency from 26 to 20 ms; with both, 95.6 % and
    30 ms. Voting in every first search too gained 0–2 points at a median
    of 11–13 ms instead of 9.5."""
    pair_scene_points: int = 160
    """Observed points (farthest-point samples) that vote for pair poses ...
    On the tuning shapes (2026-11-25): 192 points 97.0 % of poses correct,
    p90 19.9 ms; 160: 97.0 %, p90 18.8 ms; 128: 96.8 %, p90 18.3 ms."""
    pair_reference_stride: int = 2
    """... every n-th of them as a reference point (~2–3 ms on 2 cores)."""
    retry_k: int = 0
    """Candidates down the cosine ranking that join the second search (0
    or ≤ ``k``: none). Before point pairs, 128 (64: 73.7 % of the tuning
    poses correct, 128: 77.8 %, 256: 79.0 %); with them, 128 add nothing
    (95.6 % either way) and cost ~10 ms per doubtful view."""
    retry_hypotheses: int = 6
    """Hypotheses refined by the second search (5: 95.1 % of the tuning
    poses correct, 8: 95.6 %; 2026-11-25, with ``hypothesis_iterations=7``
    and ``icp_iterations=12``: 6 and 8 both 97.5 %)."""
    max_centre_offset: float = 1.25
    """× the model's radius (its farthest point from its centre). Every
    observed point of the object lies within one radius of the model's
    centre, so a refined pose whose centre is farther from the observed
    centroid than this (ICP drifting off, onto background) is not used."""
    icp_points: int = 1024
    """Observed points used by the final ICP polish of the winner."""
    icp_iterations: int = 12
    """Iterations of the final ICP polish (0: the coarse ICP result only).
    A third of polishes ran all 20 (most converge in 3–7): 12 measured
    the same on the tuning shapes (97.3 % of poses correct; 10: 97.3 % with
    one 40 % visible view fewer), and, with ``hypothesis_iterations=7``
    and ``retry_hypotheses=6``, took the crowded BOP frames' per-image time
    from ~46 to ~43 ms. With the confidence refitted on these settings (it
    decides second searches): 20 / 10 / 8 iterations and hypotheses 96.8 %,
    p90 18.3 ms; 12 / 7 / 6 97.0 %, p90 16.3–17.1 ms."""
    icp_max_distance: float = 0.1
    """× d. ICP ignores pairs farther apart than this."""
    turn_check_below: float = 0.05
    """A pose whose flip margin (``Pose.evidence["flip_margin"]``: how much
    better it explains the view than itself turned onto itself, the
    near-symmetric object's usual mistake) is below this has its best
    turned rival refined as the pose was (coarse ICP, then the polish) ...
    (any value ≤ −1: never)."""
    turn_switch_gain: float = 0.02
    """... and the pose is that rival instead when it explains this much
    more of the view (inlier fraction minus violations). Chosen on eight
    near-symmetric training parts (box, angle_block, ADIS16480, …; 10 views
    × 7 stress levels, seeds from 777600, 2026-11-25): gain 0 turned 28
    wrong poses right and 23 right ones wrong, 0.02 23 and 4, 0.05 9 and 0.
    As shipped, there 68.6 → 71.6 % of poses correct; on fresh seeds (from
    778600) 58.8 → 60.7 % (16 right, 5 wrong), and on the six tuning parts
    95.0 → 96.0 % (4 right, none wrong; the check ran on 9 % of views)."""
    alternatives: int = 3
    """``Pose.alternatives``: at most this many other poses that explain the
    view nearly as well (0: none looked for) ..."""
    alternative_within: float = 0.05
    """... within this much of the pose's share of explained points net of
    violations (inlier fraction minus free-space and scene violations).
    Their count and the best one's margin are evidence of
    ``Pose.confidence``, whose model was fitted with these two values.
    On the six tuning parts (20 views at seven levels, seeds 777000+) the
    truth was among them for 11 of 34 wrong poses at 0.03 and 0.05 alike
    and 12 at 0.1, where 21–31 % of the right occluded poses came with
    alternatives instead of 9–18 %; 0.05 is ``hypothesis_free_space_margin``."""
    unseen_turn_alternatives: int = 8
    """When the object has a near-symmetry axis (a mug's body) and the view
    leaves the turn about it open (the handle unseen): at most this many
    of those turns join ``Pose.alternatives``, spread over what the view
    allows (-1: the turn is not looked for; :mod:`edgepose.unseen_turn`).
    Enough to span a half circle at the 0.1 × diameter spacing of a mug."""
    coarse_icp_on_two_cores: bool = True
    """Split the coarse ICPs of a search's new hypotheses, when there are
    2 or 3 (the first search's; the second search's starts not already
    refined by the first), between the caller's thread and one of the Rust
    core's (4 or more run on all the core's threads anyway; the caller
    runs the core's half itself if no thread has started it when its own
    half is done, ``rust/src/threads.rs``, ``hand_over``): the same
    poses, sooner where a second core is free (on 96 tuning-part views,
    2026-11-27 08:23, ``refine_hypotheses`` 6.46 → 5.65 ms, an estimate
    0.71 ms faster at the median; ``benches/bench_confidence_cost.py
    --setting coarse_icp_on_two_cores``). :func:`edgepose.estimate_many`, when its objects share the
    cores on several threads, runs them one after another."""
    flip_rival_beside_polish: bool = True
    """Hand the search for the confidence's turned rival of the pose (its
    flip margin's, :func:`edgepose.stages.flip_rival`) to one of the Rust
    core's threads before ICP polishes the pose in the caller's, instead of
    searching after the polish: the same rival either way (it starts from
    the pose before the polish), sooner where a second core is free. The
    caller takes the search back and runs it itself if no thread has
    started it when the confidence asks (``rust/src/threads.rs``,
    ``hand_over``). :func:`edgepose.estimate_many`, when its objects share
    the cores on several threads, searches after."""
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
