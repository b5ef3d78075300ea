"""View-dependent ambiguity: turns about a near-symmetry axis that the view
cannot rule out.

A mug whose handle is hidden behind it is, from that view, a cylinder: every
turn about its axis that keeps the handle out of sight explains the depth
as well as the pose does. The object has no symmetry (the handle breaks
it), so :mod:`edgepose.symmetry` cannot forgive these turns; but its near
turns (:attr:`edgepose.Symmetry.near`) reveal the axis: three or more near
turns about one axis mean most of the surface is a body of revolution
about it. :func:`unseen_turn` tries the pose turned about that axis on a
grid of angles, keeps the turns that explain the observed points nearly as
well as the pose (inlier share net of free-space and scene violations,
within ``settings.alternatives.within``) and reports them: which of them
are too far from the pose to be right if it is (ADD > 0.1 × diameter), a
spread of those as alternatives, and the share of the explaining turns
that the pose stands for. Views that show the handle rule out all but the
turns near the pose, and nothing changes.

Frames: axes and points in the object (mesh) frame, metres; poses model
frame → camera where they come from the search (model = mesh − centre).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from edgepose.codebook import Codebook
from edgepose.settings import EstimateSettings
from edgepose.stages import Hypotheses, Query, Refined, distinct_poses, pose_distances, score_poses
from edgepose.symmetry import Symmetry
from edgepose.views import rotation_about, rotation_axis

#: Near turns about one axis (their axes within this many degrees) that
#: make it a near-symmetry axis: two could be a 3-fold's pair; a body of
#: revolution with one feature has turns at many angles.
MIN_TURNS_ABOUT_AXIS = 3
SAME_AXIS_DEG = 5.0
#: Turns tried about the axis, degrees apart (24 a circle: the arc a 0.1 ×
#: diameter ADD allows a mug is about ±20°, so each is seen by 2–3 steps).
STEP_DEG = 15.0
#: The turns screened first, either way (degrees): beyond the 0.1 ×
#: diameter of a mug-sized body, so a view leaving them open leaves the turn open.
SCREEN_DEG = 2 * STEP_DEG
#: A turn is "right if the pose is" when its ADD from the pose is below
#: this fraction of the diameter (the correctness criterion).
RIGHT_WITHIN = 0.1


@dataclass(frozen=True, eq=False)
class NearAxis:
    """An axis most of the object's surface turns onto itself about (object frame, metres)."""

    axis: np.ndarray
    """(3,) unit direction."""
    point: np.ndarray
    """(3,) a point on it."""


@dataclass(frozen=True, eq=False)
class UnseenTurn:
    """Turns about the object's near-symmetry axis that the view cannot rule
    out (:attr:`edgepose.Pose.unseen_turn`): "the mug is here, its handle is
    unseen". Object frame, metres, degrees."""

    axis: np.ndarray
    """(3,) unit direction of the axis, object frame."""
    point: np.ndarray
    """(3,) a point on the axis, object frame, metres."""
    angles_deg: np.ndarray
    """(A,) the turns of the pose about ``axis`` (right-handed, degrees in
    (-180, 180], 0 the pose itself) that explain the view nearly as well."""
    share: float
    """Of those turns, the share within ADD < 0.1 × diameter of the pose:
    the chance that the pose is the right one of them when the view cannot
    choose (the confidence is scaled by it)."""


def near_axis(symmetry: Symmetry) -> NearAxis | None:
    """The axis of at least :data:`MIN_TURNS_ABOUT_AXIS` of the object's
    near turns, or None. Its direction is their mean axis, its point the
    least-squares fixed point of the turns. Worked out once per set of
    near turns (every estimate of an object asks)."""
    near = np.ascontiguousarray(symmetry.near, dtype=np.float64).reshape(-1, 4, 4)
    if len(near) < MIN_TURNS_ABOUT_AXIS or len(symmetry.continuous):
        return None
    return _near_axis(near.tobytes())


@functools.lru_cache(maxsize=256)
def _near_axis(near_turns: bytes) -> NearAxis | None:
    near = np.frombuffer(near_turns, dtype=np.float64).reshape(-1, 4, 4)
    axes = np.array([rotation_axis(T[:3, :3]) for T in near])
    for reference in axes:
        aligned = axes * np.sign(axes @ reference)[:, None]
        same = np.degrees(np.arccos(np.clip(aligned @ reference, -1.0, 1.0))) < SAME_AXIS_DEG
        if same.sum() >= MIN_TURNS_ABOUT_AXIS:
            axis = aligned[same].mean(axis=0)
            axis /= np.linalg.norm(axis)
            turns = near[same]
            # Each turn fixes its axis: (I - R) p = t, stacked; the minimum-norm
            # solution picks the point on the axis nearest to the origin.
            A = np.concatenate([np.eye(3) - T[:3, :3] for T in turns])
            b = np.concatenate([T[:3, 3] for T in turns])
            point = np.linalg.lstsq(A, b, rcond=None)[0]
            point -= axis * (point @ axis)
            axis.setflags(write=False)  # shared by every estimate of the object
            point.setflags(write=False)
            return NearAxis(axis, point)
    return None


def turned_about(R: np.ndarray, t: np.ndarray, axis: NearAxis, centre: np.ndarray, angles_deg: np.ndarray):
    """Pose ``(R, t)`` (model frame → camera) turned about ``axis`` by each
    angle: (A, 3, 3) rotations and (A, 3) translations, model frame → camera."""
    point = axis.point - centre  # the axis point in the model frame
    turns = np.array([rotation_about(axis.axis, np.radians(a)) for a in angles_deg])
    rotations = R @ turns
    translations = t + R @ point - rotations @ point
    return rotations, translations


def unseen_turn(
    codebook: Codebook,
    net_of,
    R: np.ndarray,
    t: np.ndarray,
    settings: EstimateSettings,
) -> tuple[UnseenTurn, np.ndarray, np.ndarray, np.ndarray] | None:
    """The turns of pose ``(R, t)`` (model frame → camera) about the
    object's near-symmetry axis that explain the view within
    ``settings.alternatives.within`` of the pose (``net_of(rotations,
    translations)``: each pose's inlier share net of violations on the
    hypotheses' observed points), when some of them are more than
    0.1 × diameter from the pose; with the turned poses to offer as
    alternatives (rotations, translations, nets: a spread of them, each
    more than 0.1 × diameter from the pose and from the one before, best
    first). None when the object has no such axis or the view fixes the
    turn (neither turn :data:`SCREEN_DEG` beside the pose explains it)."""
    axis = near_axis(codebook.symmetry)
    if axis is None or settings.alternatives.unseen_turns < 0:
        return None
    # A view that fixes the turn rules out the turns beside the pose: a
    # cheap screen of those two spares most such views the full circle.
    beside = np.array([0.0, SCREEN_DEG, -SCREEN_DEG])
    screened = net_of(*turned_about(R, t, axis, codebook.model.centre, beside))
    if not (screened[1:] >= screened[0] - settings.alternatives.within).any():
        return None
    angles = np.arange(0.0, 360.0, STEP_DEG)
    angles = np.where(angles > 180.0, angles - 360.0, angles)
    rotations, translations = turned_about(R, t, axis, codebook.model.centre, angles)
    net = net_of(rotations, translations)
    # Only the turns that explain the view matter from here (the pose, at 0°, first).
    explains = net >= net[0] - settings.alternatives.within
    angles, rotations, translations, net = angles[explains], rotations[explains], translations[explains], net[explains]
    limit = RIGHT_WITHIN * codebook.model.diameter
    # ADD from the pose (ADD-S for a symmetric object: a turn onto a symmetry is the pose).
    near = pose_distances(codebook, rotations, translations, 0) < limit
    if near.all():
        return None
    found = UnseenTurn(axis.axis, axis.point, angles, float(near.mean()))
    # A spread: sweeping away from the pose both ways, a turn joins when it is
    # more than 0.1 × diameter from the last one taken (or from the pose).
    picked: list[int] = []
    for direction in (1.0, -1.0):
        apart = ~near
        for i in np.argsort(direction * angles):
            if direction * angles[i] > 0 and apart[i]:
                picked.append(int(i))
                apart = pose_distances(codebook, rotations, translations, int(i)) >= limit
    picked = sorted(sorted(set(picked)), key=lambda i: -net[i])[: settings.alternatives.unseen_turns]
    return found, rotations[picked], translations[picked], net[picked]


def view_left_open(
    query: Query,
    codebook: Codebook,
    result: Refined,
    others: Hypotheses,
    confidence: float,
    settings: EstimateSettings,
) -> tuple[UnseenTurn | None, Hypotheses, float]:
    """The turns about the object's near-symmetry axis that the view leaves
    open (:func:`edgepose.unseen_turn.unseen_turn`), if any, for a refined
    pose: their spread joins the alternatives (those not within 0.1 ×
    diameter of one already there) and the confidence is scaled by the
    share of them the pose stands for."""
    if not result.refined:
        return None, others, confidence
    observed = query.sample(settings.refine.hypothesis_points, settings.subsample_seed)
    d = codebook.model.diameter

    def net_of(rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
        inlier = settings.refine.hypothesis_inlier_distance * d
        return score_poses(query, codebook, observed, rotations, translations, inlier, 0.0, settings).net

    found = unseen_turn(codebook, net_of, result.R, result.t, settings)
    if found is None:
        return None, others, confidence
    turn, R, t, net = found
    pool = Hypotheses(
        np.concatenate([result.R[None], others.rotations, R]),
        np.concatenate([result.t[None], others.translations, t]),
        np.concatenate([result.scores.net[:1], others.net, net]),
    )
    keep = len(others.net) + len(net)
    order = np.arange(len(pool.net))  # the search's alternatives first, then the spread
    picked = distinct_poses(codebook, pool.rotations, pool.translations, order, np.ones(len(order), bool), keep)
    merged = Hypotheses(pool.rotations[picked], pool.translations[picked], pool.net[picked])
    return turn, merged, confidence * turn.share
