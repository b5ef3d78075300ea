"""Evaluation toolkit: pose error metrics (ADD, ADD-S, ADD(-S), AUC),
synthetic depth views with known poses, and BOP results files.

Units are metres; camera frames follow OpenCV (x right, y down, z forward);
poses are ``T_cam_obj`` (``p_cam = R @ p_obj + t``).
"""

from __future__ import annotations

from edgepose.eval.bop import YCBV_OBJ_ID, BopRow, append_bop_csv, read_bop_csv, write_bop_csv
from edgepose.eval.metrics import (
    YCB_SYMMETRIC,
    PoseErrors,
    add,
    add_or_s,
    add_s,
    auc,
    pose_errors,
    rotation_error_deg,
    translation_error_mm,
)
from edgepose.eval.render import (
    LINEMOD_CAMERA,
    Camera,
    RenderedView,
    depth_to_cloud,
    random_pose,
    render_view,
)
from edgepose.eval.scenes import SceneView, render_scene
from edgepose.eval.stress import STRESS_LEVELS, Stress

__all__ = [
    "LINEMOD_CAMERA",
    "YCB_SYMMETRIC",
    "YCBV_OBJ_ID",
    "BopRow",
    "Camera",
    "PoseErrors",
    "RenderedView",
    "STRESS_LEVELS",
    "SceneView",
    "Stress",
    "add",
    "add_or_s",
    "add_s",
    "append_bop_csv",
    "auc",
    "depth_to_cloud",
    "pose_errors",
    "random_pose",
    "read_bop_csv",
    "render_scene",
    "render_view",
    "rotation_error_deg",
    "translation_error_mm",
    "write_bop_csv",
]
