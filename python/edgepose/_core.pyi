"""Type stubs of the compiled core (private; use the `edgepose` API)."""

import numpy as np
import numpy.typing as npt

__version__: str

_ModelTuple = tuple[
    npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.float64], float, float, float
]

def standard_model_from_mesh(
    vertices: npt.NDArray[np.float64], faces: npt.NDArray[np.uint32], n_points: int, seed: int
) -> _ModelTuple: ...
def standard_model_from_points(
    points: npt.NDArray[np.float32], normals: npt.NDArray[np.float32], n_points: int
) -> _ModelTuple: ...
def fibonacci_viewpoints(n: int) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]: ...
def view_rotation(direction: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]: ...
def farthest_point_sample(points: npt.NDArray[np.float32], m: int) -> npt.NDArray[np.uint32]: ...
def visible_mask(
    points: npt.NDArray[np.float32], normals: npt.NDArray[np.float32], spacing: float
) -> npt.NDArray[np.bool_]: ...
def compute_maps(
    points: npt.NDArray[np.float32],
    normals: npt.NDArray[np.float32],
    scale: float,
    spacing: float,
    rotations: npt.NDArray[np.float64],
    m: int,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float64], npt.NDArray[np.uint32]]: ...
def normalize_to_map(
    points: npt.NDArray[np.float32], scale: float, m: int
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]: ...
