"""Peer pose estimators behind one interface, for side-by-side benchmarks.

- :class:`Open3DBaseline`: FPFH features + RANSAC on feature matches +
  point-to-plane ICP (Open3D's global-registration recipe).
- :class:`OpenCVPPFBaseline`: point-pair-feature voting (Drost et al. 2010,
  OpenCV ``surface_matching``) + OpenCV's ICP.
- :class:`EdgePoseMethod`: edgepose itself (``build_codebook`` / ``estimate``),
  wrapped the same way.

The peers need the optional ``baselines`` extra (``open3d``,
``opencv-contrib-python-headless``); they are imported on first use, so this
module imports without them.

Units are metres; camera frames follow OpenCV (x right, y down, z forward).
Every method returns ``T_cam_obj`` (4x4 float64) in the *original* mesh frame
(file units converted to metres as :func:`edgepose.load_model` does).
When a method finds no pose at all it returns :data:`NO_POSE` (identity, which
puts the object at the camera centre) rather than raising, so the metrics count
it as a miss; invalid inputs (wrong shape, too few points) still raise.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

import edgepose
from edgepose.cloud import as_cloud
from edgepose.model import DEFAULT_MODEL_POINTS, StandardModel

if TYPE_CHECKING:
    import trimesh

#: What a method returns when it finds no pose: identity (object at the camera centre).
NO_POSE: np.ndarray = np.eye(4)
NO_POSE.setflags(write=False)

#: Fewest valid scene points a peer accepts.
MIN_SCENE_POINTS = 16


@runtime_checkable
class PoseMethod(Protocol):
    """A pose estimator for one object at a time."""

    name: str

    def prepare(self, mesh: trimesh.Trimesh) -> None:
        """Per-object preparation (model sampling, features, training).
        ``mesh`` is in file units (metres, or millimetres detected by size)."""
        ...

    def estimate(self, cloud: np.ndarray) -> np.ndarray:
        """``T_cam_obj`` (4x4 float64, original mesh frame) of the prepared
        object from its segmented cloud ((N, 3) metres, camera frame)."""
        ...


@dataclass
class LastRun:
    """Diagnostics of the most recent :meth:`estimate` call."""

    found: bool = False
    """False when the method returned :data:`NO_POSE`."""
    score: float = 0.0
    """Method-specific confidence: inlier fitness (Open3D), votes (PPF)."""
    timings: dict[str, float] = field(default_factory=dict)
    """Seconds per stage."""
    confidence: float = float("nan")
    """Probability that the pose is correct (edgepose's ``Pose.confidence``; NaN for the peers)."""
    strict_threshold: float = float("nan")
    """edgepose's ``Pose.strict_threshold`` (NaN for the peers)."""
    alternatives: tuple[np.ndarray, ...] = ()
    """``T_cam_obj`` (4x4) of each of edgepose's ``Pose.alternatives`` (none for the peers)."""


class Open3DBaseline:
    """Open3D global registration: voxel downsampling, FPFH, RANSAC on mutual
    feature matches (edge-length and distance checks), then point-to-plane ICP.

    The scene is registered onto the model (whose normals come from the mesh),
    and the result inverted into ``T_cam_obj``. Voxel size, feature radii
    (normals 2, FPFH 5 voxels) and the RANSAC and ICP distance gates (in
    voxels) scale with the object's diameter. Open3D's OpenMP pool is set to
    ``threads``; with a fixed ``seed`` repeated calls give the same pose.

    Tuning (100 views of five YCB objects): a RANSAC gate of 1 voxel and
    confidence 0.9999 pass ADD(-S) on ~10 % more views than the tutorial's 1.5
    voxels and 0.999, at ~15 % more time; a finer voxel (diameter/30) gains
    nothing. The remaining misses are near-symmetric flips that fit the visible
    surface (small ADD-S, large ADD).
    """

    name = "open3d-fpfh-ransac"

    def __init__(
        self,
        *,
        voxel_ratio: float = 1 / 25,
        model_points: int = DEFAULT_MODEL_POINTS,
        ransac_distance: float = 1.0,
        icp_distance: float = 1.0,
        ransac_iterations: int = 100_000,
        ransac_confidence: float = 0.9999,
        icp_iterations: int = 30,
        threads: int = 2,
        seed: int = 0,
    ) -> None:
        self.voxel_ratio = voxel_ratio
        self.model_points = model_points
        self.ransac_distance = ransac_distance
        self.icp_distance = icp_distance
        self.ransac_iterations = ransac_iterations
        self.ransac_confidence = ransac_confidence
        self.icp_iterations = icp_iterations
        self.threads = threads
        self.seed = seed
        self.last = LastRun()
        self._model: StandardModel | None = None
        _open3d(threads)  # import now, so prepare() times only the preparation

    def prepare(self, mesh: trimesh.Trimesh) -> None:
        """Sample the model surface, downsample it to the voxel size, and
        compute its FPFH features (model frame = original mesh frame, metres)."""
        o3d = _open3d(self.threads)
        model = edgepose.load_model(mesh, n_points=self.model_points)
        self._model = model
        self.voxel = model.diameter * self.voxel_ratio
        full = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model.mesh_points))
        full.normals = o3d.utility.Vector3dVector(model.normals.astype(np.float64))
        self._model_full = full
        self._model_down = _normalised(full.voxel_down_sample(self.voxel))
        self._model_fpfh = self._fpfh(self._model_down)

    def estimate(self, cloud: np.ndarray) -> np.ndarray:
        o3d = _open3d(self.threads)
        reg = o3d.pipelines.registration
        if self._model is None:
            raise RuntimeError(f"{self.name}: call prepare(mesh) first")
        self.last = LastRun()
        t0 = time.perf_counter()
        points = _finite_points(cloud)
        scene = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        down = scene.voxel_down_sample(self.voxel)
        if len(down.points) < MIN_SCENE_POINTS:
            return NO_POSE.copy()
        down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * self.voxel, max_nn=30))
        down.orient_normals_towards_camera_location(np.zeros(3))
        fpfh = self._fpfh(down)
        t1 = time.perf_counter()

        o3d.utility.random.seed(self.seed)
        gate = self.ransac_distance * self.voxel
        coarse = reg.registration_ransac_based_on_feature_matching(
            down,
            self._model_down,
            fpfh,
            self._model_fpfh,
            True,
            gate,
            reg.TransformationEstimationPointToPoint(False),
            3,
            [
                reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                reg.CorrespondenceCheckerBasedOnDistance(gate),
            ],
            reg.RANSACConvergenceCriteria(self.ransac_iterations, self.ransac_confidence),
        )
        t2 = time.perf_counter()
        if len(coarse.correspondence_set) < 3:
            self.last.timings = {"features": t1 - t0, "ransac": t2 - t1}
            return NO_POSE.copy()

        # Refine the downsampled scene onto the full model surface (mesh normals).
        fine = reg.registration_icp(
            down,
            self._model_full,
            self.icp_distance * self.voxel,
            coarse.transformation,
            reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(max_iteration=self.icp_iterations),
        )
        T_obj_cam = fine.transformation if len(fine.correspondence_set) >= 3 else coarse.transformation
        t3 = time.perf_counter()
        self.last = LastRun(
            found=True,
            score=float(fine.fitness),
            timings={"features": t1 - t0, "ransac": t2 - t1, "icp": t3 - t2},
        )
        return _invert(np.asarray(T_obj_cam, dtype=np.float64))

    def _fpfh(self, cloud: Any) -> Any:
        o3d = _open3d(self.threads)
        return o3d.pipelines.registration.compute_fpfh_feature(
            cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * self.voxel, max_nn=100)
        )


class OpenCVPPFBaseline:
    """OpenCV's point-pair-feature detector (``cv2.ppf_match_3d``) and ICP.

    Trained on the standard model (points + mesh normals), centred, in
    millimetres (``units_per_metre``): in metres the same settings lose
    accuracy (OpenCV's normal fitting and ICP have absolute tolerances).
    Scene normals are fitted by OpenCV from ``normal_neighbours`` points and
    flipped towards the camera. The ``refine_top`` best-voted poses are
    refined by ICP and the one with the lowest ICP residual wins.

    Training time grows steeply as ``relative_sampling_step`` shrinks (OpenCV's
    PPF hash table chains collide on smooth surfaces): on the YCB mustard
    bottle about 0.3 s at 0.1, 30 s at 0.07 and 80–100 s at 0.05 (2 cores).
    The default 0.07 is the finest step that trains in tens of seconds.
    OpenCV's matcher runs on one thread in the pip wheels.
    """

    name = "opencv-ppf"

    def __init__(
        self,
        *,
        relative_sampling_step: float = 0.07,
        relative_distance_step: float = 0.05,
        scene_sample_step: float = 1 / 20,
        scene_distance: float = 0.05,
        model_points: int = DEFAULT_MODEL_POINTS,
        normal_neighbours: int = 12,
        refine_top: int = 5,
        icp_iterations: int = 50,
        units_per_metre: float = 1000.0,
        threads: int = 2,
    ) -> None:
        self.relative_sampling_step = relative_sampling_step
        self.relative_distance_step = relative_distance_step
        self.scene_sample_step = scene_sample_step
        self.scene_distance = scene_distance
        self.model_points = model_points
        self.normal_neighbours = normal_neighbours
        self.refine_top = refine_top
        self.icp_iterations = icp_iterations
        self.units_per_metre = units_per_metre
        self.threads = threads
        self.last = LastRun()
        self._detector: Any = None
        _opencv(threads)  # import now, so prepare() times only the training

    def prepare(self, mesh: trimesh.Trimesh) -> None:
        """Train the PPF hash table on the centred standard model."""
        cv2 = _opencv(self.threads)
        model = edgepose.load_model(mesh, n_points=self.model_points)
        self._model = model
        self._model_pc = np.ascontiguousarray(
            np.hstack([model.points * self.units_per_metre, model.normals]), dtype=np.float32
        )
        self._detector = cv2.ppf_match_3d_PPF3DDetector(self.relative_sampling_step, self.relative_distance_step)
        self._detector.trainModel(self._model_pc)
        # p_model = p_mesh - centre (metres): the model-from-mesh transform.
        self._T_model_mesh = np.eye(4)
        self._T_model_mesh[:3, 3] = -model.centre

    def estimate(self, cloud: np.ndarray) -> np.ndarray:
        cv2 = _opencv(self.threads)
        if self._detector is None:
            raise RuntimeError(f"{self.name}: call prepare(mesh) first")
        self.last = LastRun()
        t0 = time.perf_counter()
        points = _finite_points(cloud) * self.units_per_metre
        if len(points) < MIN_SCENE_POINTS:
            return NO_POSE.copy()
        _, scene = cv2.ppf_match_3d.computeNormalsPC3d(
            np.ascontiguousarray(points, dtype=np.float32), self.normal_neighbours, True, (0.0, 0.0, 0.0)
        )
        t1 = time.perf_counter()
        results = self._detector.match(scene, self.scene_sample_step, self.scene_distance)
        t2 = time.perf_counter()
        if not results:
            self.last.timings = {"normals": t1 - t0, "match": t2 - t1}
            return NO_POSE.copy()
        candidates = list(results[: self.refine_top])
        icp = cv2.ppf_match_3d_ICP(self.icp_iterations)
        _, refined = icp.registerModelToScene(self._model_pc, scene, candidates)
        best = min(refined, key=lambda p: p.residual)
        t3 = time.perf_counter()
        self.last = LastRun(
            found=True,
            score=float(best.numVotes),
            timings={"normals": t1 - t0, "match": t2 - t1, "icp": t3 - t2},
        )
        T_cam_model = np.array(best.pose, dtype=np.float64)
        T_cam_model[:3, 3] /= self.units_per_metre
        return T_cam_model @ self._T_model_mesh


class EdgePoseMethod:
    """edgepose itself: ``build_codebook(mesh)`` to prepare, ``estimate(cloud,
    codebook).matrix`` per view. Available once the package exposes both."""

    name = "edgepose"

    def __init__(self, uses_frame: bool = False, **estimate_options: Any) -> None:
        if not available_edgepose():
            raise RuntimeError("this edgepose has no build_codebook()/estimate() yet")
        self.uses_frame = uses_frame
        """Whether the benchmark hands it each view's depth frame too
        (``estimate(cloud, codebook, depth=, K=)``)."""
        self.estimate_options = estimate_options
        self.last = LastRun()
        self._codebook: Any = None

    def prepare(self, mesh: trimesh.Trimesh) -> None:
        self._codebook = edgepose.build_codebook(mesh)  # type: ignore[attr-defined]

    def estimate(self, cloud: np.ndarray, frame: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """``frame``: the view's (depth (H, W) metres, K); the benchmark gives
        it only to a method that ``uses_frame``."""
        if self._codebook is None:
            raise RuntimeError(f"{self.name}: call prepare(mesh) first")
        scene: dict[str, Any] = {} if frame is None else {"depth": frame[0], "K": frame[1], "depth_scale": 1.0}
        pose = edgepose.estimate(cloud, self._codebook, **self.estimate_options, **scene)  # type: ignore[attr-defined]
        timings = getattr(pose, "timings", None)
        self.last = LastRun(
            found=True,
            score=float(getattr(pose, "score", 0.0)),
            timings=dict(timings) if isinstance(timings, dict) else {},
            confidence=float(getattr(pose, "confidence", float("nan"))),
            strict_threshold=float(getattr(pose, "strict_threshold", float("nan"))),
            alternatives=tuple(a.matrix for a in getattr(pose, "alternatives", ())),
        )
        return np.asarray(pose.matrix, dtype=np.float64)


def available_edgepose() -> bool:
    """Whether this edgepose build can estimate poses (codebooks + estimate)."""
    return hasattr(edgepose, "estimate") and hasattr(edgepose, "build_codebook")


def _finite_points(cloud: np.ndarray) -> np.ndarray:
    """(N, 3) float64 C-contiguous valid points of ``cloud`` (metres, camera
    frame), as :func:`edgepose.cloud.as_cloud` reads them; however few remain
    (a peer answers too few with NO_POSE rather than an error)."""
    return np.ascontiguousarray(as_cloud(cloud, min_points=0))


def _normalised(cloud: Any) -> Any:
    """Voxel averaging shortens normals; make them unit again."""
    cloud.normalize_normals()
    return cloud


def _invert(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    inverse = np.eye(4)
    inverse[:3, :3] = R.T
    inverse[:3, 3] = -R.T @ t
    return inverse


_threads_set: dict[str, int] = {}


def _open3d(threads: int) -> Any:
    """The ``open3d`` module, its OpenMP pool limited to ``threads``."""
    import open3d as o3d

    if _threads_set.get("open3d") != threads:
        o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
        _set_openmp_threads(threads)
        _threads_set["open3d"] = threads
    return o3d


def _opencv(threads: int) -> Any:
    """The ``cv2`` module with ``ppf_match_3d``, its thread pool set to ``threads``."""
    import cv2

    if not hasattr(cv2, "ppf_match_3d_PPF3DDetector"):
        raise ImportError("this OpenCV has no ppf_match_3d: install opencv-contrib-python-headless")
    if _threads_set.get("cv2") != threads:
        cv2.setNumThreads(threads)
        _threads_set["cv2"] = threads
    return cv2


def _set_openmp_threads(threads: int) -> None:
    """Limit GNU OpenMP (Open3D's runtime) for parallel regions started from
    this thread; a no-op when libgomp is not loaded."""
    name = ctypes.util.find_library("gomp") or "libgomp.so.1"
    try:
        ctypes.CDLL(name, mode=os.RTLD_NOLOAD | os.RTLD_GLOBAL).omp_set_num_threads(threads)
    except (OSError, AttributeError):
        pass
