"""Every pose method the evaluations compare, by name: the one registry behind
``edgepose eval --methods``, :mod:`edgepose.catalog` and ``benches/bench_pose.py``.

Each entry has a constructor (a :class:`~edgepose.eval.baselines.PoseMethod`
whose ``name`` is the entry's) and a one-line description for reports. The
peers need the ``baselines`` extra: their constructors raise ImportError
without it (this module imports neither Open3D nor OpenCV).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from edgepose.eval.baselines import EdgePoseMethod, Open3DBaseline, OpenCVPPFBaseline, PoseMethod
from edgepose.views import DEFAULT_VIEWS


@dataclass(frozen=True)
class MethodSpec:
    """A registered pose method."""

    name: str
    construct: Callable[[], PoseMethod]
    description: str
    """One line for reports (the benchmark's method list)."""

    def create(self) -> PoseMethod:
        """A new instance, named after the entry."""
        method = self.construct()
        method.name = self.name
        return method


METHODS: dict[str, MethodSpec] = {
    spec.name: spec
    for spec in (
        MethodSpec(
            "edgepose",
            EdgePoseMethod,
            f"codebook of {DEFAULT_VIEWS:,} views; segmentation of the cloud (outliers, spill), encoder + IRR, "
            "candidate translations aligned, "
            "truncated-fit + free-space scoring, ICP of the best distinct candidates (settings below)",
        ),
        MethodSpec(
            "edgepose-frame",
            lambda: EdgePoseMethod(uses_frame=True),
            "edgepose given the view's whole depth frame too (estimate(cloud, codebook, depth=, K=)): poses "
            "are also checked against the scene around the object",
        ),
        MethodSpec(
            "edgepose-norefine",
            lambda: EdgePoseMethod(refine=False),
            "the same without ICP (estimate(..., refine=False)): the verified codebook pose alone",
        ),
        MethodSpec(
            "open3d",
            Open3DBaseline,
            "Open3D FPFH + RANSAC (mutual filter, edge-length 0.9 + distance checks, 1-voxel gate, ≤100k "
            "iterations, confidence 0.9999) + point-to-plane ICP on the mesh normals; voxel = diameter/25; "
            "2 OpenMP threads",
        ),
        MethodSpec(
            "opencv-ppf",
            OpenCVPPFBaseline,
            "OpenCV ppf_match_3d (Drost PPF): sampling step 0.07, distance step 0.05, scene sample step 1/20, "
            "scene distance 0.05; ICP on the 5 best-voted poses, lowest residual wins; model in mm",
        ),
        MethodSpec(
            "opencv-ppf-fast",
            lambda: OpenCVPPFBaseline(relative_sampling_step=0.1, scene_sample_step=1 / 10),
            "the same with sampling step 0.1, scene sample step 1/10 (trains in < 1 s)",
        ),
    )
}


def create_method(name: str) -> PoseMethod:
    """A new instance of the method registered as ``name`` (KeyError if none)."""
    return METHODS[name].create()


def parse_methods(text: str) -> list[str]:
    """Method names of a comma-separated list, checked against the registry
    (ValueError naming the unknown ones and the choices)."""
    chosen = [m.strip() for m in text.split(",") if m.strip()]
    unknown = [m for m in chosen if m not in METHODS]
    if unknown or not chosen:
        raise ValueError(f"unknown methods {unknown}; choose from {', '.join(METHODS)}")
    return chosen
