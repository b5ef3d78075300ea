//! pyo3 bindings: the private `edgepose._core` module. Thin by design: it
//! checks shapes, borrows numpy buffers without copying, releases the GIL
//! for the Rust work, and turns errors into `ValueError`. The public, typed
//! API is the Python package around it.

use numpy::ndarray::Array;
use numpy::{IntoPyArray, PyUntypedArrayMethods, PyArray1, PyArray2, PyArray3, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::error::GeometryError;
use crate::views::Rotation;
use crate::{maps, model, sampling, views, visibility, Point3};

fn value_error(e: GeometryError) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// Borrows an (N, 3) C-contiguous array as N triples, without copying.
fn triples<'a, T: numpy::Element>(array: &'a PyReadonlyArray2<'_, T>, name: &str) -> PyResult<&'a [[T; 3]]> {
    let shape = array.shape();
    if shape[1] != 3 {
        return Err(PyValueError::new_err(format!("{name} must have shape (N, 3), got {shape:?}")));
    }
    let flat = array
        .as_slice()
        .map_err(|_| PyValueError::new_err(format!("{name} must be C-contiguous")))?;
    Ok(flat.as_chunks::<3>().0)
}

fn rotations_from(array: &PyReadonlyArray3<'_, f64>) -> PyResult<Vec<Rotation>> {
    let shape = array.shape();
    if shape[1] != 3 || shape[2] != 3 {
        return Err(PyValueError::new_err(format!("rotations must have shape (V, 3, 3), got {shape:?}")));
    }
    let flat = array.as_slice().map_err(|_| PyValueError::new_err("rotations must be C-contiguous"))?;
    Ok(flat.chunks_exact(9).map(Rotation::from_row_slice).collect())
}

fn points_array<'py>(py: Python<'py>, points: Vec<Point3>) -> Bound<'py, PyArray2<f32>> {
    let n = points.len();
    Array::from_shape_vec((n, 3), points.into_flattened()).expect("n × 3 elements").into_pyarray(py)
}

/// Standard model of a triangle mesh (vertices in metres):
/// `(points, normals, centre, scale, diameter, spacing)`.
#[pyfunction]
fn standard_model_from_mesh<'py>(
    py: Python<'py>,
    vertices: PyReadonlyArray2<'py, f64>,
    faces: PyReadonlyArray2<'py, u32>,
    n_points: usize,
    seed: u64,
) -> PyResult<Bound<'py, PyAny>> {
    let v = triples(&vertices, "vertices")?;
    let f = triples(&faces, "faces")?;
    let m = py.detach(|| model::StandardModel::from_mesh(v, f, n_points, seed)).map_err(value_error)?;
    model_tuple(py, m)
}

/// Standard model of surface points with normals (metres), same tuple as
/// `standard_model_from_mesh`.
#[pyfunction]
fn standard_model_from_points<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f32>,
    normals: PyReadonlyArray2<'py, f32>,
    n_points: usize,
) -> PyResult<Bound<'py, PyAny>> {
    let p = triples(&points, "points")?;
    let n = triples(&normals, "normals")?;
    let m = py.detach(|| model::StandardModel::from_points(p, n, n_points)).map_err(value_error)?;
    model_tuple(py, m)
}

fn model_tuple<'py>(py: Python<'py>, m: model::StandardModel) -> PyResult<Bound<'py, PyAny>> {
    let centre = PyArray1::from_vec(py, m.centre.to_vec());
    (points_array(py, m.points), points_array(py, m.normals), centre, m.scale, m.diameter, m.spacing)
        .into_pyobject(py)
        .map(|t| t.into_any())
}

/// `n` Fibonacci-sphere viewpoints: `(directions (n, 3), rotations (n, 3, 3))`.
#[pyfunction]
fn fibonacci_viewpoints(py: Python<'_>, n: usize) -> (Bound<'_, PyArray2<f64>>, Bound<'_, PyArray3<f64>>) {
    let (directions, rotations) = py.detach(|| views::viewpoints(n));
    let d: Vec<f64> = directions.iter().flat_map(|d| [d.x, d.y, d.z]).collect();
    let r: Vec<f64> = rotations.iter().flat_map(|r| r.transpose().as_slice().to_vec()).collect();
    (
        Array::from_shape_vec((n, 3), d).expect("n × 3").into_pyarray(py),
        Array::from_shape_vec((n, 3, 3), r).expect("n × 3 × 3").into_pyarray(py),
    )
}

/// Farthest-point sampling: indices of `m` points of an (N, 3) cloud.
#[pyfunction]
fn farthest_point_sample<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f32>,
    m: usize,
) -> PyResult<Bound<'py, PyArray1<u32>>> {
    let p = triples(&points, "points")?;
    let idx = py.detach(|| sampling::farthest_point_sample(p, m));
    Ok(PyArray1::from_vec(py, idx))
}

/// Visibility flags of view-frame points and normals (camera looks along +z).
#[pyfunction]
fn visible_mask<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f32>,
    normals: PyReadonlyArray2<'py, f32>,
    spacing: f32,
) -> PyResult<Bound<'py, PyArray1<bool>>> {
    let p = triples(&points, "points")?;
    let n = triples(&normals, "normals")?;
    if p.len() != n.len() {
        return Err(PyValueError::new_err("points and normals differ in length"));
    }
    Ok(PyArray1::from_vec(py, py.detach(|| visibility::visible_mask(p, n, spacing))))
}

/// Maps of every viewpoint, in parallel:
/// `(maps (V, m, 3) f32, centroids (V, 3) f64, visible (V,) u32)`.
#[allow(clippy::too_many_arguments)]
#[pyfunction]
fn compute_maps<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f32>,
    normals: PyReadonlyArray2<'py, f32>,
    scale: f64,
    spacing: f64,
    rotations: PyReadonlyArray3<'py, f64>,
    m: usize,
) -> PyResult<Bound<'py, PyAny>> {
    let p = triples(&points, "points")?;
    let n = triples(&normals, "normals")?;
    if p.len() != n.len() || p.is_empty() {
        return Err(PyValueError::new_err("model points and normals must be non-empty and equal in length"));
    }
    let rots = rotations_from(&rotations)?;
    let model = model::StandardModel {
        points: p.to_vec(),
        normals: n.to_vec(),
        centre: [0.0; 3],
        scale,
        diameter: 0.0,
        spacing,
    };
    let out = py.detach(|| maps::compute_maps(&model, &rots, m));
    let v = rots.len();
    let map_points = Array::from_shape_vec((v, m, 3), out.points.into_flattened()).expect("V × m × 3");
    let centroids = Array::from_shape_vec((v, 3), out.centroids.into_flattened()).expect("V × 3");
    (map_points.into_pyarray(py), centroids.into_pyarray(py), PyArray1::from_vec(py, out.visible))
        .into_pyobject(py)
        .map(|t| t.into_any())
}

/// Centre, scale and resample a cloud to an `m`-point map: `(map (m, 3), centroid (3,))`.
#[pyfunction]
fn normalize_to_map<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f32>,
    scale: f32,
    m: usize,
) -> PyResult<(Bound<'py, PyArray2<f32>>, Bound<'py, PyArray1<f32>>)> {
    let p = triples(&points, "points")?;
    if p.is_empty() {
        return Err(PyValueError::new_err("cloud is empty"));
    }
    let (map, centroid) = py.detach(|| maps::normalize_to_map(p, scale, m));
    Ok((points_array(py, map), PyArray1::from_vec(py, centroid.to_vec())))
}

/// Rotation object → view frame for one direction (object frame, towards the camera).
#[pyfunction]
fn view_rotation<'py>(py: Python<'py>, direction: PyReadonlyArray1<'py, f64>) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let d = direction.as_slice().map_err(|_| PyValueError::new_err("direction must be contiguous"))?;
    if d.len() != 3 || !d.iter().all(|v| v.is_finite()) || d.iter().all(|v| *v == 0.0) {
        return Err(PyValueError::new_err("direction must be 3 finite values, not all zero"));
    }
    let r = views::view_rotation(&nalgebra::Vector3::new(d[0], d[1], d[2]));
    Ok(Array::from_shape_vec((3, 3), r.transpose().as_slice().to_vec()).expect("3 × 3").into_pyarray(py))
}

#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_function(wrap_pyfunction!(standard_model_from_mesh, m)?)?;
    m.add_function(wrap_pyfunction!(standard_model_from_points, m)?)?;
    m.add_function(wrap_pyfunction!(fibonacci_viewpoints, m)?)?;
    m.add_function(wrap_pyfunction!(farthest_point_sample, m)?)?;
    m.add_function(wrap_pyfunction!(visible_mask, m)?)?;
    m.add_function(wrap_pyfunction!(compute_maps, m)?)?;
    m.add_function(wrap_pyfunction!(normalize_to_map, m)?)?;
    m.add_function(wrap_pyfunction!(view_rotation, m)?)?;
    Ok(())
}
