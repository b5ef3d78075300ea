from __future__ import annotations

from pathlib import Path

import edgepose
import numpy as np
import pytest
from edgepose.model import read_mesh

#: The example object shipped inside the package: its mesh and codebook.
SHIPPED = Path(edgepose.__file__).resolve().parent / "codebooks"

#: Shared benchmark data beside the checkout (see ../shared/data/README.md).
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def ycb_dir() -> Path:
    path = SHARED_DATA / "ycb"
    if not path.is_dir():
        pytest.skip(f"shared YCB meshes not found at {path}")
    return path


@pytest.fixture(scope="session")
def train_shapes_dir() -> Path:
    """The shared training meshes the exporter reads (blobs and CAD parts)."""
    path = SHARED_DATA / "train_shapes"
    if not (path / "cad").is_dir():
        pytest.skip(f"shared training meshes not found at {path}")
    return path


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def drill():
    """The shipped power drill (asymmetric): its mesh (metres) and its shipped
    codebook, loaded once per session from the package, so the core suite
    needs nothing beside the checkout."""
    mesh = read_mesh(SHIPPED / "power_drill.ply")
    return mesh, edgepose.Codebook.load(SHIPPED / "power_drill.codebook")
