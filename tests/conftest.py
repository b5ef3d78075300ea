from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

#: Shared benchmark data beside the checkout (see ../shared/data/README.md).
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def ycb_dir() -> Path:
    path = SHARED_DATA / "ycb"
    if not path.is_dir():
        pytest.skip(f"shared YCB meshes not found at {path}")
    return path


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)
