"""``estimate(cloud, codebook)``: the 6D pose of an object from its segmented
depth cloud, by the five stages of :mod:`edgepose.stages` (prepare the query,
retrieve codebook views, pose them, score them, refine the best hypotheses);
a doubtful pose gets a second search that adds poses voted for by point
pairs, which see past occluders (:func:`doubtful`). Every pose
carries its ``confidence`` (:mod:`edgepose.confidence`) and the object's
symmetries.

Every tuning value lives in :class:`edgepose.settings.EstimateSettings`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from edgepose.cloud import DEPTH_SCALE_MM, checked_frame
from edgepose.codebook import Codebook, CodebookError
from edgepose.confidence import box_sides, evidence_of
from edgepose.encoder import Encoder, default_encoder
from edgepose.errors import InvalidArgumentError
from edgepose.settings import DEFAULT_SETTINGS, MAX_ICP_ITERATIONS, EstimateSettings
from edgepose.stages import (
    FlipMargin,
    Hypotheses,
    PoseScores,
    Query,
    Refined,
    alternatives,
    candidate_poses,
    flip_margin,
    flip_rival,
    nearest_views,
    pair_poses,
    prepare_query,
    refine_hypotheses,
    retrieve,
    score_poses,
    turned_pose,
)
from edgepose.symmetry import NO_SYMMETRY, Symmetry, transform_from
from edgepose.unseen_turn import UnseenTurn, view_left_open


@dataclass(frozen=True, eq=False)
class Alternative:
    """Another pose of the object that explains the view nearly as well as
    the estimate (:attr:`Pose.alternatives`): where the object may be
    instead when the view cannot tell."""

    R: np.ndarray
    """(3, 3) float64 rotation object → camera."""
    t: np.ndarray
    """(3,) float64 translation, metres: ``p_cam = R @ p_obj + t``."""
    margin: float
    """How much more of the view the estimate explains than this pose:
    inlier fraction minus free-space (and scene) violations, the estimate's
    minus this one's, on the same observed points; at most
    ``settings.alternative_within``, below 0 when this one explains more."""

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) float64 ``T_cam_obj``."""
        return transform_from(self.R, self.t)


@dataclass(frozen=True, eq=False)
class Pose:
    """An object's pose in the camera frame and how it was found."""

    R: np.ndarray
    """(3, 3) float64 rotation object → camera."""
    t: np.ndarray
    """(3,) float64 translation, metres: ``p_cam = R @ p_obj + t``."""
    score: float
    """Cosine similarity of the chosen view's code to the observed one (1 is best)."""
    fit: float
    """Mean distance (metres) from the observed points to the model at this
    pose, each truncated at the inlier distance (``settings.hypothesis_inlier_distance``
    × diameter when refined, else the candidates' looser one)."""
    view: int
    """Index of the chosen codebook viewpoint (for a pose voted for by
    point pairs: the viewpoint nearest to the camera's direction)."""
    candidates: np.ndarray
    """(K,) viewpoint indices of the candidates, in order: the cosine top-K,
    best code first, then (second search) the next ones down the ranking and
    the point pairs' poses' viewpoints."""
    candidate_fit: np.ndarray
    """(K,) truncated keypoint distance of each candidate pose, metres."""
    timings: dict = field(default_factory=dict)
    """Seconds per stage, named as the stage functions: prepare_query, retrieve,
    candidate_poses, score_poses, refine_hypotheses (pair_poses when the
    second search ran), then confidence (the
    evidence, the alternatives among it, and its probability), turned_pose (only when the flip margin
    was low enough to try the pose's best turned rival: that and, if it
    replaced the pose, its confidence), and the total."""
    refined: bool = False
    """Whether ICP refined the pose (``refine=True`` and ICP found enough
    points near the model)."""
    inlier_fraction: float = 0.0
    """Share of the observed points within the inlier distance of the model at this pose, 0–1."""
    free_space_violation: float = 0.0
    """Share of the model's camera-facing points on observed rays that lie in
    front of what the camera saw there (by more than the tolerance), 0–1:
    high means the pose contradicts the view."""
    kept_points: int = 0
    """Observed points that :func:`prepare_query` kept as the object (of at
    most ``settings.max_cloud_points``)."""
    searches: int = 1
    """1, or 2 when the first pose was doubtful and a second search followed
    (poses voted for by point pairs; see :func:`doubtful`); 0 for a
    :class:`edgepose.Tracker`'s tracked frame (no search)."""
    confidence: float = float("nan")
    """Probability (0–1) that the pose is correct, i.e. within ADD(-S) <
    0.1 × diameter of the truth (ADD-S for a symmetric object). Trust it at
    ``>= 0.5``. From the scoring terms in ``evidence`` by the shipped
    calibrated model (:mod:`edgepose.confidence`); NaN when the networks in
    use ship none."""
    strict_threshold: float = float("nan")
    """The strict rule: trust the pose at ``confidence >=`` this when acting
    on a wrong pose costs more than looking again. The lowest threshold that
    let at most 5 % of the wrong poses through (:data:`edgepose.confidence.STRICT_WRONG_ACCEPTED`)
    on the fitting data's cross-validated stressed views, recorded with the
    model that judged this pose (0.97 from a cloud alone and given the
    frame, with the shipped networks); NaN without one."""
    evidence: dict = field(default_factory=dict)
    """The scoring terms ``confidence`` is computed from, by name
    (:data:`edgepose.confidence.FEATURES`)."""
    symmetry: Symmetry = NO_SYMMETRY
    """The object's rotational symmetries (object frame): the pose is only
    defined up to them, so a pose turned by one is equally right."""
    alternatives: tuple[Alternative, ...] = ()
    """Other poses that explain the view nearly as well, best first: the
    search's other hypotheses and this pose turned by one of the object's
    near symmetries, each more than 0.1 × diameter from this pose and from
    each other (ADD-S for a symmetric object). When the pose is wrong the
    truth is often among them (a banana end for end, a box whose telling
    side is hidden): look again from where they differ. They come from
    the search's coarse ICP, not the final polish (a few millimetres
    coarser). How many there are and how close the best comes are
    evidence of ``confidence``. At most ``settings.alternatives``; none
    for a tracked frame or an unrefined pose (:func:`edgepose.stages.alternatives`)."""
    unseen_turn: UnseenTurn | None = None
    """When the view leaves open a turn about the object's near-symmetry
    axis (a mug with its handle hidden): that axis and the turns that
    explain the view nearly as well; None when the view fixes the turn or
    the object has no such axis. A spread of those turns is among
    ``alternatives``, and ``confidence`` is scaled by the share of them
    this pose stands for (``evidence["unseen_turn_share"]``)."""
    mode: str = "estimated"
    """How the pose was obtained: ``estimated`` (by :func:`estimate`), or by
    a :class:`edgepose.Tracker`: ``tracked`` (refined from the last frame),
    ``initialised`` (its first frame) or ``reinitialised`` (``estimate``
    again, after the tracked pose failed its check)."""

    @property
    def ambiguous(self) -> bool:
        """Whether the object is symmetric, so that other poses (this one
        turned by ``symmetry``) are equally right."""
        return self.symmetry.symmetric

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) float64 ``T_cam_obj``."""
        return transform_from(self.R, self.t)


def estimate(
    cloud: object,
    codebook: Codebook,
    *,
    depth: np.ndarray | None = None,
    K: object = None,
    depth_scale: float = DEPTH_SCALE_MM,
    refine: bool = True,
    k: int | None = None,
    encoder: Encoder | None = None,
    icp_iterations: int | None = None,
    settings: EstimateSettings = DEFAULT_SETTINGS,
) -> Pose:
    """The pose ``T_cam_obj`` of ``codebook``'s object in ``cloud``: an (N, 3)
    array of camera-frame points in metres (float32/64, or anything with
    ``.points``), segmented to that object (a detector's mask that spills onto
    the background is fine: such points are dropped). Deterministic: the same
    input gives the same pose.

    ``depth`` (H, W) and ``K`` (3×3): the whole depth frame the cloud was cut
    from (``depth / depth_scale`` metres; 1000: uint16 millimetres), when
    the caller has it. Poses are then also checked against the scene around
    the object: a pose that would stand in front of background the camera
    saw beside the object's mask contradicts the view (what an occluder
    hides does not). It makes poses of partly hidden objects more often
    right and ``confidence`` sharper; it costs ~0.3–0.7 ms.

    ``settings`` holds every tuning value; ``k`` (codebook views verified) and
    ``icp_iterations`` (final ICP polish; 0: the hypotheses' coarse ICP only)
    are shortcuts for its fields; ``refine=False`` skips ICP."""
    check_types(codebook=codebook, settings=settings)
    settings = settings.with_(
        **{name: value for name, value in (("k", k), ("icp_iterations", icp_iterations)) if value is not None}
    )
    encoder = encoder or default_encoder()
    check_estimate_inputs(codebook, encoder, settings)
    laps = Laps()
    frame = checked_frame(depth, K, depth_scale)
    query = prepare_query(cloud, codebook, settings, frame)
    laps("prepare_query")
    return pose_from_query(query, codebook, encoder, refine, settings, laps)


def check_estimate_inputs(codebook: Codebook, encoder: Encoder, settings: EstimateSettings) -> None:
    """``InvalidArgumentError`` for a ``codebook``, ``encoder`` or ``settings``
    of the wrong type; ``CodebookError`` if ``codebook`` was built by another
    encoder; ``ValueError`` for ``settings.k`` or ``settings.icp_iterations`` out of range."""
    check_types(codebook=codebook, encoder=encoder, settings=settings)
    if encoder.fingerprint != codebook.fingerprint:
        raise CodebookError(
            f"the codebook was built by encoder {codebook.fingerprint[:12]}…, a different encoder than the "
            f"one given ({encoder.fingerprint[:12]}…); rebuild the codebook with it"
        )
    if not 1 <= settings.k <= len(codebook):
        raise ValueError(f"k must be between 1 and the codebook's {len(codebook)} views, got {settings.k}")
    if not 0 <= settings.icp_iterations <= MAX_ICP_ITERATIONS:
        raise ValueError(f"icp_iterations must be between 0 and {MAX_ICP_ITERATIONS}, got {settings.icp_iterations}")


def check_types(**arguments: object) -> None:
    """``InvalidArgumentError`` naming the first of ``codebook``, ``encoder``
    and ``settings`` (by keyword) that is not of its class."""
    expected = {"codebook": Codebook, "encoder": Encoder, "settings": EstimateSettings}
    how = {
        "codebook": "edgepose.Codebook.load(path) or edgepose.build_codebook(mesh)",
        "encoder": "edgepose.Encoder(), or leave it out",
        "settings": "edgepose.EstimateSettings(...), or leave it out",
    }
    for name, value in arguments.items():
        if not isinstance(value, expected[name]):
            raise InvalidArgumentError(
                f"{name} must be an edgepose.{expected[name].__name__} ({how[name]}), got {value!r:.80}"
            )


class Laps:
    """Seconds per stage of one estimate: call it with a stage's name when
    the stage ends; ``timings`` adds up repeated stages."""

    def __init__(self) -> None:
        self.start = self.clock = time.perf_counter()
        self.timings: dict[str, float] = {}

    def __call__(self, stage: str) -> None:
        now = time.perf_counter()
        self.timings[stage] = self.timings.get(stage, 0.0) + now - self.clock
        self.clock = now


def pose_from_query(
    query: Query,
    codebook: Codebook,
    encoder: Encoder,
    refine: bool,
    settings: EstimateSettings,
    laps: Laps,
    encoded: tuple[np.ndarray, np.ndarray] | None = None,
) -> Pose:
    """Stages 2–5 and the confidence for a prepared ``query`` (``encoded``:
    its map's code and spectrum, when already computed), as :func:`estimate`."""

    def scored(
        rotations: np.ndarray, translations: np.ndarray, views: np.ndarray, similarity: np.ndarray
    ) -> Candidates:
        """Stage 4 for candidate poses (model frame → camera) and their viewpoints."""
        scores = score_poses(
            query,
            codebook,
            query.keypoints,
            rotations,
            translations,
            settings.candidate_inlier_distance * codebook.model.diameter,
            settings.candidate_free_space_weight,
            settings,
        )
        laps("score_poses")
        return Candidates(rotations, translations, scores, views, similarity)

    def posed(first: int, end: int) -> Candidates:
        """Stages 3 and 4 for the retrieved views ``first``..``end``."""
        views = retrieval.views[first:end]
        rotations, translations = candidate_poses(query, codebook, views, retrieval.angles[first:end], settings)
        laps("candidate_poses")
        return scored(rotations, translations, views, retrieval.similarity[first:end])

    def paired() -> Candidates:
        """Stages 3 and 4 for the point pairs' poses (their views: each
        pose's nearest viewpoint)."""
        rotations, translations = pair_poses(query, codebook, settings)
        laps("pair_poses")
        nearest = nearest_views(codebook, rotations, translations)
        return scored(rotations, translations, nearest, codebook.codes[nearest] @ retrieval.code)

    # One retrieval serves both searches: the second one's extra views (if
    # retry_k asks for any) are the next ones down the same ranking.
    retry_k = min(settings.retry_k, len(codebook)) if refine else 0
    retrieval = retrieve(query, codebook, encoder, max(settings.k, retry_k), encoded)
    laps("retrieve")
    k = settings.k
    found = posed(0, k)
    pairs = settings.pair_poses if refine else 0
    observed_extent = math.hypot(*box_sides(query.points)) / codebook.model.diameter

    judge = encoder.judge(with_scene=query.scene is not None)

    def judged(
        found: Candidates,
        result: Refined,
        searched: Refined,
        loose: PoseScores,
        searches: int,
        flips: FlipMargin | None = None,
    ) -> tuple[dict, float, FlipMargin, Hypotheses]:
        """The evidence, confidence (NaN without a confidence model), flip
        margin and alternatives of ``result``, a search's pose from the
        candidates ``found`` (``searched``: the last search's pick, whose
        hypotheses the alternatives come from); ``flips``: that margin when
        already known (a second search kept the first pose)."""
        tight = (
            result.scores
            if result.refined
            else scores_at(query, codebook, result, settings.hypothesis_inlier_distance, settings)
        )
        if flips is None:
            rival = (
                result.rival.get()
                if result.rival is not None
                else flip_rival(query, codebook, result.R, result.t, settings)
            )
            flips = flip_margin(tight, rival)
        others = alternatives(codebook, result, searched.hypotheses, flips.rival, settings)
        evidence = evidence_of(
            inlier_fraction=tight.inlier_fraction[0],
            loose_inlier_fraction=loose.inlier_fraction[0],
            fit_ratio=tight.fit[0] / (settings.hypothesis_inlier_distance * codebook.model.diameter),
            free_space_violation=loose.free_space_violation[0],
            score=found.similarity[result.candidate],
            searches=searches,
            refined=result.refined,
            margin=result.margin,
            off_silhouette=loose.off_silhouette[0],
            observed_extent=observed_extent,
            translation_constraint=tight.translation_constraint[0],
            flip_margin=flips.margin,
            flip_fit_ratio=float(tight.fit[0] / max(flips.rival.fits[0], 1e-12)) if len(flips.rival.fits) else 0.0,
            rmse_ratio=result.rmse_ratio,
            alternatives=len(others.net),
            alternative_margin=float(tight.net[0] - others.net[0]) if len(others.net) else 1.0,
            scene_violation=loose.scene_violation[0],
        )
        return evidence, judge.probability(evidence) if judge else float("nan"), flips, others

    icp_cache: dict = {}  # the second search reuses the first one's ICPs
    result = best_pose(query, codebook, found, refine, settings, icp_cache)
    searched = result  # the last search's pick: its hypotheses are the alternatives' pool
    loose = loose_scores(query, codebook, result, settings)
    searches = 1
    may_retry = retry_k > k or pairs > 0
    # A doubtful pose is searched again whatever its confidence: that is judged after.
    retry = may_retry and doubtful(query, codebook, result, settings, loose)
    laps("refine_hypotheses")
    evidence: dict[str, float] | None = None
    flips: FlipMargin | None = None
    others: Hypotheses | None = None
    if not retry:
        evidence, confidence, flips, others = judged(found, result, searched, loose, searches)
        laps("confidence")
        retry = may_retry and confidence < settings.retry_below_confidence
    if retry:
        if retry_k > k:
            found = found.extended(posed(k, retry_k))
        if pairs:
            found = found.extended(paired())
        wider = best_pose(
            query, codebook, found, refine, settings.with_(hypotheses=settings.retry_hypotheses), icp_cache
        )
        searches, searched = 2, wider
        # The first pose's flip margin, if it was judged, unless the wider search beats it.
        if explains_more(wider, result):
            result, loose, flips = wider, loose_scores(query, codebook, wider, settings), None
        laps("refine_hypotheses")
        evidence, confidence, flips, others = judged(found, result, searched, loose, searches, flips)
        laps("confidence")
    assert evidence is not None and flips is not None and others is not None  # judged once or twice above
    if flips.margin < settings.turn_check_below:
        # The view may show the object turned onto itself: its best turned
        # rival, refined, replaces the pose if it explains the view better.
        turned = turned_pose(query, codebook, result, flips, settings)
        if turned is not None:
            result, loose = turned, loose_scores(query, codebook, turned, settings)
            evidence, confidence, flips, others = judged(found, result, searched, loose, searches)
        laps("turned_pose")
    turn, others, confidence = view_left_open(query, codebook, result, others, confidence, settings)
    if turn is not None:
        evidence["unseen_turn_share"] = turn.share
    laps("unseen_turn")
    timings = laps.timings
    timings["total"] = time.perf_counter() - laps.start
    model = codebook.model
    # Model frame = object (mesh) frame shifted by the model centre.
    t_obj = result.t - result.R @ model.centre
    return Pose(
        R=result.R,
        t=t_obj,
        score=float(found.similarity[result.candidate]),
        fit=float(result.scores.fit[0]),
        view=int(found.views[result.candidate]),
        candidates=found.views,
        candidate_fit=found.scores.fit,
        timings=timings,
        searches=searches,
        refined=result.refined,
        inlier_fraction=float(result.scores.inlier_fraction[0]),
        free_space_violation=float(result.scores.free_space_violation[0]),
        kept_points=len(query.points),
        confidence=confidence,
        strict_threshold=judge.strict_threshold if judge else float("nan"),
        evidence=evidence,
        symmetry=codebook.symmetry,
        alternatives=tuple(
            Alternative(R, t - R @ model.centre, float(result.scores.net[0] - net)) for R, t, net in zip(*others)
        ),
        unseen_turn=turn,
    )


class Candidates(NamedTuple):
    """Candidate poses (model frame → camera), their stage-4 scores and viewpoints."""

    rotations: np.ndarray
    """(C, 3, 3)."""
    translations: np.ndarray
    """(C, 3), metres."""
    scores: PoseScores
    views: np.ndarray
    """(C,) the codebook viewpoint of each (a point-pair pose: the nearest one)."""
    similarity: np.ndarray
    """(C,) cosine similarity of that viewpoint's code to the query's."""

    def extended(self, more: Candidates) -> Candidates:
        """These followed by ``more`` (each candidate's terms are its own)."""
        return Candidates(
            np.concatenate([self.rotations, more.rotations]),
            np.concatenate([self.translations, more.translations]),
            PoseScores(*(np.concatenate([a, b]) for a, b in zip(self.scores, more.scores))),
            np.concatenate([self.views, more.views]),
            np.concatenate([self.similarity, more.similarity]),
        )


def best_pose(
    query: Query,
    codebook: Codebook,
    found: Candidates,
    refine: bool,
    settings: EstimateSettings = DEFAULT_SETTINGS,
    icp_cache: dict | None = None,
) -> Refined:
    """The lowest-cost candidate, or (``refine``) the winner of stage 5 when
    its ICP found enough points."""
    chosen = int(np.argmin(found.scores.cost))
    best = Refined(
        chosen,
        found.rotations[chosen],
        found.translations[chosen],
        PoseScores(*(s[chosen : chosen + 1] for s in found.scores)),
        False,
    )
    if refine:
        best = (
            refine_hypotheses(
                query, codebook, found.rotations, found.translations, found.scores.cost, settings, icp_cache
            )
            or best
        )
    return best


def scores_at(
    query: Query, codebook: Codebook, result: Refined, inlier_distance: float, settings: EstimateSettings
) -> PoseScores:
    """A search's pose (model frame → camera) scored on the hypotheses'
    observed points at ``inlier_distance`` × diameter."""
    return score_poses(
        query,
        codebook,
        query.sample(settings.hypothesis_points, settings.subsample_seed),
        result.R[None],
        result.t[None],
        inlier_distance * codebook.model.diameter,
        0.0,
        settings,
    )


def loose_scores(
    query: Query, codebook: Codebook, result: Refined, settings: EstimateSettings = DEFAULT_SETTINGS
) -> PoseScores:
    """The pose's scores at the looser ``settings.doubt_inlier_distance``."""
    return scores_at(query, codebook, result, settings.doubt_inlier_distance, settings)


def doubtful(
    query: Query,
    codebook: Codebook,
    result: Refined,
    settings: EstimateSettings = DEFAULT_SETTINGS,
    loose: PoseScores | None = None,
) -> bool:
    """Whether a search's pose (model frame → camera) is worth a second,
    wider search: not refined, or explaining too few of the hypotheses'
    observed points within ``settings.doubt_inlier_distance``, or
    contradicting free space (``loose``: its :func:`loose_scores`, if known).
    :func:`estimate` also searches again when the pose's confidence is below
    ``settings.retry_below_confidence``."""
    if not result.refined:
        return True
    scores = loose or loose_scores(query, codebook, result, settings)
    return bool(
        scores.inlier_fraction[0] < settings.retry_below_inlier_fraction
        or scores.free_space_violation[0] > settings.retry_above_free_space
        or scores.scene_violation[0] > settings.retry_above_scene_violation
    )


def explains_more(candidate: Refined, incumbent: Refined) -> bool:
    """Whether ``candidate`` beats ``incumbent``: refined where it is not, or
    a larger share of explained points net of free-space (and scene) violations."""
    if candidate.refined != incumbent.refined:
        return candidate.refined
    return bool(candidate.scores.net[0] > incumbent.scores.net[0])
