"""The exceptions edgepose raises. Catch :class:`EdgePoseError` for all of them.

``CodebookError`` (in :mod:`edgepose.codebook`) and ``ModelFilesError`` (in
:mod:`edgepose.encoder`) are EdgePoseErrors too, exported by the package.
"""

from __future__ import annotations


class EdgePoseError(Exception):
    """Base class of every error edgepose raises on purpose."""


class InvalidModelError(EdgePoseError, ValueError):
    """An object model (mesh or point cloud) that cannot be used: empty,
    degenerate, flat, non-finite, or of absurd size."""


class MeshLoadError(InvalidModelError):
    """A mesh file that is missing, unreadable, or holds no surface."""


class InvalidCloudError(EdgePoseError, ValueError):
    """An input point cloud of the wrong shape or type, with too few valid
    points, or whose size does not fit the object (e.g. millimetres)."""


class InvalidArgumentError(EdgePoseError, TypeError):
    """An argument of the wrong type (``None`` for a codebook, a path where a
    loaded codebook is expected, settings of another class), named in the message."""


class InternalError(EdgePoseError, RuntimeError):
    """A bug inside edgepose, e.g. a panic in the Rust core, caught before it
    could abort the process. The message says where; please report it."""
