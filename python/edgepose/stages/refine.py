"""Stage 5 of :func:`edgepose.estimate`: ICP from the best distinct
candidates, the polish of the best, and the poses that rival it — its
turned rival (the flip margin, the turned pose) and the alternatives.

Poses are model frame → camera; metres.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from edgepose import _core
from edgepose.codebook import Codebook
from edgepose.settings import DEFAULT_SETTINGS, EstimateSettings
from edgepose.stages.query import Query
from edgepose.stages.scoring import PoseScores, centre_allowance, free_space_tolerance, pose_scores, score_poses


class FlipRival(NamedTuple):
    """:func:`flip_rival`'s outcome: a pose's best turned rival, if any."""

    net: float
    """Its inlier fraction minus free-space (and scene) violations on the
    hypotheses' observed points; NaN when there is none."""
    rotations: np.ndarray
    """(R, 3, 3) that rival (model frame → camera), R = 1, or none (R = 0) ..."""
    translations: np.ndarray
    """(R, 3) ... metres ..."""
    fits: np.ndarray
    """(R,) ... and its mean truncated distance to the hypotheses' observed
    points, metres (as :attr:`PoseScores.fit`)."""


class FlipMargin(NamedTuple):
    """:func:`flip_margin`'s outcome."""

    margin: float
    """How much better the pose explains the view than its best turned rival; 1 when there is none."""
    rival: FlipRival
    """That rival (none: no rotations)."""


def flip_rival(query: Query, codebook: Codebook, R: np.ndarray, t: np.ndarray, settings: EstimateSettings) -> FlipRival:
    """The best of pose ``(R, t)`` (model frame → camera, metres) turned by
    each of the codebook's doubtful turns (half turns about the model's
    principal axes, its near turns), moved onto the view and (the best few)
    settled by ICP, that is a different pose (symmetries aside): the
    mistakes a search makes on a near-symmetric view (a banana end for end,
    a box whose telling details are hidden). One call to the Rust core
    (``rust/src/flips.rs``), which lets go of the GIL."""
    return RivalSearch(query, codebook, R, t, settings, beside=False).get()


def flip_margin(scores: PoseScores, rival: FlipRival) -> FlipMargin:
    """How much better a pose with ``scores`` (on the hypotheses' observed
    points) explains the view than its turned ``rival``
    (:func:`flip_rival`): inlier fraction minus violations, the pose's minus
    the rival's; 1 when there is none. Near 0 or below when the view cannot
    tell the object from its flip."""
    margin = float(scores.net[0] - rival.net) if len(rival.rotations) else 1.0
    return FlipMargin(margin, rival)


def turned_pose(
    query: Query, codebook: Codebook, result: Refined, flips: FlipMargin, settings: EstimateSettings = DEFAULT_SETTINGS
) -> Refined | None:
    """``result``'s best turned rival (``flips``), refined as a hypothesis
    is (coarse ICP, then the polish), when it explains more of the view
    (inlier fraction minus violations) by ``settings.turn.switch_gain``;
    None otherwise, and for a pose ICP did not refine. Its ``margin`` is
    that gain over ``result``, its ``rmse_ratio`` the search's.
    :func:`edgepose.estimate` asks when the flip margin is below
    ``settings.turn.check_below``."""
    if not result.refined or len(flips.rival.rotations) == 0:
        return None
    d = codebook.model.diameter
    coarse = query.sample(settings.refine.hypothesis_points, settings.subsample_seed)
    icp = codebook.index.refine(
        coarse,
        flips.rival.rotations,
        flips.rival.translations,
        settings.refine.hypothesis_iterations,
        settings.refine.icp_max_distance * d,
    )
    rival: RivalSearch | None = None  # unpolished: the flip margin's rival is found from the pose itself
    if (
        settings.refine.icp_iterations > 0
        and icp.inliers[0] >= settings.refine.min_icp_inliers
        and np.isfinite(icp.rmse[0])
    ):
        fine, rival = polished(query, codebook, icp.rotations[0], icp.translations[0], settings)
        icp = fine if fine is not None else icp
    R, t = icp.rotations, icp.translations
    if not usable_icp(query, codebook, icp.inliers, icp.rmse, t, settings)[0]:
        return None
    scores = score_poses(query, codebook, coarse, R, t, settings.refine.hypothesis_inlier_distance * d, 0.0, settings)
    gain = float(scores.net[0] - result.scores.net[0])
    if gain <= settings.turn.switch_gain:
        return None
    return result._replace(R=R[0], t=t[0], scores=scores, refined=True, margin=gain, rival=rival)


def alternatives(
    codebook: Codebook,
    result: Refined,
    hypotheses: Hypotheses | None,
    rival: FlipRival,
    settings: EstimateSettings = DEFAULT_SETTINGS,
) -> Hypotheses:
    """Other poses (model frame → camera) that explain the view nearly as
    well as the search's pose ``result``: of the search's ``hypotheses``
    (after their coarse ICP) and the pose's turned ``rival`` (settled,
    :func:`flip_rival`), those whose net (inlier fraction minus violations
    on the hypotheses' observed points, :attr:`PoseScores.net`) is within
    ``settings.alternatives.within`` of the pose's, each more than
    ``RIVAL_DISTANCE`` × d from the pose and from each other (ADD, or ADD-S
    for a symmetric object), best first, at most ``settings.alternatives.max_count``.
    Nothing is refined again: they cost a few distances. Empty for a pose
    stage 5 did not refine."""
    found = [Hypotheses(result.R[None], result.t[None], result.scores.net)]
    if settings.alternatives.max_count > 0 and result.refined:
        if hypotheses is not None:
            found.append(hypotheses)
        if len(rival.rotations):
            found.append(Hypotheses(rival.rotations, rival.translations, np.array([rival.net])))
    R, t, net = (np.concatenate(column) for column in zip(*found))
    allowed = net >= net[0] - settings.alternatives.within
    picked = distinct_poses(codebook, R, t, np.argsort(-net, kind="stable"), allowed, settings.alternatives.max_count)
    return Hypotheses(R[picked], t[picked], net[picked])


def distinct_poses(
    codebook: Codebook,
    rotations: np.ndarray,
    translations: np.ndarray,
    order: np.ndarray,
    allowed: np.ndarray,
    count: int,
) -> list[int]:
    """Up to ``count`` indices of poses (model frame → camera), taken in
    ``order`` where ``allowed``, each more than ``RIVAL_DISTANCE`` × d from
    pose 0 and from those taken before."""
    return codebook.index.distinct_poses(
        np.ascontiguousarray(rotations, dtype=np.float64),
        np.ascontiguousarray(translations, dtype=np.float64),
        np.ascontiguousarray(order, dtype=np.int64),
        np.ascontiguousarray(allowed, dtype=bool),
        count,
        RIVAL_DISTANCE * codebook.model.diameter,
        codebook.symmetry.symmetric,
        RIVAL_POINTS,
    )


class Refined(NamedTuple):
    """Stage 5's outcome: the chosen pose (model frame → camera) and its terms."""

    candidate: int
    """Which candidate it started from."""
    R: np.ndarray
    t: np.ndarray
    scores: PoseScores
    """The chosen pose's terms (arrays of one)."""
    refined: bool
    margin: float = 1.0
    """How much better the chosen hypothesis explains the view than the best
    rival that is a different pose (more than ``RIVAL_DISTANCE`` × d apart,
    symmetries aside): inlier fraction minus free-space violation, winner's
    minus rival's; 1 when no rival was refined."""
    rmse_ratio: float = 0.0
    """The chosen hypothesis's coarse ICP RMSE over the lowest of the rivals
    that competed with it (explaining nearly as many points, within the
    free-space margin): near 1 when the pick between different poses was a
    toss-up, 0 when no rival competed."""
    rival: RivalSearch | None = None
    """The search for the pose's best turned rival (:func:`flip_rival`)
    from the pose before its polish (:func:`polished`); None for a pose
    that was not polished there (stage 5 did not refine it, a turned pose
    left unpolished): the confidence then finds it from the pose itself."""
    hypotheses: Hypotheses | None = None
    """The search's usable refined hypotheses, the chosen one among them
    (:func:`alternatives` looks there); None when stage 5 did not run."""


class Hypotheses(NamedTuple):
    """Stage 5's hypotheses after their coarse ICP (model frame → camera)."""

    rotations: np.ndarray
    """(H, 3, 3)."""
    translations: np.ndarray
    """(H, 3), metres."""
    net: np.ndarray
    """(H,) inlier fraction minus violations on the hypotheses' observed points (:attr:`PoseScores.net`)."""


def refine_hypotheses(
    query: Query,
    codebook: Codebook,
    rotations: np.ndarray,
    translations: np.ndarray,
    candidate_cost: np.ndarray,
    settings: EstimateSettings = DEFAULT_SETTINGS,
    icp_cache: dict | None = None,
) -> Refined | None:
    """Stage 5: coarse ICP from the ``settings.refine.hypotheses`` best distinct
    candidates, each scored again. Hypotheses that explain nearly as many
    points as the best and violate free space little more than the least
    violating compete; the lowest ICP RMSE wins (near ties: :func:`pick_hypothesis`)
    and is polished by a longer ICP. None when no ICP found enough points.

    ``icp_cache`` (a dict kept between calls on the same query and the same
    leading candidates, with the same settings) holds each start's ICP
    results, the polishes of near ties and the chosen one's polish and
    rival search, so a second, wider search does not repeat the first one's."""
    cache: dict = {} if icp_cache is None else icp_cache
    d = codebook.model.diameter
    coarse = query.sample(settings.refine.hypothesis_points, settings.subsample_seed)
    starts = distinct_hypotheses(
        rotations, np.argsort(candidate_cost, kind="stable"), settings.refine.hypotheses, settings.refine.distinct_deg
    )
    max_distance = settings.refine.icp_max_distance * d
    new = [int(s) for s in starts if ("coarse", int(s)) not in cache]
    refined = None
    if new:
        icp = codebook.index.refine(
            coarse,
            rotations[new],
            translations[new],
            settings.refine.hypothesis_iterations,
            max_distance,
            two_cores=settings.refine.coarse_icp_on_two_cores,
        )
        refined = icp.rotations, icp.translations, icp.inliers, icp.rmse
        for i, s in enumerate(new):  # ICP runs each start on its own: one at a time is the same
            cache["coarse", s] = tuple(column[i] for column in refined)
    if refined is not None and len(new) == len(starts):  # all just refined, in order (a first search)
        hyp_R, hyp_t, inliers, rmse = refined
    else:
        hyp_R, hyp_t, inliers, rmse = (np.array(x) for x in zip(*(cache["coarse", int(s)] for s in starts)))

    def polished_tie(tie: list[int]) -> _core.IcpResults:
        key = ("tie", tuple(int(starts[h]) for h in tie))
        if key not in cache:
            cache[key] = polish(query, codebook, hyp_R[tie], hyp_t[tie], settings)
        return cache[key]

    picked = pick_hypothesis(query, codebook, coarse, hyp_R, hyp_t, inliers, rmse, settings, polished_tie)
    if picked is None:
        return None
    pick, tie_polish, scores, usable, margin, rmse_ratio = picked
    inlier_distance = settings.refine.hypothesis_inlier_distance * d
    net = scores.net
    chosen = int(starts[pick])
    if ("fine", chosen) not in cache:
        cache["fine", chosen] = polished(query, codebook, hyp_R[pick], hyp_t[pick], settings, done=tie_polish)
    fine_icp, rival = cache["fine", chosen]
    best = Refined(
        chosen,
        hyp_R[pick],
        hyp_t[pick],
        PoseScores(*(s[pick : pick + 1] for s in scores)),
        True,
        margin,
        rmse_ratio,
        rival,
        Hypotheses(hyp_R[usable], hyp_t[usable], net[usable]),
    )
    if fine_icp is not None:
        fine_R, fine_t = fine_icp.rotations, fine_icp.translations
        if usable_icp(query, codebook, fine_icp.inliers, fine_icp.rmse, fine_t, settings)[0]:
            fine = score_poses(query, codebook, coarse, fine_R, fine_t, inlier_distance, 0.0, settings)
            best = best._replace(R=fine_R[0], t=fine_t[0], scores=fine)
    return best


#: Hypotheses farther apart than this × d (ADD, or ADD-S for a symmetric
#: object) are different poses: rivals for :attr:`Refined.margin`.
RIVAL_DISTANCE = 0.1


#: Model points (the first, spread ones) that measure distances between poses.
RIVAL_POINTS = 64


#: Keypoint alignment iterations of each turned pose of the flip margin
#: (the candidates take ``settings.retrieve.align_iterations``) ...
FLIP_ALIGN_ITERATIONS = 1


#: ... and the rival turned poses that screen best, this many, are settled
#: by this many ICP iterations (pairing within ``settings.refine.icp_max_distance``)
#: before they are scored: an unsettled rival that is the truth loses to a
#: polished wrong pose (the evidence: ``docs/tuning.md``, "Outside the settings").
FLIP_SETTLED_RIVALS = 1


FLIP_SETTLE_ITERATIONS = 2


class RivalSearch:
    """:func:`flip_rival` of pose ``(R, t)``, found once: with ``beside``
    on one of the Rust core's threads from now on, while the caller goes
    on (the caller finds it itself if it asks before any thread has started
    it: a virtual CPU can take a millisecond to wake); else in the caller's
    thread on the first :meth:`get` (so none is searched for a pose dropped
    before the confidence asks). The same rival either way."""

    def __init__(
        self, query: Query, codebook: Codebook, R: np.ndarray, t: np.ndarray, settings: EstimateSettings, beside: bool
    ) -> None:
        d = codebook.model.diameter
        turn_rotations, turn_translations = codebook.doubtful_turns
        # Each turned pose is moved (not turned) so the query's keypoints land on
        # the model, as the candidates are (cheap); only the best few are
        # then settled by ICP (settling all of them costs several times more). Given an own
        # net of 0, the core's margin is minus the rival's net.
        self._search = codebook.index.flip_margin(
            query.keypoints,
            query.sample(settings.refine.hypothesis_points, settings.subsample_seed),
            query.free_space,
            np.ascontiguousarray(R, dtype=np.float64),
            np.ascontiguousarray(t, dtype=np.float64),
            0.0,
            turn_rotations,
            turn_translations,
            _core.FlipSettings(
                align_iterations=FLIP_ALIGN_ITERATIONS,
                align_distance=settings.retrieve.candidate_inlier_distance * d,
                inlier_distance=settings.refine.hypothesis_inlier_distance * d,
                free_space_tolerance=free_space_tolerance(query.median_depth, d, settings),
                model_stride=max(settings.score.free_space_model_stride, 1),
                rival_distance=RIVAL_DISTANCE * d,
                rival_points=RIVAL_POINTS,
                symmetric=codebook.symmetry.symmetric,
                settled=FLIP_SETTLED_RIVALS,
                settle_iterations=FLIP_SETTLE_ITERATIONS,
                settle_distance=settings.refine.icp_max_distance * d,
            ),
            beside=beside,
        )

    def get(self) -> FlipRival:
        """The rival (waited for while a core thread finds it)."""
        margin, rotations, translations, fits = self._search.result()
        return FlipRival(-margin if len(rotations) else float("nan"), rotations, translations, fits)


def polished(
    query: Query,
    codebook: Codebook,
    R: np.ndarray,
    t: np.ndarray,
    settings: EstimateSettings,
    done: _core.IcpResults | None = None,
) -> tuple[_core.IcpResults | None, RivalSearch]:
    """Pose ``(R, t)``'s final ICP :func:`polish` (None when
    ``settings.refine.icp_iterations`` is 0; ``done`` when given, a polish of the
    pose already made: a near tie's) and the search for its turned rival
    (:func:`flip_rival`, from the pose before the polish: the rival is
    settled by ICP anyway), handed to another core before the polish starts
    when ``settings.refine.flip_rival_beside_polish``, else found when first
    asked for (:class:`RivalSearch`)."""
    beside = settings.refine.icp_iterations > 0 and settings.refine.flip_rival_beside_polish
    rival = RivalSearch(query, codebook, R, t, settings, beside=beside)
    if settings.refine.icp_iterations == 0:
        return None, rival
    if done is not None:
        return done, rival
    return polish(query, codebook, R[None], t[None], settings), rival


def polish(
    query: Query, codebook: Codebook, rotations: np.ndarray, translations: np.ndarray, settings: EstimateSettings
) -> _core.IcpResults:
    """The final ICP polish of poses (model frame → camera): ``settings.refine.icp_iterations``
    on ``settings.refine.icp_points`` of the query's points."""
    return codebook.index.refine(
        query.sample(settings.refine.icp_points, settings.subsample_seed + 1),
        rotations,
        translations,
        settings.refine.icp_iterations,
        settings.refine.icp_max_distance * codebook.model.diameter,
    )


class Pick(NamedTuple):
    """:func:`pick_hypothesis`'s outcome."""

    pick: int
    """The winning hypothesis."""
    tie_polish: _core.IcpResults | None
    """Its polish when a near tie was broken by polishing (results of one), else None."""
    scores: PoseScores
    """Every hypothesis's terms on the hypotheses' observed points."""
    usable: np.ndarray
    """(H,) bool: which hypotheses' ICP results are usable (:func:`usable_icp`)."""
    margin: float
    """See :attr:`Refined.margin`."""
    rmse_ratio: float
    """See :attr:`Refined.rmse_ratio`."""


def pick_hypothesis(
    query: Query,
    codebook: Codebook,
    observed: np.ndarray,
    rotations: np.ndarray,
    translations: np.ndarray,
    inliers: np.ndarray,
    rmse: np.ndarray,
    settings: EstimateSettings,
    polish_tie: Callable[[list[int]], _core.IcpResults],
) -> Pick | None:
    """Stage 5's pick among hypotheses (model frame → camera, after their
    coarse ICP: its ``inliers`` and ``rmse``), scored on the ``observed``
    points at ``settings.refine.hypothesis_inlier_distance``; None when no
    ICP result is usable (:func:`usable_icp`). Hypotheses that explain at
    least ``settings.refine.hypothesis_inlier_ratio`` of the best one's
    inliers and violate free space at most ``settings.refine.hypothesis_free_space_margin``
    more than the least violating compete; the lowest RMSE wins. When
    competing rivals (more than ``RIVAL_DISTANCE`` × d away) come within
    ``settings.refine.tie_polish_within`` of its RMSE, ``polish_tie`` gets
    their indices, the pick first, and returns their polishes; the lowest
    polished RMSE of a usable polish wins (the first on equal RMSEs). One
    call to the Rust core (``rust/src/hypotheses.rs``)."""
    d = codebook.model.diameter
    inlier_distance = settings.refine.hypothesis_inlier_distance * d
    rules = _core.PickRules(
        min_icp_inliers=settings.refine.min_icp_inliers,
        max_centre_offset=centre_allowance(codebook, settings),
        inlier_distance=inlier_distance,
        free_space_tolerance=free_space_tolerance(query.median_depth, d, settings),
        model_stride=max(settings.score.free_space_model_stride, 1),
        inlier_ratio=settings.refine.hypothesis_inlier_ratio,
        free_space_margin=settings.refine.hypothesis_free_space_margin,
        tie_polish_within=settings.refine.tie_polish_within if settings.refine.icp_iterations > 0 else 0.0,
        rival_distance=RIVAL_DISTANCE * d,
        rival_points=RIVAL_POINTS,
        symmetric=codebook.symmetry.symmetric,
    )
    picked = codebook.index.pick_hypothesis(
        observed,
        query.free_space,
        np.ascontiguousarray(rotations, dtype=np.float64),
        np.ascontiguousarray(translations, dtype=np.float64),
        np.ascontiguousarray(inliers, dtype=np.uint32),
        np.ascontiguousarray(rmse, dtype=np.float64),
        query.centroid,
        rules,
        polish_tie,
    )
    if picked is None:
        return None
    pick, tie_polish, scored, usable, margin, rmse_ratio = picked
    return Pick(pick, tie_polish, pose_scores(scored, inlier_distance, 0.0), usable, margin, rmse_ratio)


def usable_icp(
    query: Query,
    codebook: Codebook,
    inliers: np.ndarray,
    rmse: np.ndarray,
    translations: np.ndarray,
    settings: EstimateSettings,
) -> np.ndarray:
    """(H,) bool: which ICP results (their inlier counts, RMSEs and
    translations, metres) to use: enough inliers, a finite RMSE, the
    model's centre still near the cloud (:func:`near_the_cloud`). The rule
    stage 5's pick applies to its hypotheses, in the Rust core
    (``rust/src/hypotheses.rs``, ``usable_icp``)."""
    return _core.usable_icp(
        np.ascontiguousarray(inliers, dtype=np.uint32),
        np.ascontiguousarray(rmse, dtype=np.float64),
        np.ascontiguousarray(translations, dtype=np.float64),
        query.centroid,
        settings.refine.min_icp_inliers,
        centre_allowance(codebook, settings),
    )


def pose_distances(codebook: Codebook, rotations: np.ndarray, translations: np.ndarray, ref: int) -> np.ndarray:
    """(H,) ADD (ADD-S for a symmetric object) of each pose (model frame →
    camera) from pose ``ref``, on the model's first ``RIVAL_POINTS``
    farthest-point samples, metres."""
    return codebook.index.pose_distances(
        np.ascontiguousarray(rotations, dtype=np.float64),
        np.ascontiguousarray(translations, dtype=np.float64),
        ref,
        codebook.symmetry.symmetric,
        RIVAL_POINTS,
    )


def distinct_hypotheses(rotations: np.ndarray, order: np.ndarray, count: int, min_angle_deg: float) -> np.ndarray:
    """Indices of up to ``count`` of ``rotations`` ((K, 3, 3)), taken in
    ``order``, each at least ``min_angle_deg`` away from those taken before."""
    # The cosine of the angle between two rotations: (trace(Raᵀ Rb) − 1) / 2, in the core.
    kept = _core.distinct_rotations(
        np.ascontiguousarray(rotations, dtype=np.float64),
        np.ascontiguousarray(order, dtype=np.int64),
        count,
        float(np.cos(np.radians(min_angle_deg))),
    )
    return np.asarray(kept, dtype=np.intp)
