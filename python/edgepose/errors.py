"""The exceptions edgepose raises. Catch :class:`EdgePoseError` for all of them."""

from __future__ import annotations


class EdgePoseError(Exception):
    """Base class of every error edgepose raises on purpose."""


class InvalidModelError(EdgePoseError, ValueError):
    """An object model (mesh or point cloud) that cannot be used: empty,
    degenerate, non-finite, or of absurd size."""


class MeshLoadError(InvalidModelError):
    """A mesh file that is missing, unreadable, or holds no surface."""


class InvalidCloudError(EdgePoseError, ValueError):
    """An input point cloud of the wrong shape or type, or with too few valid points."""
