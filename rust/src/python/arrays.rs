//! numpy ↔ Rust conversions of the bindings: borrowed views of C-contiguous
//! input arrays, and owned output arrays. Shape problems come back as a
//! message for the caller to raise as the right exception.

use nalgebra::Vector3;
use numpy::ndarray::Array;
use numpy::{
    IntoPyArray, PyArray2, PyArray3, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3,
    PyUntypedArrayMethods,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::index::Pose;
use crate::views::Rotation;
use crate::Point3;

/// An `order` array's entries as indices into `len` of `what` (rotations,
/// poses); `ValueError` naming the first that is not one.
pub fn indices_into(
    order: &PyReadonlyArray1<'_, i64>,
    len: usize,
    what: &str,
) -> PyResult<Vec<usize>> {
    order
        .as_array()
        .iter()
        .map(|&i| {
            usize::try_from(i).ok().filter(|&i| i < len).ok_or_else(|| {
                PyValueError::new_err(format!("order holds {i}, not one of the {len} {what}"))
            })
        })
        .collect()
}

/// Borrows an (N, 3) C-contiguous array as N triples, without copying; the
/// error message names the array.
pub fn triples<'a, T: numpy::Element>(
    array: &'a PyReadonlyArray2<'_, T>,
    name: &str,
) -> Result<&'a [[T; 3]], String> {
    let shape = array.shape();
    if shape[1] != 3 {
        return Err(format!("{name} must have shape (N, 3), got {shape:?}"));
    }
    let flat = array
        .as_slice()
        .map_err(|_| format!("{name} must be C-contiguous"))?;
    Ok(flat.as_chunks::<3>().0)
}

/// A vector from a contiguous array of 3 values; the error names it.
pub fn vector3_from(array: &PyReadonlyArray1<'_, f64>, name: &str) -> PyResult<Vector3<f64>> {
    match array.as_slice()? {
        [x, y, z] => Ok(Vector3::new(*x, *y, *z)),
        _ => Err(PyValueError::new_err(format!("{name} must be 3 values"))),
    }
}

/// Rotations from a (V, 3, 3) C-contiguous array (row-major matrices).
pub fn rotations_from(array: &PyReadonlyArray3<'_, f64>) -> PyResult<Vec<Rotation>> {
    let shape = array.shape();
    if shape[1] != 3 || shape[2] != 3 {
        return Err(PyValueError::new_err(format!(
            "rotations must have shape (V, 3, 3), got {shape:?}"
        )));
    }
    let flat = array
        .as_slice()
        .map_err(|_| PyValueError::new_err("rotations must be C-contiguous"))?;
    Ok(flat.chunks_exact(9).map(Rotation::from_row_slice).collect())
}

/// Poses (model → camera) from `rotations` (C, 3, 3) and `translations` (C, 3).
pub fn poses_from(
    rotations: &PyReadonlyArray3<'_, f64>,
    translations: &PyReadonlyArray2<'_, f64>,
) -> PyResult<Vec<Pose>> {
    let r = rotations_from(rotations)?;
    let t = triples(translations, "translations").map_err(PyValueError::new_err)?;
    if r.len() != t.len() {
        return Err(PyValueError::new_err("one translation per rotation"));
    }
    Ok(r.iter()
        .zip(t)
        .map(|(r, t)| Pose {
            rotation: *r,
            translation: nalgebra::Vector3::from(*t),
        })
        .collect())
}

/// Rotations as a (C, 3, 3) float64 array of row-major matrices.
pub fn rotations_array<'a, 'py>(
    py: Python<'py>,
    rotations: impl ExactSizeIterator<Item = &'a nalgebra::Matrix3<f64>>,
) -> Bound<'py, PyArray3<f64>> {
    let c = rotations.len();
    let flat: Vec<f64> = rotations
        .flat_map(|r| r.transpose().as_slice().to_vec())
        .collect();
    Array::from_shape_vec((c, 3, 3), flat)
        .expect("C × 3 × 3")
        .into_pyarray(py)
}

/// One 3 × 3 matrix as a (3, 3) float64 array (row-major).
pub fn matrix_array<'py>(
    py: Python<'py>,
    matrix: &nalgebra::Matrix3<f64>,
) -> Bound<'py, PyArray2<f64>> {
    Array::from_shape_vec((3, 3), matrix.transpose().as_slice().to_vec())
        .expect("3 × 3")
        .into_pyarray(py)
}

/// Translations (metres) as a (C, 3) float64 array.
pub fn translations_array<'a, 'py>(
    py: Python<'py>,
    translations: impl ExactSizeIterator<Item = &'a nalgebra::Vector3<f64>>,
) -> Bound<'py, PyArray2<f64>> {
    let c = translations.len();
    let flat: Vec<f64> = translations.flat_map(|t| [t.x, t.y, t.z]).collect();
    Array::from_shape_vec((c, 3), flat)
        .expect("C × 3")
        .into_pyarray(py)
}

/// Points as an (N, 3) float32 array.
pub fn points_array<'py>(py: Python<'py>, points: &[Point3]) -> Bound<'py, PyArray2<f32>> {
    Array::from_shape_vec((points.len(), 3), points.as_flattened().to_vec())
        .expect("n × 3 elements")
        .into_pyarray(py)
}
