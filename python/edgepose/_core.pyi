"""Type stubs of the compiled core (private; use the `edgepose` API)."""

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

__version__: str

def fibonacci_viewpoints(n: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
def view_rotation(direction: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]: ...
def farthest_point_sample(points: npt.NDArray[np.float32], m: int) -> npt.NDArray[np.uint32]: ...
def visible_mask(
    points: npt.NDArray[np.float32], normals: npt.NDArray[np.float32], spacing: float
) -> npt.NDArray[np.bool_]: ...
def compute_maps(
    model: StandardModel, rotations: npt.NDArray[np.float64], m: int
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float64], npt.NDArray[np.uint32]]: ...
def keep_work_on_this_thread(keep: bool) -> bool: ...
def normalize_to_map(
    points: npt.NDArray[np.float32], scale: float, m: int
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]: ...
def map_features(
    maps: npt.NDArray[np.float32], centres: int, k: int, harmonics: int
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.float32]]: ...
def top_k(
    codes: npt.NDArray[np.float32], query: npt.NDArray[np.float32], k: int
) -> tuple[npt.NDArray[np.uint32], npt.NDArray[np.float32]]: ...
def box_sides(points: npt.NDArray[np.float32]) -> list[float]: ...
def usable_icp(
    inliers: npt.NDArray[np.uint32],
    rmse: npt.NDArray[np.float64],
    translations: npt.NDArray[np.float64],
    centroid: npt.NDArray[np.float64],
    min_icp_inliers: int,
    max_centre_offset: float,
) -> npt.NDArray[np.bool_]: ...
def distinct_rotations(
    rotations: npt.NDArray[np.float64], order: npt.NDArray[np.int64], count: int, cos_min: float
) -> list[int]: ...
def segment_object(
    cloud: npt.NDArray[np.float32], diameter: float, settings: SegmentSettings
) -> tuple[npt.NDArray[np.bool_], float]: ...
def ray_alignment(centroid: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]: ...
def back_project(
    depth: npt.NDArray[np.uint16] | npt.NDArray[np.float32] | npt.NDArray[np.float64],
    mask: npt.NDArray[np.bool_],
    k: npt.NDArray[np.float64],
    depth_scale: float,
) -> npt.NDArray[np.float64]: ...
def on_support_plane(
    points: npt.NDArray[np.float32],
    depth: npt.NDArray[np.uint16] | npt.NDArray[np.float32] | npt.NDArray[np.float64],
    k: npt.NDArray[np.float64],
    depth_scale: float,
    diameter: float,
) -> npt.NDArray[np.bool_]: ...

class CleanSettings:
    def __init__(
        self,
        *,
        max_points: int,
        seed: int,
        min_points: int,
        max_coordinate: float,
        max_extent_diameters: float,
        min_extent_diameters: float,
    ) -> None: ...

def clean_cloud(
    cloud: npt.NDArray[np.float32] | npt.NDArray[np.float64],
    diameter: float,
    settings: CleanSettings,
) -> npt.NDArray[np.float32]: ...
def clean_depth_cloud(
    depth: npt.NDArray[np.uint16] | npt.NDArray[np.float32] | npt.NDArray[np.float64],
    mask: npt.NDArray[np.bool_],
    k: npt.NDArray[np.float64],
    depth_scale: float,
    diameter: float,
    settings: CleanSettings,
) -> npt.NDArray[np.float32]: ...
def prepare_query(
    points: npt.NDArray[np.float32],
    diameter: float,
    scale: float,
    map_points: int,
    keypoints: int,
    min_points: int,
    segmentation: SegmentSettings | None,
) -> tuple[
    npt.NDArray[np.float32],
    float,
    npt.NDArray[np.float64],
    npt.NDArray[np.float64],
    npt.NDArray[np.float32],
    npt.NDArray[np.float32],
    float,
]: ...

class StandardModel:
    def __init__(
        self,
        points: npt.NDArray[np.float32],
        normals: npt.NDArray[np.float32],
        centre: npt.NDArray[np.float64],
        scale: float,
        diameter: float,
        spacing: float,
    ) -> None: ...
    @staticmethod
    def from_mesh(
        vertices: npt.NDArray[np.float64],
        faces: npt.NDArray[np.uint32],
        n_points: int,
        seed: int,
        source: str = "mesh",
    ) -> StandardModel: ...
    @staticmethod
    def from_points(
        points: npt.NDArray[np.float32], normals: npt.NDArray[np.float32], n_points: int, source: str = "points"
    ) -> StandardModel: ...
    def __len__(self) -> int: ...
    @property
    def points(self) -> npt.NDArray[np.float32]: ...
    @property
    def normals(self) -> npt.NDArray[np.float32]: ...
    @property
    def centre(self) -> npt.NDArray[np.float64]: ...
    @property
    def scale(self) -> float: ...
    @property
    def diameter(self) -> float: ...
    @property
    def spacing(self) -> float: ...

class IcpResults:
    def __len__(self) -> int: ...
    def row(self, index: int) -> IcpResults: ...
    @property
    def rotations(self) -> npt.NDArray[np.float64]: ...
    @property
    def translations(self) -> npt.NDArray[np.float64]: ...
    @property
    def iterations(self) -> npt.NDArray[np.uint32]: ...
    @property
    def converged(self) -> npt.NDArray[np.bool_]: ...
    @property
    def inliers(self) -> npt.NDArray[np.uint32]: ...
    @property
    def rmse(self) -> npt.NDArray[np.float64]: ...

class ScoreResults:
    def __len__(self) -> int: ...
    @property
    def fit(self) -> npt.NDArray[np.float64]: ...
    @property
    def inlier_fraction(self) -> npt.NDArray[np.float64]: ...
    @property
    def free_space_violation(self) -> npt.NDArray[np.float64]: ...
    @property
    def off_silhouette(self) -> npt.NDArray[np.float64]: ...
    @property
    def translation_constraint(self) -> npt.NDArray[np.float64]: ...
    @property
    def scene_violation(self) -> npt.NDArray[np.float64]: ...
    def terms(
        self, inlier_distance: float, free_space_weight: float
    ) -> tuple[
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
        npt.NDArray[np.float64],
    ]: ...

class FlipSettings:
    def __init__(
        self,
        *,
        align_iterations: int,
        align_distance: float,
        inlier_distance: float,
        free_space_tolerance: float,
        model_stride: int,
        rival_distance: float,
        rival_points: int,
        symmetric: bool,
        settled: int,
        settle_iterations: int,
        settle_distance: float,
    ) -> None: ...

class PickRules:
    def __init__(
        self,
        *,
        min_icp_inliers: int,
        max_centre_offset: float,
        inlier_distance: float,
        free_space_tolerance: float,
        model_stride: int,
        inlier_ratio: float,
        free_space_margin: float,
        tie_polish_within: float,
        rival_distance: float,
        rival_points: int,
        symmetric: bool,
    ) -> None: ...

class FlipMarginSearch:
    def result(
        self,
    ) -> tuple[float, npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...

class ConfidenceCurves:
    def __init__(
        self, terms: list[tuple[int, str, float, list[tuple[float, float]]]], intercept: float, evidence: int
    ) -> None: ...
    def probability(self, evidence: list[float]) -> float: ...

class DepthGrid:
    def __init__(
        self,
        cloud: npt.NDArray[np.float32],
        spacing: float,
        scene_depth: npt.NDArray[np.uint16] | npt.NDArray[np.float32] | npt.NDArray[np.float64] | None = None,
        scene_camera: tuple[float, float, float, float] | None = None,
        scene_radius: int = 2,
        edge_slack: bool = False,
        scene_window: tuple[int, int, int, int] | None = None,
        scene_depth_scale: float = 1.0,
    ) -> None: ...

class SegmentSettings:
    def __init__(self, **fields: float | int | bool) -> None: ...
    @property
    def neighbours(self) -> int: ...
    @property
    def outlier_sigmas(self) -> float: ...
    @property
    def cluster_spacings(self) -> float: ...
    @property
    def min_component_fraction(self) -> float: ...
    @property
    def max_component_offset(self) -> float: ...
    @property
    def max_shadowed_fraction(self) -> float: ...
    @property
    def shadow_spacings(self) -> float: ...
    @property
    def occluder_points(self) -> int: ...
    @property
    def occluder_fraction(self) -> float: ...
    @property
    def occluder_margin(self) -> float: ...
    @property
    def steep_faces(self) -> bool: ...
    @property
    def ramp_spacings(self) -> float: ...
    @property
    def ramp_neighbours(self) -> int: ...
    @property
    def ramp_noise(self) -> float: ...
    @property
    def ramp_min_noise_spacings(self) -> float: ...
    @property
    def ramp_link(self) -> float: ...

class TrackFrameSettings:
    def __init__(
        self,
        *,
        icp_iterations: int,
        icp_max_distance: float,
        inlier_distance: float,
        tight_inlier_distance: float,
        model_stride: int,
        diameter: float,
        scene_radius: int,
        scene_margin: float,
    ) -> None: ...

class TrackedFit:
    @property
    def icp(self) -> IcpResults: ...
    @property
    def loose(self) -> ScoreResults: ...
    @property
    def tight(self) -> ScoreResults: ...
    @property
    def sides(self) -> tuple[float, float, float]: ...
    @property
    def with_scene(self) -> bool: ...

class ModelIndex:
    def __init__(self, model: StandardModel) -> None: ...
    def with_model(self, model: StandardModel) -> ModelIndex: ...
    def __len__(self) -> int: ...
    def verify(
        self,
        keypoints: npt.NDArray[np.float32],
        rotations: npt.NDArray[np.float64],
        translations: npt.NDArray[np.float64],
    ) -> npt.NDArray[np.float64]: ...
    def distances(
        self,
        points: npt.NDArray[np.float32],
        rotations: npt.NDArray[np.float64],
        translations: npt.NDArray[np.float64],
        along_normal: bool = False,
        stop_above: float | None = None,
    ) -> npt.NDArray[np.float64]: ...
    def align_translations(
        self,
        observed: npt.NDArray[np.float32],
        rotations: npt.NDArray[np.float64],
        translations: npt.NDArray[np.float64],
        iterations: int,
        max_distance: float,
        two_cores: bool = False,
    ) -> npt.NDArray[np.float64]: ...
    def score(
        self,
        observed: npt.NDArray[np.float32],
        free_space: DepthGrid,
        rotations: npt.NDArray[np.float64],
        translations: npt.NDArray[np.float64],
        inlier_distance: float,
        free_space_tolerance: float,
        model_stride: int,
        two_cores: bool = False,
    ) -> ScoreResults: ...
    def track_frame(
        self,
        points: npt.NDArray[np.float32],
        seen: npt.NDArray[np.float32],
        rotations: npt.NDArray[np.float64],
        translations: npt.NDArray[np.float64],
        free_space_tolerance: float,
        settings: TrackFrameSettings,
        depth: npt.NDArray[np.uint16] | npt.NDArray[np.float32] | npt.NDArray[np.float64] | None = None,
        k: npt.NDArray[np.float64] | None = None,
        depth_scale: float = 1.0,
        box_corners: npt.NDArray[np.float64] | None = None,
    ) -> TrackedFit: ...
    def refine(
        self,
        cloud: npt.NDArray[np.float32],
        rotations: npt.NDArray[np.float64],
        translations: npt.NDArray[np.float64],
        max_iterations: int,
        max_distance: float,
        two_cores: bool = False,
        converged: float = ...,
    ) -> IcpResults: ...
    def distinct_poses(
        self,
        rotations: npt.NDArray[np.float64],
        translations: npt.NDArray[np.float64],
        order: npt.NDArray[np.int64],
        allowed: npt.NDArray[np.bool_],
        count: int,
        rival_distance: float,
        symmetric: bool,
        points: int,
    ) -> list[int]: ...
    def pick_hypothesis(
        self,
        observed: npt.NDArray[np.float32],
        free_space: DepthGrid,
        rotations: npt.NDArray[np.float64],
        translations: npt.NDArray[np.float64],
        inliers: npt.NDArray[np.uint32],
        rmse: npt.NDArray[np.float64],
        centroid: npt.NDArray[np.float64],
        rules: PickRules,
        polish_tie: Callable[[list[int]], IcpResults],
    ) -> tuple[int, IcpResults | None, ScoreResults, npt.NDArray[np.bool_], float, float] | None: ...
    def pose_distances(
        self,
        rotations: npt.NDArray[np.float64],
        translations: npt.NDArray[np.float64],
        reference: int,
        symmetric: bool,
        points: int,
    ) -> npt.NDArray[np.float64]: ...
    def flip_margin(
        self,
        keypoints: npt.NDArray[np.float32],
        observed: npt.NDArray[np.float32],
        free_space: DepthGrid,
        rotation: npt.NDArray[np.float64],
        translation: npt.NDArray[np.float64],
        own_net: float,
        turn_rotations: npt.NDArray[np.float64],
        turn_translations: npt.NDArray[np.float64],
        settings: FlipSettings,
        beside: bool = False,
    ) -> FlipMarginSearch: ...
    def pair_poses(
        self, cloud: npt.NDArray[np.float32], scene_points: int, reference_stride: int, poses: int
    ) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...

# Built with the `test-hooks` cargo feature only (`make build`; never in the wheel).
def _panic_for_tests(message: str, where_: str) -> None: ...
