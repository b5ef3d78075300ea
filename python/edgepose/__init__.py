"""edgepose: 6D pose of unseen objects from a depth point cloud, on a CPU.

Units are metres; camera frames follow OpenCV (x right, y down, z forward);
poses are ``T_cam_obj`` (``p_cam = R @ p_obj + t``).
"""

from __future__ import annotations

from edgepose._core import __version__
from edgepose.cloud import cloud_from_depth
from edgepose.codebook import Codebook, CodebookError, StaleCodebookWarning, build_codebook
from edgepose.confidence import TRUST_THRESHOLD
from edgepose.encoder import Encoder, ModelFilesError
from edgepose.errors import EdgePoseError, InvalidArgumentError, InvalidCloudError, InvalidModelError, MeshLoadError
from edgepose.frame import FramePoses, estimate_many, track_many
from edgepose.maps import Maps, compute_maps, farthest_point_sample, normalize_to_map, visible_mask
from edgepose.model import StandardModel, detect_scale, load_model, model_from_points, read_mesh
from edgepose.pose import Alternative, Pose, estimate
from edgepose.settings import (
    AlternativeSettings,
    EstimateSettings,
    RefineSettings,
    RetrieveSettings,
    ScoreSettings,
    SecondSearchSettings,
    SegmentSettings,
    TurnSettings,
)
from edgepose.symmetry import Symmetry, detect_symmetry
from edgepose.track import Tracker, TrackSettings
from edgepose.views import Viewpoints, fibonacci_viewpoints, view_rotation

__all__ = [
    "__version__",
    "Alternative",
    "AlternativeSettings",
    "Codebook",
    "CodebookError",
    "EdgePoseError",
    "Encoder",
    "EstimateSettings",
    "FramePoses",
    "ModelFilesError",
    "Pose",
    "RefineSettings",
    "RetrieveSettings",
    "ScoreSettings",
    "SecondSearchSettings",
    "SegmentSettings",
    "Symmetry",
    "TRUST_THRESHOLD",
    "TrackSettings",
    "Tracker",
    "TurnSettings",
    "build_codebook",
    "cloud_from_depth",
    "estimate",
    "estimate_many",
    "track_many",
    "InvalidArgumentError",
    "InvalidCloudError",
    "InvalidModelError",
    "MeshLoadError",
    "Maps",
    "StaleCodebookWarning",
    "StandardModel",
    "Viewpoints",
    "compute_maps",
    "detect_scale",
    "detect_symmetry",
    "farthest_point_sample",
    "fibonacci_viewpoints",
    "load_model",
    "model_from_points",
    "normalize_to_map",
    "read_mesh",
    "view_rotation",
    "visible_mask",
]
