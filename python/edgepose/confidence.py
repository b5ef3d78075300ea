"""``Pose.confidence``: the probability that a pose is correct, i.e. within
ADD(-S) < 0.1 × diameter of the truth (ADD-S for an object with a detected
symmetry).

It is a logistic model over a few scoring terms that :func:`edgepose.estimate`
computes anyway (the *evidence*, :data:`FEATURES`), fitted on training shapes
in procedural scenes, clean and stressed, never on the benchmark objects
(``python -m export.confidence``). The fitted weights ship with the networks,
in ``models/manifest.json`` under ``confidence``, with the features' names
and definitions. Trust a pose at ``confidence >= TRUST_THRESHOLD``; a robot
that must rarely act on a wrong pose can ask for the model's strict rule,
``confidence >= Pose.strict_threshold`` (:meth:`ConfidenceModel.threshold_for`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from edgepose import _core

#: The documented default rule: trust a pose whose confidence is at least this.
TRUST_THRESHOLD = 0.5

#: The strict rule (``Pose.strict_threshold``) let at most this share of the
#: wrong poses through on the fitting data's cross-validated stressed views.
STRICT_WRONG_ACCEPTED = 0.05

#: The evidence, by name: what each term means. Fractions are of the observed
#: points the hypotheses were scored on (``settings.refine.hypothesis_points``), at
#: the pose; d is the object's diameter.
FEATURES: dict[str, str] = {
    "inlier_fraction": "share of observed points within refine.hypothesis_inlier_distance (0.02 d) of the model, 0-1",
    "loose_inlier_fraction": "share of observed points within second_search.doubt_inlier_distance (0.04 d) "
    "of the model, 0-1",
    "fit": "mean observed-point distance to the model, each truncated at 0.02 d, over 0.02 d, 0-1",
    "free_space_violation": "share of the model's camera-facing points in front of what the camera saw, 0-1",
    "score": "cosine similarity of the chosen codebook view's code to the observed one, -1-1",
    "searched_twice": "1 when the first search's pose was doubtful and a wider search followed, else 0",
    "refined": "1 when ICP refined the pose, else 0",
    "margin": "inlier fraction minus free-space violation of the chosen hypothesis minus that of the best "
    "rival hypothesis more than 0.1 d away (symmetries aside); 1 when there is none",
    "off_silhouette": "share of the model's camera-facing points that land where nothing was observed, 0-1",
    "observed_extent": "diagonal of the kept observed points' bounding box over d (how much of the object is seen)",
    "translation_constraint": "smallest eigenvalue of the mean n n^T of the model normals nearest to the observed "
    "points explained within 0.02 d: 0 when the pose could slide along the seen surface, up to 1/3",
    "flip_margin": "inlier fraction minus free-space violation of the pose minus that of the pose turned by one of "
    "the model's doubtful turns (half turns about its principal axes, its near turns) and moved onto the view, "
    "the one that screens best settled by 2 ICP iterations (if a different pose); the turns start from the pose "
    "before its final ICP polish; 1 when none is",
    "rmse_ratio": "coarse ICP RMSE of the chosen hypothesis over the lowest of the rival hypotheses (more than "
    "0.1 d away) that competed with it for the pick; 0 when none competed",
    "flip_fit_ratio": "fit of the pose over that of the flip margin's best turned rival (settled), on the same "
    "points: well below 1 when fine detail tells the pose from its turn, about 1 when nothing does; 0 when there "
    "is no rival",
    "alternatives": "how many other poses explain the view nearly as well (Pose.alternatives, at most "
    "settings.alternatives.max_count): the search's hypotheses and the flip margin's turned rival within "
    "alternatives.within of the pose's net, more than 0.1 d from it and from each other",
    "alternative_margin": "net of the pose minus that of its best alternative; 1 when there is none",
    "scene_violation": "share of the model's camera-facing points that land off the observed silhouette in front of "
    "the frame's depth there (the model would hide background the camera saw), 0-1; only with the depth image",
}

#: The evidence that needs the frame's depth image (``estimate(..., depth=, K=)``):
#: the model fitted without it never reads these.
SCENE_FEATURES = ("scene_violation",)


def _value(v: float) -> float:
    """The feature as it is."""
    return float(v)


def _unexplained(fraction: float) -> float:
    """log of the share of points left unexplained (floored at 1 %)."""
    return math.log(max(1.0 - fraction, 0.0) + 0.01)


def _log_share(share: float) -> float:
    """log of a share (floored at 1 %)."""
    return math.log(share + 0.01)


def _clipped_margin(margin: float) -> float:
    """The margin where it matters: −0.2 (a rival explains more) to 0.3 (clearly ahead)."""
    return min(max(margin, -0.2), 0.3)


def _no_rival(margin: float) -> float:
    """1 when no rival hypothesis was refined (margin 1), else 0."""
    return float(margin >= 0.99)


def _capped_extent(extent: float) -> float:
    """Observed extent up to 1.2 d (beyond, the whole object is in view)."""
    return min(extent, 1.2)


#: The terms each feature enters the model as (logistic regression is linear in them).
TERMS: dict[str, tuple[Callable[[float], float], ...]] = {
    "inlier_fraction": (_unexplained,),
    "loose_inlier_fraction": (_unexplained,),
    "fit": (_value,),
    "free_space_violation": (_log_share,),
    "score": (_value,),
    "searched_twice": (_value,),
    "refined": (_value,),
    "margin": (_value, _clipped_margin, _no_rival),
    "off_silhouette": (_value, _log_share),
    "observed_extent": (_value, _capped_extent),
    "translation_constraint": (_value, _log_share),
    "flip_margin": (_value, _clipped_margin, _no_rival),
    "rmse_ratio": (_value,),
    "flip_fit_ratio": (_value,),
    "alternatives": (_value,),
    "alternative_margin": (_value, _clipped_margin, _no_rival),
    "scene_violation": (_value, _log_share),
}


def feature_vector(evidence: dict[str, float], names: tuple[str, ...]) -> np.ndarray:
    """The model's inputs: the terms of each named feature of ``evidence``, in order."""
    return np.array([term(evidence[n]) for n in names for term in TERMS[n]], dtype=np.float64)


def term_names(names: tuple[str, ...]) -> list[str]:
    """``feature:transform`` for each model input, in :func:`feature_vector`'s order."""
    return [f"{n}:{transform_name(term)}" for n in names for term in TERMS[n]]


def transform_name(term: Callable[[float], float]) -> str:
    """A term's transform by name, as the manifest and the Rust core (``rust/src/confidence.rs``) know it."""
    return term.__name__.strip("_")


def hinge_names(names: tuple[str, ...], knots: tuple[tuple[float, ...], ...]) -> list[str]:
    """The model's inputs: each term (:func:`term_names`), then its hinges
    ``term>knot`` (max(0, term − knot)), in :meth:`ConfidenceModel.inputs`' order."""
    return [
        name
        for term, term_knots in zip(term_names(names), knots)
        for name in (term, *(f"{term}>{k:.6g}" for k in term_knots))
    ]


@dataclass(frozen=True)
class StricterRule:
    """A threshold above the default one, as ``export.confidence`` measured it
    on the fitting data (held out by 4-fold cross-validation, stressed views)."""

    wrong_accepted_at_most: float
    """The share of wrong poses it was chosen to let through at most, 0–1 ..."""
    threshold: float
    """... the lowest confidence (in steps of 0.01) that did ..."""
    wrong_accepted: float
    """... the share of wrong poses it let through ..."""
    correct_kept: float
    """... and the share of correct poses it kept, 0–1."""


@dataclass(frozen=True)
class ConfidenceModel:
    """Logistic regression over transformed, standardised evidence, each term
    a piecewise-linear curve: the term itself plus max(0, term − knot) at its
    knots (none: linear in it)."""

    features: tuple[str, ...]
    knots: tuple[tuple[float, ...], ...]
    """One tuple per term (:func:`feature_vector`), ascending."""
    mean: np.ndarray
    """(I,) of each input (:func:`hinge_names`) over the fitting data."""
    scale: np.ndarray
    """(I,) their standard deviations."""
    weights: np.ndarray
    """(I,) on the standardised inputs."""
    bias: float
    stricter_rules: tuple[StricterRule, ...] = ()
    """Thresholds that let fewer wrong poses through than 0.5, recorded with the fit (none: not recorded)."""
    _curves: _core.ConfidenceCurves = field(init=False, repr=False, compare=False)
    """The same model on the unstandardised terms, summed by the Rust core
    (``rust/src/confidence.rs``), term by term in the order plain Python
    would (the same bits), faster than the same loop in Python
    (``docs/confidence.md``, "The model")."""

    def __post_init__(self) -> None:
        term_count = sum(len(TERMS[n]) for n in self.features)
        if len(self.knots) != term_count:
            raise ValueError(f"a confidence model of {term_count} terms has {len(self.knots)} lists of knots")
        coefficients = iter((self.weights / self.scale).tolist())
        terms = [
            (i, transform_name(term), next(coefficients), [(k, next(coefficients)) for k in term_knots])
            for (i, term), term_knots in zip(
                ((i, t) for i, n in enumerate(self.features) for t in TERMS[n]), self.knots
            )
        ]
        intercept = float(self.bias - self.mean @ (self.weights / self.scale))
        object.__setattr__(self, "_curves", _core.ConfidenceCurves(terms, intercept, len(self.features)))

    @staticmethod
    def inputs(terms: np.ndarray, knots: tuple[tuple[float, ...], ...]) -> np.ndarray:
        """(..., I) inputs from (..., T) terms: each term, then its hinges."""
        columns = []
        for j, term_knots in enumerate(knots):
            columns.append(terms[..., j])
            columns.extend(np.maximum(terms[..., j] - k, 0.0) for k in term_knots)
        return np.stack(columns, axis=-1)

    def probability(self, evidence: dict[str, float]) -> float:
        """P(correct | evidence), 0–1."""
        return self._curves.probability([evidence[n] for n in self.features])

    def threshold_for(self, wrong_accepted: float) -> float:
        """The lowest threshold that let at most ``wrong_accepted`` (0–1) of the
        wrong poses through on the fitting data: that of the recorded rule
        (:attr:`stricter_rules`) with the largest share not above it;
        ``ValueError`` when no recorded rule is that strict."""
        fitting = [r for r in self.stricter_rules if r.wrong_accepted_at_most <= wrong_accepted]
        if not fitting:
            recorded = ", ".join(f"{r.wrong_accepted_at_most:g}" for r in self.stricter_rules) or "none"
            raise ValueError(
                f"no stricter rule recorded for at most {wrong_accepted:g} of wrong poses accepted "
                f"(recorded: {recorded}; refit with python -m export.confidence --write)"
            )
        return max(fitting, key=lambda r: r.wrong_accepted_at_most).threshold

    @cached_property
    def strict_threshold(self) -> float:
        """:meth:`threshold_for` :data:`STRICT_WRONG_ACCEPTED`; NaN when not recorded."""
        try:
            return self.threshold_for(STRICT_WRONG_ACCEPTED)
        except ValueError:
            return float("nan")

    def to_manifest(self) -> dict[str, Any]:
        return {
            "features": {n: FEATURES[n] for n in self.features},
            "terms": term_names(self.features),
            "knots": [list(k) for k in self.knots],
            "inputs": hinge_names(self.features, self.knots),
            "mean": self.mean.tolist(),
            "scale": self.scale.tolist(),
            "weights": self.weights.tolist(),
            "bias": self.bias,
        }

    @classmethod
    def from_manifest(cls, info: dict[str, Any]) -> ConfidenceModel:
        """From the manifest's ``confidence`` entry (without ``knots``: linear
        in every term; the stricter rules from its
        ``fitted_on.cross_validation.stricter_thresholds``, if any);
        ``ValueError`` naming what is wrong."""
        names = tuple(info["features"])
        unknown = [n for n in names if n not in FEATURES]
        if unknown:
            raise ValueError(f"confidence model uses features this edgepose does not compute: {unknown}")
        terms = len(term_names(names))
        knots = tuple(tuple(float(k) for k in term_knots) for term_knots in info.get("knots", [[]] * terms))
        if len(knots) != terms or any(list(k) != sorted(set(k)) for k in knots):
            raise ValueError(f"confidence model: knots must be {terms} ascending lists (one per term)")
        mean, scale, weights = (np.asarray(info[k], dtype=np.float64) for k in ("mean", "scale", "weights"))
        bias = float(info["bias"])
        inputs = len(hinge_names(names, knots))
        if not all(a.shape == (inputs,) for a in (mean, scale, weights)):
            raise ValueError(
                f"confidence model: mean/scale/weights must each hold {inputs} numbers (one per term and knot)"
            )
        if not (
            np.isfinite([*mean, *scale, *weights, bias, *(k for t in knots for k in t)]).all() and (scale > 0).all()
        ):
            raise ValueError("confidence model: numbers must be finite and scales positive")
        return cls(names, knots, mean, scale, weights, bias, stricter_rules_of(info))


def stricter_rules_of(info: dict[str, Any]) -> tuple[StricterRule, ...]:
    """The stricter rules a manifest's ``confidence`` entry records (under
    ``fitted_on.cross_validation.stricter_thresholds``); ``ValueError`` when malformed."""
    rows = info.get("fitted_on", {}).get("cross_validation", {}).get("stricter_thresholds", [])
    try:
        rules = tuple(StricterRule(**{k: float(row[k]) for k in StricterRule.__dataclass_fields__}) for row in rows)
    except (KeyError, TypeError, ValueError):
        raise ValueError(
            "confidence model: each stricter_thresholds entry needs numbers wrong_accepted_at_most, threshold, "
            "wrong_accepted and correct_kept"
        ) from None
    if not all(0.0 <= v <= 1.0 for r in rules for v in vars(r).values()):
        raise ValueError("confidence model: stricter_thresholds shares and thresholds must lie in 0-1")
    return rules


def box_sides(points: np.ndarray) -> list[float]:
    """Bounding-box side lengths of (N, 3) float32 points (a query's),
    metres (``observed_extent`` is their diagonal over d): each column's
    ``np.ptp``, in one pass of the Rust core."""
    return list(_core.box_sides(points))


@dataclass(frozen=True)
class FitEvidence:
    """The evidence a pose's scores give (:data:`FEATURES`), measured on the
    view: by the search that found the pose and afresh by each tracked frame."""

    inlier_fraction: float
    loose_inlier_fraction: float
    fit: float
    """Truncated fit over the hypothesis inlier distance, 0–1."""
    free_space_violation: float
    off_silhouette: float
    observed_extent: float
    translation_constraint: float
    scene_violation: float = 0.0

    @classmethod
    def of(cls, tight: Any, loose: Any, tight_distance: float, observed_extent: float) -> FitEvidence:
        """From one pose's scores (first row) at the hypothesis inlier
        distance ``tight_distance`` (metres; ``tight``: its fit terms) and at
        the doubt's ``loose`` one (its free-space terms), and the observed
        points' extent over the diameter."""
        return cls(
            inlier_fraction=tight.inlier_fraction[0],
            loose_inlier_fraction=loose.inlier_fraction[0],
            fit=tight.fit[0] / tight_distance,
            free_space_violation=loose.free_space_violation[0],
            off_silhouette=loose.off_silhouette[0],
            observed_extent=observed_extent,
            translation_constraint=tight.translation_constraint[0],
            scene_violation=loose.scene_violation[0],
        )


@dataclass(frozen=True)
class SearchEvidence:
    """The evidence the search that found a pose gives (:data:`FEATURES`):
    its retrieval score, how far the pose stood out from its rivals, its
    turns and alternatives. A tracked pose carries its estimate's."""

    score: float
    searched_twice: bool
    refined: bool
    margin: float
    flip_margin: float
    rmse_ratio: float
    flip_fit_ratio: float
    alternatives: int
    alternative_margin: float

    @classmethod
    def carried(cls, evidence: dict[str, float], score: float) -> SearchEvidence:
        """The search terms of an earlier pose's ``evidence`` (its retrieval
        ``score`` where the evidence has none), for a pose refined from it
        by ICP on one search's worth of points."""
        return cls(
            score=evidence.get("score", score),
            searched_twice=False,
            refined=True,
            margin=evidence.get("margin", 1.0),
            flip_margin=evidence.get("flip_margin", 1.0),
            rmse_ratio=evidence.get("rmse_ratio", 0.0),
            flip_fit_ratio=evidence.get("flip_fit_ratio", 0.0),
            alternatives=int(evidence.get("alternatives", 0.0)),
            alternative_margin=evidence.get("alternative_margin", 1.0),
        )


def evidence_of(fit: FitEvidence, search: SearchEvidence) -> dict[str, float]:
    """The evidence (:data:`FEATURES`) as a dict of floats, in their order."""
    return {
        "inlier_fraction": float(fit.inlier_fraction),
        "loose_inlier_fraction": float(fit.loose_inlier_fraction),
        "fit": float(fit.fit),
        "free_space_violation": float(fit.free_space_violation),
        "score": float(search.score),
        "searched_twice": float(search.searched_twice),
        "refined": float(search.refined),
        "margin": float(search.margin),
        "off_silhouette": float(fit.off_silhouette),
        "observed_extent": float(fit.observed_extent),
        "translation_constraint": float(fit.translation_constraint),
        "flip_margin": float(search.flip_margin),
        "rmse_ratio": float(search.rmse_ratio),
        "flip_fit_ratio": float(search.flip_fit_ratio),
        "alternatives": float(search.alternatives),
        "alternative_margin": float(search.alternative_margin),
        "scene_violation": float(fit.scene_violation),
    }
