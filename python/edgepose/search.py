"""The search behind :func:`edgepose.estimate`, step by step: the candidate
poses of the retrieved views (and, in a second search, of point pairs),
the best of them refined, whether it is doubtful, and how it is judged
(evidence, confidence, flip margin, alternatives).

:class:`Search` holds what these steps share in one estimate: the prepared
query, the codebook, the networks, the settings, the clock and the
retrieval. Poses here are model frame → camera (model = mesh − the model's
centre), metres; :func:`edgepose.pose.pose_from_query` runs the steps and
turns the result into a :class:`edgepose.Pose`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from edgepose.codebook import Codebook
from edgepose.confidence import ConfidenceModel, FitEvidence, SearchEvidence, box_sides, evidence_of
from edgepose.encoder import Encoder
from edgepose.settings import DEFAULT_SETTINGS, EstimateSettings
from edgepose.stages import (
    FlipMargin,
    Hypotheses,
    PoseScores,
    Query,
    Refined,
    Retrieval,
    alternatives,
    candidate_poses,
    flip_margin,
    flip_rival,
    nearest_views,
    pair_poses,
    refine_hypotheses,
    rim_tolerant_violation,
    score_poses,
    turned_pose,
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


@dataclass
class Search:
    """What the steps of one estimate share."""

    query: Query
    codebook: Codebook
    encoder: Encoder
    settings: EstimateSettings
    laps: Laps
    retrieval: Retrieval
    """The cosine ranking: the first search's views, then the second's extra ones."""
    judge: ConfidenceModel | None
    """The confidence model for this query (given the frame or not); None: the networks ship none."""
    icp_cache: dict = field(default_factory=dict)
    """Hypotheses' coarse ICPs by start pose: the second search reuses the first one's."""

    @property
    def observed_extent(self) -> float:
        """The observed cloud's extent across, × the diameter."""
        return math.hypot(*box_sides(self.query.points)) / self.codebook.model.diameter


class Judgement(NamedTuple):
    """How a search's pose is judged (:func:`judged`)."""

    evidence: dict
    confidence: float
    """NaN without a confidence model."""
    flips: FlipMargin
    others: Hypotheses
    """Its alternatives (model frame → camera)."""


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
        query.sample(settings.refine.hypothesis_points, settings.subsample_seed),
        result.R[None],
        result.t[None],
        inlier_distance * codebook.model.diameter,
        0.0,
        settings,
    )


def loose_scores(
    query: Query, codebook: Codebook, result: Refined, settings: EstimateSettings = DEFAULT_SETTINGS
) -> PoseScores:
    """The pose's scores at the looser ``settings.second_search.doubt_inlier_distance``."""
    return scores_at(query, codebook, result, settings.second_search.doubt_inlier_distance, settings)


def doubtful(
    query: Query,
    codebook: Codebook,
    result: Refined,
    settings: EstimateSettings = DEFAULT_SETTINGS,
    loose: PoseScores | None = None,
) -> bool:
    """Whether a search's pose (model frame → camera) is worth a second,
    wider search: not refined, or explaining too few of the hypotheses'
    observed points within ``settings.second_search.doubt_inlier_distance``, or
    contradicting free space even with a cell of slack at the silhouette's
    edge (:func:`rim_tolerant_violation`), or the scene (``loose``: its
    :func:`loose_scores`, if known).
    :func:`estimate` also searches again when the pose's confidence is below
    ``settings.second_search.retry_below_confidence``."""
    if not result.refined:
        return True
    scores = loose or loose_scores(query, codebook, result, settings)
    return bool(
        scores.inlier_fraction[0] < settings.second_search.retry_below_inlier_fraction
        or scores.scene_violation[0] > settings.second_search.retry_above_scene_violation
        # The slack only lowers the violation: it is worked out only when it could matter.
        or (
            scores.free_space_violation[0] > settings.second_search.retry_above_free_space
            and rim_tolerant_violation(query, codebook, result.R, result.t, settings)
            > settings.second_search.retry_above_free_space
        )
    )


def explains_more(candidate: Refined, incumbent: Refined) -> bool:
    """Whether ``candidate`` beats ``incumbent``: refined where it is not, or
    a larger share of explained points net of free-space (and scene) violations."""
    if candidate.refined != incumbent.refined:
        return candidate.refined
    return bool(candidate.scores.net[0] > incumbent.scores.net[0])


def scored(
    search: Search, rotations: np.ndarray, translations: np.ndarray, views: np.ndarray, similarity: np.ndarray
) -> Candidates:
    """Stage 4 for candidate poses and their viewpoints."""
    settings, codebook = search.settings, search.codebook
    scores = score_poses(
        search.query,
        codebook,
        search.query.keypoints,
        rotations,
        translations,
        settings.retrieve.candidate_inlier_distance * codebook.model.diameter,
        settings.score.candidate_free_space_weight,
        settings,
        two_cores=settings.retrieve.candidates_on_two_cores,
    )
    search.laps("score_poses")
    return Candidates(rotations, translations, scores, views, similarity)


def posed(search: Search, first: int, end: int) -> Candidates:
    """Stages 3 and 4 for the retrieved views ``first``..``end``."""
    retrieval = search.retrieval
    views = retrieval.views[first:end]
    rotations, translations = candidate_poses(
        search.query, search.codebook, views, retrieval.angles[first:end], search.settings
    )
    search.laps("candidate_poses")
    return scored(search, rotations, translations, views, retrieval.similarity[first:end])


def paired(search: Search) -> Candidates:
    """Stages 3 and 4 for the point pairs' poses (their views: each pose's nearest viewpoint)."""
    codebook = search.codebook
    rotations, translations = pair_poses(search.query, codebook, search.settings)
    search.laps("pair_poses")
    nearest = nearest_views(codebook, rotations, translations)
    return scored(search, rotations, translations, nearest, codebook.codes[nearest] @ search.retrieval.code)


def judged(
    search: Search,
    found: Candidates,
    result: Refined,
    searched: Refined,
    loose: PoseScores,
    searches: int,
    flips: FlipMargin | None = None,
) -> Judgement:
    """The evidence, confidence, flip margin and alternatives of ``result``,
    a search's pose from the candidates ``found`` (``searched``: the last
    search's pick, whose hypotheses the alternatives come from); ``flips``:
    that margin when already known (a second search kept the first pose)."""
    query, codebook, settings = search.query, search.codebook, search.settings
    tight = (
        result.scores
        if result.refined
        else scores_at(query, codebook, result, settings.refine.hypothesis_inlier_distance, settings)
    )
    if flips is None:
        rival = (
            result.rival.get()
            if result.rival is not None
            else flip_rival(query, codebook, result.R, result.t, settings)
        )
        flips = flip_margin(tight, rival)
    others = alternatives(codebook, result, searched.hypotheses, flips.rival, settings)
    d = codebook.model.diameter
    evidence = evidence_of(
        FitEvidence.of(tight, loose, settings.refine.hypothesis_inlier_distance * d, search.observed_extent),
        SearchEvidence(
            score=found.similarity[result.candidate],
            searched_twice=searches > 1,
            refined=result.refined,
            margin=result.margin,
            flip_margin=flips.margin,
            rmse_ratio=result.rmse_ratio,
            flip_fit_ratio=float(tight.fit[0] / max(flips.rival.fits[0], 1e-12)) if len(flips.rival.fits) else 0.0,
            alternatives=len(others.net),
            alternative_margin=float(tight.net[0] - others.net[0]) if len(others.net) else 1.0,
        ),
    )
    confidence = search.judge.probability(evidence) if search.judge else float("nan")
    return Judgement(evidence, confidence, flips, others)


class Searched(NamedTuple):
    """A search's outcome, judged."""

    found: Candidates
    """Every candidate it posed."""
    result: Refined
    """Its pose."""
    searched: Refined
    """The last search's pick (its hypotheses are the alternatives' pool)."""
    loose: PoseScores
    """The pose's scores at the doubt's inlier distance."""
    searches: int
    judgement: Judgement


def first_search(search: Search, refine: bool, may_retry: bool) -> tuple[Candidates, Refined, PoseScores, bool]:
    """Stages 3–5 on the first ``settings.retrieve.k`` retrieved views: the candidates,
    the best pose, its loose scores, and whether it is doubtful (when a
    second search ``may_retry``)."""
    settings = search.settings
    found = posed(search, 0, settings.retrieve.k)
    result = best_pose(search.query, search.codebook, found, refine, settings, search.icp_cache)
    loose = loose_scores(search.query, search.codebook, result, settings)
    # A doubtful pose is searched again whatever its confidence: that is judged after.
    return found, result, loose, may_retry and doubtful(search.query, search.codebook, result, settings, loose)


def second_search(
    search: Search,
    first: Searched | None,
    found: Candidates,
    result: Refined,
    loose: PoseScores,
    refine: bool,
    retry_k: int,
) -> Searched:
    """The second, wider search (``retry_k`` views down the ranking, the
    point pairs' poses, ``settings.second_search.retry_hypotheses`` hypotheses) after the
    first one's pose ``result`` (``first``: it judged, if it was); the
    first pose is kept unless the wider one explains more."""
    settings = search.settings
    if retry_k > settings.retrieve.k:
        found = found.extended(posed(search, settings.retrieve.k, retry_k))
    if settings.second_search.pair_poses if refine else 0:
        found = found.extended(paired(search))
    wider = best_pose(
        search.query,
        search.codebook,
        found,
        refine,
        settings.with_(**{"refine.hypotheses": settings.second_search.retry_hypotheses}),
        search.icp_cache,
    )
    flips = first.judgement.flips if first is not None else None
    if explains_more(wider, result):
        result, loose, flips = wider, loose_scores(search.query, search.codebook, wider, settings), None
    search.laps("refine_hypotheses")
    judgement = judged(search, found, result, wider, loose, 2, flips)
    search.laps("confidence")
    return Searched(found, result, wider, loose, 2, judgement)


def turned_check(search: Search, searched: Searched) -> Searched:
    """When the flip margin is low, the pose's best turned rival, refined
    (:func:`edgepose.stages.turned_pose`), replaces it if it explains the view better."""
    if searched.judgement.flips.margin >= search.settings.turn.check_below:
        return searched
    turned = turned_pose(search.query, search.codebook, searched.result, searched.judgement.flips, search.settings)
    if turned is not None:
        loose = loose_scores(search.query, search.codebook, turned, search.settings)
        judgement = judged(search, searched.found, turned, searched.searched, loose, searched.searches)
        searched = searched._replace(result=turned, loose=loose, judgement=judgement)
    search.laps("turned_pose")
    return searched
