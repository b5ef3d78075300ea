"""Stage 1 of :func:`edgepose.estimate`: the observed cloud made ready for
the codebook (:class:`Query`: the object's points, the viewpoint
correction, the map and its keypoints), and the window of the frame's depth
around the object that the scene test reads (:class:`SceneDepth`).

Camera frame, metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property, lru_cache

import numpy as np

from edgepose import _core
from edgepose.cloud import MIN_POINTS, clean_cloud
from edgepose.codebook import Codebook
from edgepose.settings import DEFAULT_SETTINGS, EstimateSettings


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
    median_depth: float
    """Median z of ``points``, metres (:func:`edgepose.cloud.median_depth`'s
    value): the depth the sensor's noise is read at."""
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
        scene = self.scene
        return _core.DepthGrid(
            self.points,
            self.spacing,
            scene.depth,
            scene.camera,
            scene.radius,
            scene_window=scene.window,
            scene_depth_scale=scene.depth_scale,
        )

    @cached_property
    def rim_tolerant_free_space(self) -> _core.DepthGrid:
        """:attr:`free_space` (without the scene) whose cells at the edge of
        the observed silhouette read the nearest depth within one cell: what
        the doubt's free-space test reads (:func:`rim_tolerant_violation`)."""
        return _core.DepthGrid(self.points, self.spacing, edge_slack=True)

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
    """The whole checked frame (:func:`edgepose.cloud.checked_depth`), not
    copied: ``depth / depth_scale`` metres; 0 or not finite: no measurement."""
    depth_scale: float
    window: tuple[int, int, int, int]
    """Rows ``top..bottom`` and columns ``left..right`` of ``depth`` around
    the object: the pixels the test reads (converted to metres in the core)."""
    camera: tuple[float, float, float, float]
    """(fx, fy, cx, cy) of the frame's pixels."""
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


def _scene_window(
    depth: np.ndarray, K: np.ndarray, depth_scale: float, points: np.ndarray, grow_u: float, grow_v: float
) -> SceneDepth:
    """The window of ``depth`` over the pixel bounding box of ``points``
    (camera frame, in front of it), grown by ``grow_u`` and ``grow_v`` pixels."""
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    z = np.maximum(points[:, 2], 1e-6)
    h, w = depth.shape
    with np.errstate(over="ignore", invalid="ignore"):  # absurd intrinsics: handled by _pixel_span
        u, v = fx * points[:, 0] / z + cx, fy * points[:, 1] / z + cy
        c0, c1 = _pixel_span(u.min() - grow_u, u.max() + grow_u + 1, w)
        r0, r1 = _pixel_span(v.min() - grow_v, v.max() + grow_v + 1, h)
    return SceneDepth(depth, depth_scale, (r0, r1, c0, c1), (fx, fy, cx, cy))


#: How far beyond the observed points (× d) the scene window reaches: a pose
#: the search keeps (its centre within 1.25 model radii of the observed
#: centroid) puts almost all of its model there.
SCENE_MARGIN = 0.75


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
    cleaned = clean_cloud(cloud, codebook.model.diameter, settings.max_cloud_points)
    return query_of_cleaned(cleaned, codebook, settings, frame)


def query_of_cleaned(
    cleaned: np.ndarray,
    codebook: Codebook,
    settings: EstimateSettings = DEFAULT_SETTINGS,
    frame: tuple[np.ndarray, np.ndarray, float] | None = None,
) -> Query:
    """:func:`prepare_query` of points :func:`edgepose.cloud.clean_cloud`
    (or :func:`edgepose.cloud.clean_depth_cloud`) already kept, at most
    ``settings.max_cloud_points`` of them."""
    model = codebook.model
    points, spacing, centroid, r_corr, query_map, keypoints, depth = _core.prepare_query(
        off_support_plane(cleaned, frame, model.diameter, settings),
        model.diameter,
        model.scale,
        codebook.map_points,
        settings.retrieve.keypoints,
        MIN_POINTS,
        settings.segmentation.core() if settings.segment else None,
    )
    scene = None if frame is None else scene_around(*frame, points, model.diameter)
    return Query(points, spacing, centroid, r_corr, query_map, keypoints, depth, scene)


def _pixel_span(lo: float, hi: float, size: int) -> tuple[int, int]:
    """Pixels ``[lo, hi)`` within ``[0, size]``; all of them when a bound is
    not finite (absurd intrinsics put the points at infinity)."""
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return 0, size
    return int(min(max(lo, 0), size)), int(min(max(hi, 0), size))


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
