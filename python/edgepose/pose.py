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

import time
from dataclasses import dataclass, field

import numpy as np

from edgepose.cloud import DEPTH_SCALE_MM, checked_frame
from edgepose.codebook import Codebook, CodebookError
from edgepose.encoder import Encoder, default_encoder
from edgepose.errors import InvalidArgumentError
from edgepose.search import Laps, Search, Searched, first_search, judged, second_search, turned_check
from edgepose.settings import DEFAULT_SETTINGS, MAX_ICP_ITERATIONS, EstimateSettings
from edgepose.stages import Hypotheses, Query, prepare_query, retrieve
from edgepose.symmetry import NO_SYMMETRY, Symmetry, transform_from
from edgepose.unseen_turn import UnseenTurn, near_axis, view_left_open


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
    ``settings.alternatives.within``, below 0 when this one explains more."""

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
    pose, each truncated at the inlier distance (``settings.refine.hypothesis_inlier_distance``
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
    replaced the pose, its confidence), unseen_turn (only for an object with
    a near-symmetry axis: :mod:`edgepose.unseen_turn`), and the total."""
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
    evidence of ``confidence``. At most ``settings.alternatives.max_count``; none
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
    right and ``confidence`` sharper, for a fraction of a millisecond.

    ``settings`` holds every tuning value; ``k`` (codebook views verified) and
    ``icp_iterations`` (final ICP polish; 0: the hypotheses' coarse ICP only)
    are shortcuts for ``settings.retrieve.k`` and ``settings.refine.icp_iterations``;
    ``refine=False`` skips ICP."""
    check_types(codebook=codebook, settings=settings)
    settings = settings.with_(
        **{
            name: value
            for name, value in (("retrieve.k", k), ("refine.icp_iterations", icp_iterations))
            if value is not None
        }
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
    encoder; ``ValueError`` for ``settings.retrieve.k`` or ``settings.refine.icp_iterations`` out of range."""
    check_types(codebook=codebook, encoder=encoder, settings=settings)
    if encoder.fingerprint != codebook.fingerprint:
        raise CodebookError(
            f"the codebook was built by encoder {codebook.fingerprint[:12]}…, a different encoder than the "
            f"one given ({encoder.fingerprint[:12]}…); rebuild the codebook with it"
        )
    if not 1 <= settings.retrieve.k <= len(codebook):
        raise ValueError(f"k must be between 1 and the codebook's {len(codebook)} views, got {settings.retrieve.k}")
    if not 0 <= settings.refine.icp_iterations <= MAX_ICP_ITERATIONS:
        raise ValueError(
            f"icp_iterations must be between 0 and {MAX_ICP_ITERATIONS}, got {settings.refine.icp_iterations}"
        )


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


def pose_from_query(
    query: Query,
    codebook: Codebook,
    encoder: Encoder,
    refine: bool,
    settings: EstimateSettings,
    laps: Laps,
) -> Pose:
    """Stages 2–5, the second search, the turned-pose check, the confidence
    and the turn the view leaves open, for a prepared ``query``, as :func:`estimate`."""
    # One retrieval serves both searches: the second one's extra views (if
    # retry_k asks for any) are the next ones down the same ranking.
    retry_k = min(settings.second_search.retry_k, len(codebook)) if refine else 0
    retrieval = retrieve(query, codebook, encoder, max(settings.retrieve.k, retry_k))
    laps("retrieve")
    judge = encoder.judge(with_scene=query.scene is not None)
    search = Search(query, codebook, encoder, settings, laps, retrieval, judge)
    may_retry = retry_k > settings.retrieve.k or (settings.second_search.pair_poses if refine else 0) > 0
    found, result, loose, retry = first_search(search, refine, may_retry)
    laps("refine_hypotheses")
    first = None
    if not retry:
        first = Searched(found, result, result, loose, 1, judged(search, found, result, result, loose, 1))
        laps("confidence")
        retry = may_retry and first.judgement.confidence < settings.second_search.retry_below_confidence
    searched = second_search(search, first, found, result, loose, refine, retry_k) if retry else first
    assert searched is not None  # judged once or twice above
    searched = turned_check(search, searched)
    others, confidence, turn = searched.judgement.others, searched.judgement.confidence, None
    if near_axis(codebook.symmetry) is not None:  # a mug: the view may leave the turn about its body open
        turn, others, confidence = view_left_open(query, codebook, searched.result, others, confidence, settings)
        if turn is not None:
            searched.judgement.evidence["unseen_turn_share"] = turn.share
        laps("unseen_turn")
    return as_pose(searched, others, confidence, turn, search)


def as_pose(searched: Searched, others: Hypotheses, confidence: float, turn: UnseenTurn | None, search: Search) -> Pose:
    """The search's outcome as a :class:`Pose` in the object (mesh) frame."""
    result, found, codebook = searched.result, searched.found, search.codebook
    timings = search.laps.timings
    timings["total"] = time.perf_counter() - search.laps.start
    centre = codebook.model.centre  # model frame = object (mesh) frame shifted by the model centre
    return Pose(
        R=result.R,
        t=result.t - result.R @ centre,
        score=float(found.similarity[result.candidate]),
        fit=float(result.scores.fit[0]),
        view=int(found.views[result.candidate]),
        candidates=found.views,
        candidate_fit=found.scores.fit,
        timings=timings,
        searches=searched.searches,
        refined=result.refined,
        inlier_fraction=float(result.scores.inlier_fraction[0]),
        free_space_violation=float(result.scores.free_space_violation[0]),
        kept_points=len(search.query.points),
        confidence=confidence,
        strict_threshold=search.judge.strict_threshold if search.judge else float("nan"),
        evidence=searched.judgement.evidence,
        symmetry=codebook.symmetry,
        alternatives=tuple(
            Alternative(R, t - R @ centre, float(result.scores.net[0] - net)) for R, t, net in zip(*others)
        ),
        unseen_turn=turn,
    )
