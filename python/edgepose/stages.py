"""The five named stages of :func:`edgepose.estimate` (../shared/DESIGN.md,
step 7), each reusable on its own (the exporter's evaluation, benchmarks):

1. :func:`prepare_query` — keep the points that are the object (outliers,
   flying pixels and background a spilled mask picked up are dropped), turn
   the cloud so its centroid ray is the optical axis, centre, scale and
   resample it to a map;
2. :func:`retrieve` — encode the map, cosine top-K over the codebook's
   codes (Rust), the in-plane angle of each candidate (IRR head);
3. :func:`candidate_poses` — each candidate view and angle as a pose
   (:func:`pair_poses`: poses voted for by point pairs, for doubtful views);
4. :func:`score_poses` — how well each pose explains the view: truncated
   keypoint distances to the model and free-space violations (Rust);
5. :func:`refine_hypotheses` — point-to-plane ICP (Rust) from the best few
   distinct candidates, scored again; the best one is polished (while
   another core searches for its turned rival for the confidence,
   :func:`polished`).

Poses are model frame → camera (the model frame is the mesh frame shifted by
the model's centre); units are metres. Every tuning value lives in
:class:`edgepose.settings.EstimateSettings`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from typing import NamedTuple

import numpy as np

from edgepose import _core
from edgepose.cloud import MIN_POINTS, clean_cloud
from edgepose.codebook import Codebook
from edgepose.encoder import Encoder
from edgepose.settings import DEFAULT_SETTINGS, EstimateSettings
from edgepose.views import rotation_about_z


@dataclass(frozen=True, eq=False)
class Query:
    """An observed cloud made ready for the codebook (stage 1)."""

    points: np.ndarray
    """(N, 3) float32 camera-frame points kept as the object, metres."""
    spacing: float
    """Median distance between neighbouring points, metres (sizes the free-space grid)."""
    centroid: np.ndarray
    """(3,) float64 centroid of ``points``."""
    r_corr: np.ndarray
    """(3, 3) viewpoint correction: camera frame → frame whose +z is the centroid ray."""
    map: np.ndarray
    """(M, 3) float32 the corrected, centred, scaled and resampled map."""
    keypoints: np.ndarray
    """(KP, 3) float32 the map's first farthest-point samples, back in the camera frame."""
    scene: SceneDepth | None = None
    """The frame's depth around the object, when the caller gave the depth
    image (:func:`scene_around`): the scene-violation test reads it."""
    _samples: dict = field(default_factory=dict, repr=False)

    @cached_property
    def free_space(self) -> _core.DepthGrid:
        """The nearest observed depth along each ray of ``points`` (what the
        free-space test of :func:`score_poses` reads), with the scene's depth
        around the object when known; built once per query."""
        if self.scene is None:
            return _core.DepthGrid(self.points, self.spacing)
        return _core.DepthGrid(self.points, self.spacing, self.scene.depth, self.scene.camera, self.scene.radius)

    @cached_property
    def rim_tolerant_free_space(self) -> _core.DepthGrid:
        """:attr:`free_space` (without the scene) whose cells at the edge of
        the observed silhouette read the nearest depth within one cell: what
        the doubt's free-space test reads (:func:`rim_tolerant_violation`)."""
        return _core.DepthGrid(self.points, self.spacing, edge_slack=True)

    @cached_property
    def median_depth(self) -> float:
        """Median z of ``points``, metres: the depth the sensor's noise is read at."""
        return float(np.median(self.points[:, 2]))

    def sample(self, count: int, seed: int) -> np.ndarray:
        """:func:`subsample` of ``points`` (``count``, ``seed``), drawn once
        per query: the stages ask for the same samples several times."""
        if (count, seed) not in self._samples:
            self._samples[count, seed] = subsample(self.points, count, seed)
        return self._samples[count, seed]


@dataclass(frozen=True)
class SceneDepth:
    """A window of the frame's depth image around one object: what the
    scene-violation test compares model points off the object's silhouette
    with (see ``rust/src/scoring.rs``)."""

    depth: np.ndarray
    """(h, w) float32 C-contiguous depth of the window, metres; 0: no measurement."""
    camera: tuple[float, float, float, float]
    """(fx, fy, cx, cy) of the window's pixels."""
    radius: int = 2
    """Each pixel is read as the nearest depth within this many pixels
    (an object's edge jitters by a pixel or two)."""


def on_support_plane(
    points: np.ndarray, depth: np.ndarray, K: np.ndarray, depth_scale: float, diameter: float
) -> np.ndarray:
    """(n,) bool: the ``points`` ((n, 3) float32, camera frame, metres) that
    lie on the surface the object stands on or in front of (a table, a
    wall): a plane that most pixels 6–12 px around the points' silhouette in
    the checked ``depth`` image (``depth / depth_scale`` metres, intrinsics
    ``K``) show, with the rest of the points on the camera's side of it. A
    detector's mask takes such points where it spills; where a table meets
    the object there is no depth jump to drop them by. All False when the
    surroundings show no such plane. Runs in the Rust core
    (``rust/src/support.rs``, its thresholds there) without the GIL."""
    return _core.on_support_plane(points, depth, K, float(depth_scale), float(diameter))


def off_support_plane(
    points: np.ndarray,
    frame: tuple[np.ndarray, np.ndarray, float] | None,
    diameter: float,
    settings: EstimateSettings,
) -> np.ndarray:
    """``points`` ((n, 3) float32, camera frame, metres) without those
    :func:`on_support_plane` finds on the surface the object stands on in
    ``frame`` (the checked depth image, K and depth scale they came from),
    unless fewer than ``MIN_POINTS`` would remain; ``points`` as they are
    without a frame or with ``settings.support_plane`` off."""
    if frame is None or not settings.support_plane:
        return points
    on = on_support_plane(points, *frame, diameter)
    if on.any() and (~on).sum() >= MIN_POINTS:
        return np.ascontiguousarray(points[~on])
    return points


def scene_around(
    depth: np.ndarray, K: np.ndarray, depth_scale: float, points: np.ndarray, diameter: float
) -> SceneDepth:
    """The window of a checked ``depth`` image (``depth / depth_scale``
    metres, intrinsics ``K``) that a pose of an object of ``diameter``
    (metres) near its observed ``points`` (camera frame) can project into:
    their pixel bounding box grown by ``SCENE_MARGIN`` × the diameter's size
    in pixels at their nearest depth."""
    grow = SCENE_MARGIN * diameter / max(float(points[:, 2].min()), 1e-6)
    return _scene_window(depth, K, depth_scale, points, grow * float(K[0, 0]), grow * float(K[1, 1]))


def scene_of_pose(
    depth: np.ndarray, K: np.ndarray, depth_scale: float, codebook: Codebook, R: np.ndarray, t: np.ndarray
) -> SceneDepth | None:
    """The window of a checked ``depth`` image that one pose (model frame →
    camera) of ``codebook``'s object projects into: its bounding box's
    eight corners projected, grown by the scene test's pixel radius; None
    when a corner is not in front of the camera. The tracker's window: its
    pose is known before the scene is read, so the window need not cover
    every pose a search might keep (:func:`scene_around`)."""
    corners = codebook.model.box_corners @ R.T + t
    if corners[:, 2].min() <= 1e-6:
        return None
    grow = SceneDepth.radius + 1
    return _scene_window(depth, K, depth_scale, corners, grow, grow)


def _scene_window(
    depth: np.ndarray, K: np.ndarray, depth_scale: float, points: np.ndarray, grow_u: float, grow_v: float
) -> SceneDepth:
    """The window of ``depth`` over the pixel bounding box of ``points``
    (camera frame, in front of it), grown by ``grow_u`` and ``grow_v`` pixels."""
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    z = np.maximum(points[:, 2], 1e-6)
    u, v = fx * points[:, 0] / z + cx, fy * points[:, 1] / z + cy
    h, w = depth.shape
    c0, c1 = int(max(u.min() - grow_u, 0)), int(min(u.max() + grow_u + 1, w))
    r0, r1 = int(max(v.min() - grow_v, 0)), int(min(v.max() + grow_v + 1, h))
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # the core reads NaN, inf, ≤ 0 as none
        window = np.divide(depth[r0:r1, c0:c1], depth_scale, dtype=np.float32)
    return SceneDepth(window, (fx, fy, cx - c0, cy - r0))


#: How far beyond the observed points (× d) the scene window reaches: a pose
#: the search keeps (its centre within 1.25 model radii of the observed
#: centroid) puts almost all of its model there.
SCENE_MARGIN = 0.75


class PoseScores(NamedTuple):
    """Stage 4's terms per pose (see ``rust/src/scoring.rs``); lower ``cost`` is better."""

    fit: np.ndarray
    inlier_fraction: np.ndarray
    free_space_violation: np.ndarray
    cost: np.ndarray
    """fit / inlier distance + free_space_weight × (free-space + scene violations)."""
    off_silhouette: np.ndarray
    """Share of the camera-facing model points landing where nothing was observed, 0–1."""
    translation_constraint: np.ndarray
    """How firmly the explained points pin the translation: the smallest
    eigenvalue of the mean n nᵀ of their model normals, 0 (the pose could
    slide along the seen surface) to 1/3."""
    scene_violation: np.ndarray
    """Share of the camera-facing model points off the observed silhouette
    that stand in front of the scene's depth there, 0–1 (0 without a scene)."""

    @property
    def violation(self) -> np.ndarray:
        """Free-space plus scene violations: how much the pose contradicts the view."""
        return self.free_space_violation + self.scene_violation

    @property
    def net(self) -> np.ndarray:
        """Inlier fraction minus :attr:`violation`: how hypotheses compete."""
        return self.inlier_fraction - self.violation


def prepare_query(
    cloud: object,
    codebook: Codebook,
    settings: EstimateSettings = DEFAULT_SETTINGS,
    frame: tuple[np.ndarray, np.ndarray, float] | None = None,
) -> Query:
    """Stage 1: the object's points of ``cloud`` (camera frame, metres) and
    its map, in one call to the Rust core (``rust/src/query.rs``);
    ``frame``: the checked depth image, K and depth scale the cloud came
    from, for the scene-violation test (:func:`scene_around`) and, first,
    to drop the points the mask took from the surface the object stands on
    (:func:`on_support_plane`, ``settings.support_plane``)."""
    model = codebook.model
    cleaned = clean_cloud(cloud, model.diameter, settings.max_cloud_points)
    points, spacing, centroid, r_corr, query_map, keypoints = _core.prepare_query(
        off_support_plane(cleaned, frame, model.diameter, settings),
        model.diameter,
        model.scale,
        codebook.map_points,
        settings.keypoints,
        MIN_POINTS,
        settings.segment,
        settings.shadow_spacings,
        settings.max_shadowed_fraction,
        settings.min_component_fraction,
        settings.max_component_offset,
        settings.steep_faces,
    )
    scene = None if frame is None else scene_around(*frame, points, model.diameter)
    return Query(points, spacing, centroid, r_corr, query_map, keypoints, scene)


class Retrieval(NamedTuple):
    """Stage 2's outcome: the codebook views most similar to the query."""

    views: np.ndarray
    """(k,) viewpoint indices, most similar first."""
    similarity: np.ndarray
    """(k,) cosine similarity of each view's code to the query's."""
    angles: np.ndarray
    """(k,) in-plane angle to each view, radians."""
    code: np.ndarray
    """(D,) the query map's unit code."""


def retrieve(
    query: Query,
    codebook: Codebook,
    encoder: Encoder,
    k: int,
    encoded: tuple[np.ndarray, np.ndarray] | None = None,
) -> Retrieval:
    """Stage 2: the map's code and its ``k`` most similar codebook views, with
    the in-plane angle to each. ``encoded``: the map's ``(code, spectrum)``
    when already encoded (:func:`edgepose.estimate_many` encodes a frame's
    maps at once)."""
    if encoded is None:
        codes, spectra = encoder.encode(query.map[None])
        encoded = codes[0], spectra[0]
    code, spectrum = encoded
    candidates, similarity = _core.top_k(codebook.codes, code, k)
    candidates = candidates.astype(np.intp)
    angles = encoder.in_plane_angles(spectrum, codebook.spectra[candidates]).astype(np.float64)
    return Retrieval(candidates, similarity, angles, code)


def candidate_poses(
    query: Query,
    codebook: Codebook,
    candidates: np.ndarray,
    angles: np.ndarray,
    settings: EstimateSettings = DEFAULT_SETTINGS,
) -> tuple[np.ndarray, np.ndarray]:
    """Stage 3: model frame → camera poses ``(R (k, 3, 3), t (k, 3))``:
    ``R = R_corrᵀ · Rz(θ) · R_view``; the translation from the centroids,
    then moved so the keypoints land on the model."""
    rotations = query.r_corr.T @ rotation_about_z(angles) @ codebook.viewpoints.rotations[candidates]
    translations = query.centroid - np.einsum("kij,kj->ki", rotations, codebook.centroids[candidates])
    if settings.align_iterations > 0:
        translations = codebook.index.align_translations(
            query.keypoints,
            rotations,
            translations,
            settings.align_iterations,
            settings.candidate_inlier_distance * codebook.model.diameter,
        )
    return rotations, translations


def pair_poses(
    query: Query, codebook: Codebook, settings: EstimateSettings = DEFAULT_SETTINGS
) -> tuple[np.ndarray, np.ndarray]:
    """Stage 3 without the codebook's views: poses voted for by pairs of
    oriented points of the query and the model (point-pair features, Rust),
    ``(R (P, 3, 3), t (P, 3))`` model frame → camera, most votes first, at
    most ``settings.pair_poses``. Each pair is local, so they find the
    object when most of it is hidden and the map's code matches no view."""
    rotations, translations, _ = codebook.index.pair_poses(
        query.points, settings.pair_scene_points, settings.pair_reference_stride, settings.pair_poses
    )
    return rotations, translations


def nearest_views(codebook: Codebook, rotations: np.ndarray, translations: np.ndarray) -> np.ndarray:
    """(P,) the codebook viewpoint nearest to the camera's direction in each
    pose (model frame → camera)."""
    towards_camera = -np.einsum("pji,pj->pi", rotations, translations)
    towards_camera /= np.linalg.norm(towards_camera, axis=1, keepdims=True)
    return np.argmax(towards_camera @ codebook.viewpoints.directions.T, axis=1).astype(np.intp)


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
    (inlier fraction minus violations) by ``settings.turn_switch_gain``;
    None otherwise, and for a pose ICP did not refine. Its ``margin`` is
    that gain over ``result``, its ``rmse_ratio`` the search's.
    :func:`edgepose.estimate` asks when the flip margin is below
    ``settings.turn_check_below``."""
    if not result.refined or len(flips.rival.rotations) == 0:
        return None
    d = codebook.model.diameter
    coarse = query.sample(settings.hypothesis_points, settings.subsample_seed)
    icp = codebook.index.refine(
        coarse,
        flips.rival.rotations,
        flips.rival.translations,
        settings.hypothesis_iterations,
        settings.icp_max_distance * d,
    )
    rival: RivalSearch | None = None  # unpolished: the flip margin's rival is found from the pose itself
    if settings.icp_iterations > 0 and icp.inliers[0] >= settings.min_icp_inliers and np.isfinite(icp.rmse[0]):
        fine, rival = polished(query, codebook, icp.rotations[0], icp.translations[0], settings)
        icp = fine if fine is not None else icp
    R, t = icp.rotations, icp.translations
    if not usable_icp(query, codebook, icp.inliers, icp.rmse, t, settings)[0]:
        return None
    scores = score_poses(query, codebook, coarse, R, t, settings.hypothesis_inlier_distance * d, 0.0, settings)
    gain = float(scores.net[0] - result.scores.net[0])
    if gain <= settings.turn_switch_gain:
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
    ``settings.alternative_within`` of the pose's, each more than
    ``RIVAL_DISTANCE`` × d from the pose and from each other (ADD, or ADD-S
    for a symmetric object), best first, at most ``settings.alternatives``.
    Nothing is refined again: they cost a few distances. Empty for a pose
    stage 5 did not refine."""
    found = [Hypotheses(result.R[None], result.t[None], result.scores.net)]
    if settings.alternatives > 0 and result.refined:
        if hypotheses is not None:
            found.append(hypotheses)
        if len(rival.rotations):
            found.append(Hypotheses(rival.rotations, rival.translations, np.array([rival.net])))
    R, t, net = (np.concatenate(column) for column in zip(*found))
    allowed = net >= net[0] - settings.alternative_within
    picked = distinct_poses(codebook, R, t, np.argsort(-net, kind="stable"), allowed, settings.alternatives)
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
    if count == 0 or not allowed[1:].any():  # only pose 0 itself may qualify: no distances needed
        return []
    apart = allowed & (pose_distances(codebook, rotations, translations, 0) > RIVAL_DISTANCE * codebook.model.diameter)
    taken: list[int] = []
    for i in order:
        if len(taken) == count:
            break
        if apart[i]:
            taken.append(int(i))
            apart &= (
                pose_distances(codebook, rotations, translations, int(i)) > RIVAL_DISTANCE * codebook.model.diameter
            )
    return taken


def free_space_tolerance(query: Query, diameter: float, settings: EstimateSettings = DEFAULT_SETTINGS) -> float:
    """How far (metres) a camera-facing model point must stand in front of
    the observed depth to contradict the view: ``settings.free_space_tolerance``
    × ``diameter``, or ``settings.free_space_noise_sigmas`` standard
    deviations of the sensor's depth noise (``settings.depth_noise``) at
    the query's median depth, whichever is larger."""
    a, b, c = settings.depth_noise
    noise = a + b * (query.median_depth - c) ** 2
    return max(settings.free_space_tolerance * diameter, settings.free_space_noise_sigmas * noise)


def score_poses(
    query: Query,
    codebook: Codebook,
    observed: np.ndarray,
    rotations: np.ndarray,
    translations: np.ndarray,
    inlier_distance: float,
    free_space_weight: float,
    settings: EstimateSettings = DEFAULT_SETTINGS,
) -> PoseScores:
    """Stage 4: the terms of each pose against the ``observed`` points (camera
    frame) and the free space of the whole query. ``inlier_distance`` is in metres."""
    d = codebook.model.diameter
    fit, inliers, violation, off_silhouette, constraint, scene = codebook.index.score(
        observed,
        query.free_space,
        np.ascontiguousarray(rotations),
        np.ascontiguousarray(translations),
        inlier_distance,
        free_space_tolerance(query, d, settings),
        settings.free_space_model_stride,
    )
    cost = fit / inlier_distance + free_space_weight * (violation + scene)
    return PoseScores(fit, inliers, violation, cost, off_silhouette, constraint, scene)


def rim_tolerant_violation(
    query: Query, codebook: Codebook, R: np.ndarray, t: np.ndarray, settings: EstimateSettings = DEFAULT_SETTINGS
) -> float:
    """The free-space violation (0–1) of one pose (model frame → camera)
    with one grid cell of slack at the silhouette's edge
    (:attr:`Query.rim_tolerant_free_space`). A real sensor's silhouette is a
    pixel or two off the object (depth and mask registered apart, mixed
    depth at the edge), so a right pose's rim stands just in front of the
    edge cells: that alone must not make it doubtful."""
    violation = codebook.index.score(
        query.points[:1],
        query.rim_tolerant_free_space,
        np.ascontiguousarray(R[None], dtype=np.float64),
        np.ascontiguousarray(t[None], dtype=np.float64),
        settings.hypothesis_inlier_distance * codebook.model.diameter,
        free_space_tolerance(query, codebook.model.diameter, settings),
        settings.free_space_model_stride,
    )[2]
    return float(violation[0])


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
    """Stage 5: coarse ICP from the ``settings.hypotheses`` best distinct
    candidates, each scored again. Hypotheses that explain nearly as many
    points as the best and violate free space little more than the least
    violating compete; the lowest ICP RMSE wins (near ties: :func:`tie_broken`)
    and is polished by a longer ICP. None when no ICP found enough points.

    ``icp_cache`` (a dict kept between calls on the same query and the same
    leading candidates, with the same settings) holds each start's ICP
    results, the polishes of near ties and the chosen one's polish and
    rival search, so a second, wider search does not repeat the first one's."""
    cache: dict = {} if icp_cache is None else icp_cache
    d = codebook.model.diameter
    coarse = query.sample(settings.hypothesis_points, settings.subsample_seed)
    starts = distinct_hypotheses(
        rotations, np.argsort(candidate_cost, kind="stable"), settings.hypotheses, settings.distinct_deg
    )
    max_distance = settings.icp_max_distance * d
    new = [int(s) for s in starts if ("coarse", int(s)) not in cache]
    if new:
        icp = codebook.index.refine(
            coarse,
            rotations[new],
            translations[new],
            settings.hypothesis_iterations,
            max_distance,
            two_cores=settings.coarse_icp_on_two_cores,
        )
        for i, s in enumerate(new):  # ICP runs each start on its own: one at a time is the same
            cache["coarse", s] = (icp.rotations[i], icp.translations[i], icp.inliers[i], icp.rmse[i])
    hyp_R, hyp_t, inliers, rmse = (np.array(x) for x in zip(*(cache["coarse", int(s)] for s in starts)))
    usable = usable_icp(query, codebook, inliers, rmse, hyp_t, settings)
    if not usable.any():
        return None
    inlier_distance = settings.hypothesis_inlier_distance * d
    scores = score_poses(query, codebook, coarse, hyp_R, hyp_t, inlier_distance, 0.0, settings)
    explains = scores.inlier_fraction >= settings.hypothesis_inlier_ratio * scores.inlier_fraction[usable].max()
    free = scores.violation <= scores.violation[usable].min() + settings.hypothesis_free_space_margin
    competing = usable & explains & free
    pick = int(np.argmin(np.where(competing, rmse, np.inf)))
    pick, tie_polish = tie_broken(query, codebook, hyp_R, hyp_t, rmse, competing, pick, starts, settings, cache)
    net = scores.net
    rivals = usable & (pose_distances(codebook, hyp_R, hyp_t, pick) > RIVAL_DISTANCE * d)
    margin = float(net[pick] - net[rivals].max()) if rivals.any() else 1.0
    competitors = rivals & competing
    rmse_ratio = float(rmse[pick] / rmse[competitors].min()) if competitors.any() else 0.0
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


def tie_broken(
    query: Query,
    codebook: Codebook,
    hyp_R: np.ndarray,
    hyp_t: np.ndarray,
    rmse: np.ndarray,
    competing: np.ndarray,
    pick: int,
    starts: np.ndarray,
    settings: EstimateSettings,
    cache: dict,
) -> tuple[int, _core.IcpResults | None]:
    """Stage 5's pick among hypotheses (model frame → camera; ``rmse`` their
    coarse ICP RMSEs) once near ties are broken, and the pick's polish when
    one was made: when ``competing`` rivals of ``pick`` (more than
    ``RIVAL_DISTANCE`` × d away) have an RMSE within
    ``settings.tie_polish_within`` of its, each of them and ``pick`` are
    polished (:func:`polish`) and the lowest polished RMSE of a usable ICP
    wins (the first on equal RMSEs). ``pick`` itself when there is no such
    tie, no polish (``settings.icp_iterations`` 0) or no usable polish. The
    polishes are kept in ``cache`` under the tied ``starts``."""
    if settings.tie_polish_within <= 0 or settings.icp_iterations == 0:
        return pick, None
    d = codebook.model.diameter
    rivals = pose_distances(codebook, hyp_R, hyp_t, pick) > RIVAL_DISTANCE * d
    tied = np.flatnonzero(competing & rivals & (rmse <= rmse[pick] * (1 + settings.tie_polish_within)))
    if not len(tied):
        return pick, None
    tie = np.concatenate([[pick], tied])
    key = ("tie", tuple(int(starts[h]) for h in tie))
    if key not in cache:
        cache[key] = polish(query, codebook, hyp_R[tie], hyp_t[tie], settings)
    fine = cache[key]
    usable = usable_icp(query, codebook, fine.inliers, fine.rmse, fine.translations, settings)
    won = int(np.argmin(np.where(usable, fine.rmse, np.inf))) if usable.any() else 0
    return int(tie[won]), fine.row(won)


#: Hypotheses farther apart than this × d (ADD, or ADD-S for a symmetric
#: object) are different poses: rivals for :attr:`Refined.margin`.
RIVAL_DISTANCE = 0.1
#: Model points (the first, spread ones) that measure distances between poses.
RIVAL_POINTS = 64
#: Keypoint alignment iterations of each turned pose of the flip margin
#: (the candidates take ``settings.align_iterations``) ...
FLIP_ALIGN_ITERATIONS = 1
#: ... and the rival turned poses that screen best, this many, are settled
#: by this many ICP iterations (pairing within ``settings.icp_max_distance``)
#: before they are scored: an unsettled rival that is the truth loses to a
#: polished wrong pose. On stressed views of near-symmetric training parts
#: the margin alone told right from wrong poses at AUROC 0.75 unsettled,
#: 0.80–0.87 settled (2 rivals, 2 iterations), 0.82–0.88 with every rival
#: settled at ~3× the cost; on all stressed training views 0.833 → 0.868,
#: for ~0.2 ms an estimate (``export/README.md``). One rival instead of two:
#: the confidence's cross-validated stressed AUROC the same (0.967 against
#: 0.966), its lap 0.59 → 0.43 ms (median, 288 tuning-part estimates).
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
        # the model, as the candidates are (~0.05 ms); only the best few are
        # then settled by ICP (settling all of them: ~3× the cost). Given an own
        # net of 0, the core's margin is minus the rival's net.
        self._search = codebook.index.flip_margin(
            query.keypoints,
            query.sample(settings.hypothesis_points, settings.subsample_seed),
            query.free_space,
            np.ascontiguousarray(R, dtype=np.float64),
            np.ascontiguousarray(t, dtype=np.float64),
            0.0,
            turn_rotations,
            turn_translations,
            FLIP_ALIGN_ITERATIONS,
            settings.candidate_inlier_distance * d,
            settings.hypothesis_inlier_distance * d,
            free_space_tolerance(query, d, settings),
            settings.free_space_model_stride,
            RIVAL_DISTANCE * d,
            RIVAL_POINTS,
            codebook.symmetry.symmetric,
            FLIP_SETTLED_RIVALS,
            FLIP_SETTLE_ITERATIONS,
            settings.icp_max_distance * d,
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
    ``settings.icp_iterations`` is 0; ``done`` when given, a polish of the
    pose already made: a near tie's) and the search for its turned rival
    (:func:`flip_rival`, from the pose before the polish: the rival is
    settled by ICP anyway), handed to another core before the polish starts
    when ``settings.flip_rival_beside_polish``, else found when first
    asked for (:class:`RivalSearch`)."""
    beside = settings.icp_iterations > 0 and settings.flip_rival_beside_polish
    rival = RivalSearch(query, codebook, R, t, settings, beside=beside)
    if settings.icp_iterations == 0:
        return None, rival
    if done is not None:
        return done, rival
    return polish(query, codebook, R[None], t[None], settings), rival


def polish(
    query: Query, codebook: Codebook, rotations: np.ndarray, translations: np.ndarray, settings: EstimateSettings
) -> _core.IcpResults:
    """The final ICP polish of poses (model frame → camera): ``settings.icp_iterations``
    on ``settings.icp_points`` of the query's points."""
    return codebook.index.refine(
        query.sample(settings.icp_points, settings.subsample_seed + 1),
        rotations,
        translations,
        settings.icp_iterations,
        settings.icp_max_distance * codebook.model.diameter,
    )


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
    model's centre still near the cloud (:func:`near_the_cloud`)."""
    return (
        np.isfinite(rmse)
        & (inliers >= settings.min_icp_inliers)
        & near_the_cloud(query, codebook, translations, settings)
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


def near_the_cloud(
    query: Query, codebook: Codebook, translations: np.ndarray, settings: EstimateSettings = DEFAULT_SETTINGS
) -> np.ndarray:
    """(H,) bool: whether each pose (model frame → camera, ``translations``
    (H, 3) metres: where the model's centre lands) keeps the model's centre
    within ``settings.max_centre_offset`` model radii of the observed centroid."""
    radius = 1.0 / codebook.model.scale
    return np.linalg.norm(translations - query.centroid, axis=1) <= settings.max_centre_offset * radius


def subsample(points: np.ndarray, count: int, seed: int) -> np.ndarray:
    """At most ``count`` of ``points``, drawn without replacement (seeded), C-contiguous."""
    if len(points) > count:
        points = points[_drawn(len(points), count, seed)]
    return np.ascontiguousarray(points)


@lru_cache(maxsize=256)
def _drawn(n: int, count: int, seed: int) -> np.ndarray:
    """The indices :func:`subsample` takes: the same for the same sizes and
    seed, so a tracker's frames of similar size draw them once."""
    drawn = np.random.default_rng(seed).choice(n, count, replace=False)
    drawn.flags.writeable = False
    return drawn


def distinct_hypotheses(rotations: np.ndarray, order: np.ndarray, count: int, min_angle_deg: float) -> np.ndarray:
    """Indices of up to ``count`` of ``rotations`` ((K, 3, 3)), taken in
    ``order``, each at least ``min_angle_deg`` away from those taken before."""
    cos_min = np.cos(np.radians(min_angle_deg))
    kept: list[int] = []
    for j in order:
        # cos of the angle between two rotations: (trace(Raᵀ Rb) − 1) / 2.
        if all((np.einsum("ij,ij->", rotations[j], rotations[k]) - 1) / 2 < cos_min for k in kept):
            kept.append(int(j))
            if len(kept) == count:
                break
    return np.asarray(kept, dtype=np.intp)
