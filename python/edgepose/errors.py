"""The exceptions edgepose raises. Catch :class:`EdgePoseError` for all of them.

``CodebookError`` (in :mod:`edgepose.codebook`) and ``ModelFilesError`` (in
:mod:`edgepose.encoder`) are EdgePoseErrors too, exported by the package.
"""

from __future__ import annotations

import os
from pathlib import Path


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


def checked_path(value: object, name: str = "path") -> Path:
    """``value`` as a ``Path``; ``InvalidArgumentError`` naming ``name`` if it
    is not a ``str`` or ``os.PathLike`` (``None``, bytes, a number, an array)."""
    if not isinstance(value, (str, os.PathLike)):
        raise InvalidArgumentError(f"{name} must be a file path (str or os.PathLike), got {value!r:.80}")
    return Path(value)
