"""An object's rotational symmetries, detected from its sampled model.

A turn that maps the surface onto itself leaves a depth view unchanged, so
poses that differ by it are equally right: a can turned about its axis, a box
turned 180° about a face normal. :func:`detect_symmetry` finds them when a
codebook is built; the codebook stores them, every :class:`edgepose.Pose`
carries them, and the evaluation judges symmetric objects with ADD-S.

Symmetries are given in the object (mesh) frame, as BOP's ``models_info``
does: discrete ones as 4 × 4 transforms, continuous ones as an axis and a
point on it (metres).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np

from edgepose import _core
from edgepose.model import StandardModel
from edgepose.views import rotation_about, rotation_angle, rotation_axis

#: Turns tried about each candidate axis: n-fold for these n ...
ORDERS = (2, 3, 4, 5, 6, 8)
#: ... and these odd angles (degrees): an axis passing all three is continuous.
CONTINUOUS_PROBES_DEG = (37.0, 101.0, 163.0)
#: A turn is a symmetry when the turned model points lie on the model's
#: surface (distance to the nearest point's tangent plane, blind to how the
#: surface was sampled): their mean distance is at most this many point
#: spacings (true symmetries: 0.03–0.11; a hexagon turned 72°: 0.54) ...
MAX_MEAN_SPACINGS = 0.5
#: ... and this quantile of them (99 %) ...
TAIL_QUANTILE = 0.99
#: ... is within this many spacings (true: ≤ 0.3; an asymmetric part that
#: moves leaves a tail: a box's holes 3.6–5.5).
MAX_Q99_SPACINGS = 1.6
#: Normal directions tried as axes besides the principal axes (the face
#: normals of boxes and prisms, whose principal axes are degenerate).
NORMAL_AXES = 12
#: Points used to screen candidate turns (and to polish the survivors by ICP,
#: in this many iterations, pairing points within this fraction of the
#: diameter) before judging them on all points ...
SCREEN_POINTS = 512
ICP_ITERATIONS = 15
ICP_MAX_DIAMETERS = 0.1
#: The polish stops when an update moves less than this (radians and metres
#: together: 10 µm), finer than an estimate's ICP, for a codebook stores the
#: turns it finds. Not hashed into the fingerprint below (the search has
#: always used it): a change to it is a change of the search, so raise
#: ``SEARCH_REVISION``.
ICP_CONVERGED = 1e-5
#: ... and the screen's looser mean distance (spacings, tangent planes).
SCREEN_MEAN_SPACINGS = 1.0
#: Groups larger than this are cut off (a cube has 24 turns).
MAX_TURNS = 60
#: Turns closer than this (degrees) are the same turn.
SAME_TURN_DEG = 2.0
#: A *near turn* (not a symmetry) keeps the model's points this close to the
#: surface on average, as a fraction of the diameter, so a partial or noisy
#: depth view may not tell a pose from the pose so turned (a box whose holes
#: are small, a disc with a notch, a lump whose seen side looks alike turned) ...
NEAR_MEAN_DIAMETERS = 0.03
#: ... is at least this far from the identity and from every other near
#: turn and symmetry (degrees) ...
NEAR_MIN_ANGLE_DEG = 30.0
#: ... and at most this many are kept, the closest fits first.
NEAR_MAX_TURNS = 6
#: Near turns are sought about the symmetry probes' axes and, besides, about
#: this many axes spread over the sphere (a lump's look-alike turn need not be
#: about a principal axis or a face normal), by these angles (degrees) ...
NEAR_PROBE_AXES = 64
NEAR_PROBE_ANGLES_DEG = (30.0, 60.0, 90.0, 120.0, 150.0, 180.0)
#: ... they are screened at this many times ``NEAR_MEAN_DIAMETERS`` (an
#: unpolished probe's axis may be a few degrees off) ...
NEAR_SCREEN_FACTOR = 2.0
#: ... and of the probes that screen close, at most this many, spread
#: ``NEAR_MIN_ANGLE_DEG`` apart and best first, are polished by ICP.
NEAR_POLISHED = 4 * NEAR_MAX_TURNS
#: Angles this close (radians) below a limit above count as reaching it:
#: probes on a 30° grid are exactly ``NEAR_MIN_ANGLE_DEG`` apart, and
#: which way the arithmetic rounds (±3e-16) decided whether they were
#: (27 of the 67 fitting objects' near turns changed when it stopped).
ROUNDING_RAD = 1e-9
#: Raised when :func:`detect_symmetry` changes in a way the constants above
#: do not show, the Rust core's distances and ICP included (a test compares
#: the shipped codebooks' symmetries with what the search finds now).
#: 5: near turns about spread axes, a sphere gets none; 6: turns exactly a
#: limit apart reach it (``ROUNDING_RAD``), and an object with a continuous
#: symmetry has at most a flip besides ...
SEARCH_REVISION = 6
#: ... so that this, recorded in every codebook, tells a codebook whose
#: symmetries and near turns an older search found (``edgepose build``
#: rebuilds it): the revision and the constants, hashed.
SEARCH_FINGERPRINT = hashlib.sha256(
    repr(
        (
            SEARCH_REVISION,
            ORDERS,
            CONTINUOUS_PROBES_DEG,
            MAX_MEAN_SPACINGS,
            TAIL_QUANTILE,
            MAX_Q99_SPACINGS,
            NORMAL_AXES,
            SCREEN_POINTS,
            ICP_ITERATIONS,
            ICP_MAX_DIAMETERS,
            SCREEN_MEAN_SPACINGS,
            MAX_TURNS,
            SAME_TURN_DEG,
            NEAR_MEAN_DIAMETERS,
            NEAR_MIN_ANGLE_DEG,
            NEAR_MAX_TURNS,
            NEAR_PROBE_AXES,
            NEAR_PROBE_ANGLES_DEG,
            NEAR_SCREEN_FACTOR,
            NEAR_POLISHED,
            ROUNDING_RAD,
        )
    ).encode()
).hexdigest()[:16]


@dataclass(frozen=True, eq=False)
class Symmetry:
    """Rotational symmetries of an object, object (mesh) frame, metres.
    Empty for an asymmetric object. Immutable."""

    discrete: np.ndarray
    """(M, 4, 4) float64 turns ``T`` with ``surface = T · surface``, identity
    excluded (for a continuous symmetry: the extra flips, e.g. a can's 180°
    turn top to bottom)."""
    continuous: np.ndarray
    """(A, 6) float64: each row a unit axis and a point on it; the surface is
    unchanged by any turn about it."""
    near: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    """(K, 4, 4) float64 *near turns*: not symmetries, but turns that keep
    the surface within ``NEAR_MEAN_DIAMETERS`` of itself, so a view may not
    tell a pose from the pose so turned. The confidence tests them
    (``flip_margin``); the evaluation does not forgive them (ADD)."""

    @property
    def symmetric(self) -> bool:
        """Whether any turn but the identity maps the object onto itself."""
        return len(self.discrete) > 0 or len(self.continuous) > 0

    def describe(self) -> str:
        """One line for people: ``none``, ``continuous about (0, 0, 1)``, ``3 discrete turns``…"""
        parts = [f"continuous about ({', '.join(f'{v:.2f}' for v in row[:3])})" for row in self.continuous]
        if len(self.discrete):
            parts.append(f"{len(self.discrete)} discrete turn{'s' if len(self.discrete) > 1 else ''}")
        near = f" ({len(self.near)} near turn{'s' if len(self.near) > 1 else ''})" if len(self.near) else ""
        return (" + ".join(parts) or "none") + near

    def transforms(self, steps: int = 36) -> np.ndarray:
        """(G, 4, 4) every turn of the group, identity first, a continuous one
        sampled every ``360 / steps`` degrees (for metrics over symmetries)."""
        turns = [np.eye(4)]
        if len(self.continuous):
            axis, point = self.continuous[0, :3], self.continuous[0, 3:]
            for k in range(1, steps):
                turns.append(_turn_about(axis, point, 2 * np.pi * k / steps))
        return np.stack(turns + [D @ T for D in self.discrete for T in turns])

    def to_json(self) -> dict[str, list]:
        """Rounded to 1e-6 (µm, µrad): the same model gives the same codebook bytes."""
        return {
            "discrete": np.round(self.discrete.reshape(-1, 16), 6).tolist(),
            "continuous": np.round(self.continuous, 6).tolist(),
            "near": np.round(self.near.reshape(-1, 16), 6).tolist(),
        }

    @classmethod
    def from_json(cls, info: dict) -> Symmetry:
        """From :meth:`to_json`'s dict (no ``near`` entry: none recorded);
        ``ValueError`` if it is not valid."""
        discrete = np.asarray(info["discrete"], dtype=np.float64).reshape(-1, 4, 4)
        continuous = np.asarray(info["continuous"], dtype=np.float64).reshape(-1, 6)
        near = np.asarray(info.get("near", []), dtype=np.float64).reshape(-1, 4, 4)
        if not (np.isfinite(discrete).all() and np.isfinite(continuous).all() and np.isfinite(near).all()):
            raise ValueError("symmetries contain NaN or infinite values")
        for turns, what in ((discrete, "discrete symmetry"), (near, "near turn")):
            R = turns[:, :3, :3]
            if len(R) and (
                np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max() > 1e-4
                or np.abs(turns[:, 3] - [0, 0, 0, 1]).max() > 0
            ):
                raise ValueError(f"a {what} is not a rigid turn")
        if len(continuous) and np.abs(np.linalg.norm(continuous[:, :3], axis=1) - 1).max() > 1e-4:
            raise ValueError("a continuous symmetry's axis is not a unit vector")
        return cls(discrete, continuous, near)


NO_SYMMETRY = Symmetry(np.zeros((0, 4, 4)), np.zeros((0, 6)))


def detect_symmetry(model: StandardModel, index: _core.ModelIndex | None = None) -> Symmetry:
    """The turns that map ``model``'s surface onto itself (object frame).

    Axes through the surface's centroid are tried: the principal axes and
    the most spread-out normal directions; about each, n-fold turns and
    three odd angles (continuous). A turn that roughly fits is polished by
    ICP of the model onto itself (a sampled axis is a degree or two off),
    and counts when the turned points then lie on the model
    (``MAX_MEAN_SPACINGS``, ``MAX_Q99_SPACINGS``). An axis whose three odd
    turns all count is continuous, and then only a flip across it is kept
    besides; else the turns are closed into their group. Near turns (:func:`_near_turns`) are
    sought too. Deterministic."""
    index = index or _core.ModelIndex(model.core)
    points = model.points.astype(np.float64)
    centroid = points.mean(axis=0)
    axes = _candidate_axes(points - centroid, model.normals)
    every = np.ascontiguousarray(model.points)
    screen = np.ascontiguousarray(model.points[:: max(1, len(points) // SCREEN_POINTS)])

    def fits(R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Which turns (C, 3, 3), (C, 3) map every model point onto the surface."""
        limit = MAX_MEAN_SPACINGS * model.spacing
        d = index.distances(every, np.ascontiguousarray(R), np.ascontiguousarray(t), True, limit)
        ok = d.mean(axis=1) <= limit  # the others' rows were cut short
        ok[ok] = np.quantile(d[ok], TAIL_QUANTILE, axis=1) <= MAX_Q99_SPACINGS * model.spacing
        return ok

    probes = [(a, angle) for a in axes for angle in np.radians([*CONTINUOUS_PROBES_DEG, *(360 / n for n in ORDERS)])]
    R = np.stack([rotation_about(a, angle) for a, angle in probes])
    t = centroid - R @ centroid
    # Screen loosely, polish the survivors by ICP, then judge strictly on every point.
    loose = SCREEN_MEAN_SPACINGS * model.spacing
    near = index.distances(screen, R, t, True, loose).mean(axis=1) <= loose
    turns: dict[int, np.ndarray] = {}
    if near.any():
        icp = index.refine(
            screen, R[near], t[near], ICP_ITERATIONS, ICP_MAX_DIAMETERS * model.diameter, converged=ICP_CONVERGED
        )
        good = fits(icp.rotations, icp.translations)
        for probe, R_i, t_i, ok in zip(np.flatnonzero(near), icp.rotations, icp.translations, good):
            if ok:
                turns[int(probe)] = transform_from(R_i, t_i)
    per_axis = len(probes) // len(axes)

    continuous: list[tuple[np.ndarray, np.ndarray]] = []
    for i in range(len(axes)):
        found = [T for j, T in turns.items() if j // per_axis == i]
        if not found:
            continue
        # The polished axis, from the polished turn of largest angle, is
        # tried at the three odd angles (ICP could slide along a continuous
        # symmetry, or snap an odd angle to a hexagon's 60°).
        T = max(found, key=lambda T: rotation_angle(T[:3, :3]))
        axis, point = rotation_axis(T[:3, :3]), _point_on_axis(T, centroid)
        odd = np.stack([_turn_about(axis, point, a) for a in np.radians(CONTINUOUS_PROBES_DEG)])
        if fits(odd[:, :3, :3], odd[:, :3, 3]).all() and all(
            abs(axis @ c) < np.cos(np.radians(SAME_TURN_DEG)) for c, _ in continuous
        ):
            continuous.append((axis, point))
    generators = [T for _, T in sorted(turns.items())]
    if continuous:
        # Turns about the axis are covered, and any flip across it (the axis
        # end for end) is the same flip up to such a turn, so one is kept. A
        # turn that tilts the axis is a loose fit, not a symmetry (a gear
        # turned by about a tooth and tilted 8° passed).
        axis = continuous[0][0]
        generators = [T for T in generators if axis @ T[:3, :3] @ axis < -np.cos(np.radians(SAME_TURN_DEG))][:1]
    group = _closure(generators)
    if len(continuous) > 1:  # two continuous axes: a sphere, every axis
        continuous, group = [(np.eye(3)[i], centroid) for i in range(3)], []
    # Model frame → object frame: p_obj = p_model + centre.
    discrete = _shifted(group, model.centre)
    rows = [np.concatenate([a * np.sign(a[np.argmax(np.abs(a))]), p + model.centre]) for a, p in continuous]
    near = _near_turns(index, model, screen, centroid, R, t, group, [a for a, _ in continuous])
    return Symmetry(discrete, np.array(rows).reshape(-1, 6), _shifted(near, model.centre))


def _near_turns(
    index: _core.ModelIndex,
    model: StandardModel,
    screen: np.ndarray,
    centroid: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    group: list[np.ndarray],
    continuous_axes: list[np.ndarray],
) -> list[np.ndarray]:
    """Near turns (model frame, 4 × 4) among the probe turns ``R``, ``t``
    and the turns about ``NEAR_PROBE_AXES`` spread axes through the model
    points' ``centroid``: the probes that screen close (at most ``NEAR_POLISHED``,
    spread apart) each polished by ICP (kept unpolished when ICP slides it
    back towards the identity), then kept when the turned model points lie
    on average within ``NEAR_MEAN_DIAMETERS`` of the surface and it is no
    symmetry (fails their test; none of ``group``, no turn about a
    ``continuous_axes``), closest first. None for a sphere (two or more
    continuous axes: every turn is a symmetry)."""
    if len(continuous_axes) > 1:
        return []
    limit = NEAR_MEAN_DIAMETERS * model.diameter
    minimum = np.radians(NEAR_MIN_ANGLE_DEG)
    spread_R = _turns_about_spread_axes()
    R = np.ascontiguousarray(np.concatenate([R, spread_R]))
    t = np.ascontiguousarray(np.concatenate([t, centroid - spread_R @ centroid]))
    # Turns screened above the cut-off are cut short (their mean reads inf).
    screened = index.distances(screen, R, t, True, NEAR_SCREEN_FACTOR * limit).mean(axis=1)
    chosen: list[int] = []
    for i in np.argsort(screened, kind="stable"):
        if screened[i] > NEAR_SCREEN_FACTOR * limit or len(chosen) == NEAR_POLISHED:
            break
        if all(_apart(R[i], R[j], NEAR_MIN_ANGLE_DEG) for j in chosen):
            chosen.append(int(i))
    if not chosen:
        return []
    R, t = np.ascontiguousarray(R[chosen]), np.ascontiguousarray(t[chosen])
    icp = index.refine(screen, R, t, ICP_ITERATIONS, ICP_MAX_DIAMETERS * model.diameter, converged=ICP_CONVERGED)
    polished = np.array([_apart(np.eye(3), Ri, NEAR_MIN_ANGLE_DEG) for Ri in icp.rotations])
    R_c = np.where(polished[:, None, None], icp.rotations, R)
    t_c = np.where(polished[:, None], icp.translations, t)
    mean = index.distances(np.ascontiguousarray(model.points), R_c, t_c, True, limit).mean(axis=1)
    kept: list[np.ndarray] = []
    known = [np.eye(4), *group]
    for i in np.argsort(mean, kind="stable"):
        if mean[i] > limit or len(kept) == NEAR_MAX_TURNS:
            break
        T = transform_from(R_c[i], t_c[i])
        if not all(_apart(T[:3, :3], G[:3, :3], NEAR_MIN_ANGLE_DEG) for G in known + kept):
            continue
        # About a continuous axis, or across it when the object has a flip: a symmetry.
        if any(
            a @ T[:3, :3] @ a > np.cos(minimum) or (group and a @ T[:3, :3] @ a < -np.cos(minimum))
            for a in continuous_axes
        ):
            continue
        kept.append(T)
    return kept


def doubtful_turns(model: StandardModel, symmetry: Symmetry) -> tuple[np.ndarray, np.ndarray]:
    """The turns of the model a search may mistake a pose for, model frame:
    rotations (K, 3, 3) and translations (K, 3), metres. The object's near
    turns (:attr:`Symmetry.near`) and the half turns about the model points'
    principal axes through their centroid (a banana end for end) that are
    not already among them (a box's near turns are its half turns)."""
    turns = list(_shifted(symmetry.near, -model.centre))  # object frame -> model frame
    centroid, axes = model.principal_axes
    for axis in axes.T:
        T = _turn_about(axis, centroid, np.pi)
        if all(_apart(T[:3, :3], N[:3, :3], NEAR_MIN_ANGLE_DEG) for N in turns):
            turns.append(T)
    stacked = np.stack(turns)
    return np.ascontiguousarray(stacked[:, :3, :3]), np.ascontiguousarray(stacked[:, :3, 3])


def _turns_about_spread_axes() -> np.ndarray:
    """(NEAR_PROBE_AXES × angles, 3, 3) turns by ``NEAR_PROBE_ANGLES_DEG``
    about ``NEAR_PROBE_AXES`` near-uniform axes."""
    axes, _ = _core.fibonacci_viewpoints(NEAR_PROBE_AXES)
    return np.stack(
        [rotation_about(a / np.linalg.norm(a), np.radians(angle)) for a in axes for angle in NEAR_PROBE_ANGLES_DEG]
    )


def _apart(Ra: np.ndarray, Rb: np.ndarray, degrees: float) -> bool:
    """Whether rotations ``Ra`` and ``Rb`` (3 × 3) are at least ``degrees``
    apart, up to ``ROUNDING_RAD``: probes turned exactly that far apart (30°
    and 60° about one axis) are, whichever way the arithmetic rounds."""
    return rotation_angle(Ra.T @ Rb) >= np.radians(degrees) - ROUNDING_RAD


def _shifted(turns: list[np.ndarray] | np.ndarray, offset: np.ndarray) -> np.ndarray:
    """(K, 4, 4) the 4 × 4 ``turns`` of points ``p`` as turns of ``p + offset``
    (metres): model frame -> object frame with the model centre as ``offset``,
    back with its negative."""
    shift, unshift = transform_from(np.eye(3), offset), transform_from(np.eye(3), -offset)
    return np.stack([shift @ T @ unshift for T in turns]) if len(turns) else np.zeros((0, 4, 4))


def _candidate_axes(centred: np.ndarray, normals: np.ndarray) -> list[np.ndarray]:
    """Unit axes (sign-free, deduplicated): principal axes, then spread normals."""
    _, vectors = np.linalg.eigh(np.cov(centred.T))
    folded = np.where(normals[:, 2:3] < 0, -normals, normals).astype(np.float32)
    spread = _core.farthest_point_sample(np.ascontiguousarray(folded), min(NORMAL_AXES, len(folded)))
    axes: list[np.ndarray] = []
    for a in [*vectors.T, *folded[spread].astype(np.float64)]:
        a = a / np.linalg.norm(a)
        if all(abs(a @ b) < np.cos(np.radians(SAME_TURN_DEG)) for b in axes):
            axes.append(a)
    return axes


def _closure(generators: list[np.ndarray]) -> list[np.ndarray]:
    """The group the turns (4 × 4) generate, identity excluded, at most ``MAX_TURNS``."""
    group = [np.eye(4)]

    def known(T: np.ndarray) -> bool:
        return not all(_apart(T[:3, :3], G[:3, :3], SAME_TURN_DEG) for G in group)

    frontier = []
    for g in generators:
        if not known(g):
            group.append(g)
            frontier.append(g)
    while frontier and len(group) < MAX_TURNS:
        new = []
        for A in frontier:
            for G in list(group):
                for T in (A @ G, G @ A):
                    if len(group) < MAX_TURNS and not known(T):
                        group.append(T)
                        new.append(T)
        frontier = new
    return group[1:]


def _point_on_axis(T: np.ndarray, near: np.ndarray) -> np.ndarray:
    """The point of turn ``T``'s fixed line closest to ``near``."""
    R, t = T[:3, :3], T[:3, 3]
    q = np.linalg.lstsq(np.eye(3) - R, t - (np.eye(3) - R) @ near, rcond=1e-6)[0]
    return near + q


def transform_from(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) float64 transform of rotation ``R`` and translation ``t``."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _turn_about(axis: np.ndarray, point: np.ndarray, angle: float) -> np.ndarray:
    """4 × 4 turn by ``angle`` (radians) about the line through ``point`` along ``axis``."""
    R = rotation_about(axis, angle)
    return transform_from(R, point - R @ point)
