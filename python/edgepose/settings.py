"""Every tuning value of :func:`edgepose.estimate`, in one place.

Distances that depend on the object are given as fractions of its diameter
(``d``), so one setting serves a 5 cm part and a 30 cm box. Change a value
here (or pass ``settings=EstimateSettings(...)``) and every caller — the
CLI, the catalogue, the benchmarks — sees it.
"""

from __future__ import annotations

import functools
import os
from dataclasses import asdict, dataclass, fields, is_dataclass, replace
from typing import Any

from edgepose import _core

#: The segmentation's defaults, defined once in the core (``SegmentSettings::default``
#: in ``rust/src/segment.rs``); the evidence for each is in ``docs/tuning.md``.
_SEGMENT_DEFAULTS = _core.SegmentSettings()


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
class SegmentSettings:
    """Tuning of stage 1's segmentation (``rust/src/segment.rs``): which
    points of the observed cloud are the object. Distances are in the
    cloud's median point spacing ("spacings") or the object's diameter;
    image neighbourhoods are taken by viewing direction."""

    neighbours: int = _SEGMENT_DEFAULTS.neighbours
    """Clouds of fewer than twice this many points are kept whole; a point
    with fewer than a quarter of this many neighbours is an outlier."""
    outlier_sigmas: float = _SEGMENT_DEFAULTS.outlier_sigmas
    """A point with fewer than ``1 / (1 + outlier_sigmas)`` of the cloud's
    median number of neighbours is a flying pixel."""
    cluster_spacings: float = _SEGMENT_DEFAULTS.cluster_spacings
    """Points closer than this many spacings are one surface: surfaces
    apart by a depth jump fall into separate components."""
    min_component_fraction: float = _SEGMENT_DEFAULTS.min_component_fraction
    """A component apart from the largest is kept as part of the object
    when it has at least this fraction of the largest one's points ..."""
    max_component_offset: float = _SEGMENT_DEFAULTS.max_component_offset
    """... its centroid lies within this many diameters of the largest one's ..."""
    max_shadowed_fraction: float = _SEGMENT_DEFAULTS.max_shadowed_fraction
    """... and less than this fraction of its points lie in the largest
    one's shadow (a mask's spill onto the table or wall behind is all shadow)."""
    shadow_spacings: float = _SEGMENT_DEFAULTS.shadow_spacings
    """The shadow: within this many spacings of the largest component in
    the image, and behind it."""
    occluder_points: int = _SEGMENT_DEFAULTS.occluder_points
    """A component in front of at least this many of the object's points ..."""
    occluder_fraction: float = _SEGMENT_DEFAULTS.occluder_fraction
    """... smaller than this fraction of the object ..."""
    occluder_margin: float = _SEGMENT_DEFAULTS.occluder_margin
    """... and this many diameters or more in front of them is an occluder
    the mask spilled onto: dropped."""
    steep_faces: bool = _SEGMENT_DEFAULTS.steep_faces
    """Put back the faces the steps above cut away because they are seen
    nearly edge-on (sparse in space, dense in the image): dropped points
    whose depth is a smooth ramp meeting the object's edge."""
    ramp_spacings: float = _SEGMENT_DEFAULTS.ramp_spacings
    """A steep face's image neighbourhood, spacings at the median depth."""
    ramp_neighbours: int = _SEGMENT_DEFAULTS.ramp_neighbours
    """A dropped point's depth plane is fitted to it and at least this many
    dropped image neighbours ..."""
    ramp_noise: float = _SEGMENT_DEFAULTS.ramp_noise
    """... with an rms residual within this many times the object's own
    (the sensor's noise) ..."""
    ramp_min_noise_spacings: float = _SEGMENT_DEFAULTS.ramp_min_noise_spacings
    """... or this many spacings, whichever is larger (quantised depth)."""
    ramp_link: float = _SEGMENT_DEFAULTS.ramp_link
    """An image neighbour within this many of those tolerances of the plane
    in depth links the face to the object."""

    def core(self) -> _core.SegmentSettings:
        """These settings as the core takes them (built once)."""
        return _core_segment(self)


@functools.lru_cache(maxsize=64)
def _core_segment(settings: SegmentSettings) -> _core.SegmentSettings:
    return _core.SegmentSettings(**asdict(settings))


@dataclass(frozen=True)
class RetrieveSettings:
    """Tuning of stages 2 and 3 (:mod:`edgepose.stages.retrieval`): the
    codebook views most similar to the query's map, posed as candidates and
    verified on the query's keypoints."""

    keypoints: int = 32
    """Observed keypoints (the map's first farthest-point samples) that verify candidates."""
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
    candidates_on_two_cores: bool = True
    """Share the candidates' keypoint alignment and their stage-4 scores
    (2 to 63 candidates: a first search's ``k``) between the caller's
    thread and one of the Rust core's (64 or more run on all the core's
    threads anyway; each thread takes the next candidate not yet taken,
    ``rust/src/threads.rs``, ``on_two_cores``): the same poses and
    scores, sooner where a second core is free. :func:`edgepose.estimate_many`,
    when its objects share the cores on several threads, runs them on one."""


@dataclass(frozen=True)
class ScoreSettings:
    """Tuning of stage 4 (:mod:`edgepose.stages.scoring`): the free-space
    test every pose is scored by, and how candidates are ranked."""

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


@dataclass(frozen=True)
class RefineSettings:
    """Tuning of stage 5 (:mod:`edgepose.stages.refine`): coarse ICP of the
    best distinct candidates (the hypotheses), the pick among them, and the
    final ICP polish of the winner."""

    hypotheses: int = 3
    """Distinct candidate poses refined by a coarse ICP; the best-scoring one
    wins. A near-symmetric object verifies almost equally well either way up;
    the fit after ICP and free space tell them apart."""
    distinct_deg: float = 20.0
    """Candidate rotations closer than this (degrees) to a kept one are the same hypothesis."""
    hypothesis_points: int = 256
    """Observed points used by the hypotheses' coarse ICP and their scoring."""
    hypothesis_iterations: int = 7
    """Coarse ICP iterations per hypothesis: enough to tell hypotheses apart, not to polish them."""
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
    fraction (0–1) of its RMSE: then each of those is polished too (the final
    ICP, ``icp_iterations`` on ``icp_points``) and the lowest polished RMSE
    wins. The winner's polish is the stage's final polish (not made twice).
    0: never (the cheaper, less robust search). The coarse ICP's 256 points
    decide such near ties by noise on a small fragment."""
    max_centre_offset: float = 1.25
    """× the model's radius (its farthest point from its centre). Every
    observed point of the object lies within one radius of the model's
    centre, so a refined pose whose centre is farther from the observed
    centroid than this (ICP drifting off, onto background) is not used."""
    icp_points: int = 1024
    """Observed points used by the final ICP polish of the winner."""
    icp_iterations: int = 12
    """Iterations of the final ICP polish (0: the coarse ICP result only);
    most polishes converge well before."""
    icp_max_distance: float = 0.1
    """× d. ICP ignores pairs farther apart than this."""
    min_icp_inliers: int = 16
    """An ICP result with fewer inlier pairs is not trusted."""
    coarse_icp_on_two_cores: bool = True
    """Share the coarse ICPs of a search's new hypotheses, when there are
    2 or 3 (the first search's; the second search's starts not already
    refined by the first), between the caller's thread and one of the Rust
    core's (4 or more run on all the core's threads anyway; each thread
    takes the next hypothesis not yet taken, so one slow to wake holds the
    caller up by at most the one it took, ``rust/src/threads.rs``,
    ``on_two_cores``): the same poses, sooner where a second core is free.
    :func:`edgepose.estimate_many`, when its objects share the cores on
    several threads, runs them one after another."""
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


@dataclass(frozen=True)
class SecondSearchSettings:
    """When a first pose is doubtful (:func:`edgepose.search.doubtful`) and
    how the second, wider search then goes (:func:`edgepose.search.second_search`)."""

    retry_below_inlier_fraction: float = 0.95
    """A refined pose explaining fewer of the observed points than this
    fraction (0–1) within ``doubt_inlier_distance`` is doubtful: correct
    poses rarely fall below it, wrong ones mostly do ..."""
    doubt_inlier_distance: float = 0.04
    """× d. Looser than ``refine.hypothesis_inlier_distance``, so that depth
    noise at range does not make a correct pose doubtful."""
    retry_above_free_space: float = 0.03
    """... as is one violating free space (a fraction 0–1 of its
    camera-facing model points, one grid cell of slack at the silhouette's
    edge: ``stages.rim_tolerant_violation``) more than this. A doubtful pose is searched
    again: ``pair_poses`` poses voted for by point pairs (and ``retry_k``
    candidates down the cosine ranking) join the first search's candidates,
    ``retry_hypotheses`` of them are refined, and the result that explains
    more points net of free-space violations wins. Trusted poses cost
    nothing extra."""
    retry_above_scene_violation: float = 0.1
    """... as is one (with the frame's depth given) whose camera-facing model
    points off the observed silhouette stand in front of the scene's depth
    for more than this share of them (the pose leaves an occluder's shadow)."""
    retry_below_confidence: float = 0.8
    """... and so is one whose ``Pose.confidence`` (0–1) is below this: a
    wrong pose can explain the few points of a mostly hidden object well
    and still get a middling confidence (the confidence model was fitted
    with this rule deciding the second searches)."""
    pair_poses: int = 8
    """Poses voted for by pairs of oriented points (``stages.pair_poses``)
    that join a doubtful pose's second search (0: none): occlusion is what
    makes a pose doubtful and what the map's code cannot see past; point
    pairs see past it."""
    pair_scene_points: int = 160
    """Observed points (farthest-point samples) that vote for pair poses ..."""
    pair_reference_stride: int = 2
    """... every n-th of them as a reference point (fewer references: less voting time)."""
    retry_k: int = 0
    """Candidates down the cosine ranking that join the second search (0
    or ≤ ``retrieve.k``: none); with ``pair_poses`` they add little."""
    retry_hypotheses: int = 6
    """Hypotheses refined by the second search (its ``refine.hypotheses``)."""


@dataclass(frozen=True)
class TurnSettings:
    """The turned-pose check (:func:`edgepose.stages.turned_pose`): a pose's
    best turned rival replaces it when it explains the view better."""

    check_below: float = 0.05
    """A pose whose flip margin (``Pose.evidence["flip_margin"]``: how much
    better it explains the view than itself turned onto itself, the
    near-symmetric object's usual mistake) is below this has its best
    turned rival refined as the pose was (coarse ICP, then the polish) ...
    (any value ≤ −1: never)."""
    switch_gain: float = 0.02
    """... and the pose is that rival instead when it explains this much
    more of the view (inlier fraction minus violations, 0–1): a margin
    against noise, so a right pose is rarely turned wrong."""


@dataclass(frozen=True)
class AlternativeSettings:
    """``Pose.alternatives`` (:func:`edgepose.stages.alternatives`,
    :mod:`edgepose.unseen_turn`): other poses that explain the view nearly as well."""

    max_count: int = 3
    """At most this many other poses that explain the view nearly as well
    (0: none looked for) ..."""
    within: float = 0.05
    """... within this much of the pose's share of explained points net of
    violations (inlier fraction minus free-space and scene violations).
    Their count and the best one's margin are evidence of
    ``Pose.confidence``, whose model was fitted with these two values.
    The same margin as ``refine.hypothesis_free_space_margin``."""
    unseen_turns: int = 8
    """When the object has a near-symmetry axis (a mug's body) and the view
    leaves the turn about it open (the handle unseen): at most this many
    of those turns join ``Pose.alternatives``, spread over what the view
    allows (-1: the turn is not looked for; :mod:`edgepose.unseen_turn`).
    Enough to span a half circle at the 0.1 × diameter spacing of a mug."""


@dataclass(frozen=True)
class EstimateSettings:
    """Tuning of :func:`edgepose.estimate`, nested by stage: a stage's
    settings are one frozen dataclass (``settings.refine.icp_iterations``;
    ``with_(**{"refine.icp_iterations": 20})``). Tuned on training shapes and
    seeds disjoint from the reported benchmark
    (``benches/bench_pose.py --tune`` writes their figures to ``benches/TUNING.md``).
    The evidence for each default is in ``docs/tuning.md``."""

    # --- prepare the query (stage 1)
    max_cloud_points: int = 1536
    """Larger clouds are subsampled (seeded) first: bounded time and memory;
    1,536 points cover an object densely for a 512-point map."""
    segment: bool = True
    """Drop statistical outliers and components split off by depth jumps
    (background a spilled mask picked up, flying pixels) before anything else."""
    segmentation: SegmentSettings = SegmentSettings()
    """How stage 1 tells the object's points from spill and flying pixels
    (with ``segment`` on): :class:`SegmentSettings`."""
    support_plane: bool = True
    """Given the depth frame (``estimate``, ``estimate_many``, a
    ``Tracker``'s frames): drop the cloud's points on the surface the
    object stands on or in front of (a table, a wall), found around the
    mask (:func:`edgepose.stages.on_support_plane`). On by default: spill
    onto a table that meets the object crosses no depth jump, so
    segmentation keeps it and the pose then explains fewer of its points (a
    second search, a lower confidence; README, "On a table")."""
    subsample_seed: int = 1
    """Seed of the (deterministic) subsampling of the cloud for ICP (the
    hypotheses' points, the polish's, the confidence's and the tracker's)."""

    # --- the stages after it
    retrieve: RetrieveSettings = RetrieveSettings()
    """Stages 2 and 3, retrieve and verify candidates: :class:`RetrieveSettings`."""
    score: ScoreSettings = ScoreSettings()
    """Stage 4, score poses: :class:`ScoreSettings`."""
    refine: RefineSettings = RefineSettings()
    """Stage 5, refine hypotheses: :class:`RefineSettings`."""
    second_search: SecondSearchSettings = SecondSearchSettings()
    """A second, wider search when the first pose is doubtful: :class:`SecondSearchSettings`."""
    turn: TurnSettings = TurnSettings()
    """The turned pose, when the flip margin is low: :class:`TurnSettings`."""
    alternatives: AlternativeSettings = AlternativeSettings()
    """``Pose.alternatives``: :class:`AlternativeSettings`."""

    def __post_init__(self) -> None:
        for name, stage in _STAGES.items():
            value = getattr(self, name)
            if not isinstance(value, stage):
                moved = f" (the old {name}={value!r:.20} is now {_RENAMED[name]!r})" if name in _RENAMED else ""
                raise TypeError(f"{name} must be an edgepose.{stage.__name__}, got {value!r:.80}{moved}")

    def with_(self, **changes: Any) -> EstimateSettings:
        """A copy with some fields changed; a stage's field by its dotted
        name: ``with_(**{"refine.icp_iterations": 20})``. ``TypeError``
        naming a name that is no setting (and, for a name from before the
        settings were nested, the dotted name it is now). No changes: these
        settings themselves (``estimate`` asks for its shortcuts on every call)."""
        if not changes:
            return self
        nested: dict[str, dict[str, Any]] = {}
        for name in list(changes):
            if name not in _NAMES:
                raise TypeError(unknown_setting(name))
            stage, dot, field_name = name.partition(".")
            if dot:
                nested.setdefault(stage, {})[field_name] = changes.pop(name)
        for stage, stage_changes in nested.items():
            changes[stage] = replace(changes.get(stage, getattr(self, stage)), **stage_changes)
        return replace(self, **changes)

    def as_dict(self) -> dict[str, object]:
        """Every field and its value (for reports)."""
        return asdict(self)

    def flat(self) -> dict[str, object]:
        """Every field and its value, a stage's fields by their dotted names
        (``refine.icp_iterations``): what :meth:`with_` takes."""
        out: dict[str, object] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in _STAGES:
                out.update({f"{f.name}.{g.name}": getattr(value, g.name) for g in fields(value)})
            else:
                out[f.name] = value
        return out


#: The stages: every field of :class:`EstimateSettings` that is itself a
#: dataclass, by name, and its class.
_STAGES: dict[str, type] = {f.name: type(f.default) for f in fields(EstimateSettings) if is_dataclass(f.default)}

#: Fields that lost a prefix or suffix repeating their stage's name when the
#: settings were nested by stage (the others kept theirs): old flat name → dotted name.
_RENAMED = {
    "alternatives": "alternatives.max_count",
    "alternative_within": "alternatives.within",
    "unseen_turn_alternatives": "alternatives.unseen_turns",
    "turn_check_below": "turn.check_below",
    "turn_switch_gain": "turn.switch_gain",
}

DEFAULT_SETTINGS = EstimateSettings()

#: Every name :meth:`EstimateSettings.with_` takes: the fields, a stage's fields dotted.
_NAMES = frozenset([*(f.name for f in fields(EstimateSettings)), *DEFAULT_SETTINGS.flat()])


def unknown_setting(name: str) -> str:
    """Why ``name`` is no setting of :class:`EstimateSettings`: where it is
    now if it was a flat one before the settings were nested by stage (or is
    a stage's field named without its stage)."""
    dotted = _RENAMED.get(name) or next((n for n in DEFAULT_SETTINGS.flat() if n.partition(".")[2] == name), None)
    if dotted is not None:
        return f"no setting {name!r}: it is {dotted!r} (settings are nested by stage)"
    return f"no setting {name!r} (EstimateSettings().flat() names every one)"


#: ICP converges in tens of iterations; more is a caller's mistake, not a wish.
MAX_ICP_ITERATIONS = 1000
