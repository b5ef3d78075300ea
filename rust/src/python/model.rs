//! `StandardModel`: the core's model, built once per object (from a mesh,
//! from points, or from a codebook file's arrays) and passed as it is to
//! `compute_maps` and `ModelIndex`.

use numpy::ndarray::Array;
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use super::arrays::{points_array, rotations_from, triples};
use super::{guarded, InvalidModelError};
use crate::maps;
use crate::model::StandardModel;

/// An object's surface samples in the model frame (metres) and the numbers
/// every later stage needs. Immutable: safe to share between threads.
#[pyclass(frozen, name = "StandardModel", module = "edgepose._core")]
pub struct PyStandardModel {
    pub inner: StandardModel,
}

fn model_error(source: &str, message: impl std::fmt::Display) -> PyErr {
    InvalidModelError::new_err(format!("{source}: {message}"))
}

#[pymethods]
impl PyStandardModel {
    /// A model from its parts as stored (a codebook file): `points` and
    /// `normals` (N, 3) float32 in the model frame, `centre` (3,) in the mesh
    /// frame, metres; `scale` (1/m), `diameter` and `spacing` (m).
    #[new]
    fn new(
        points: PyReadonlyArray2<'_, f32>,
        normals: PyReadonlyArray2<'_, f32>,
        centre: PyReadonlyArray1<'_, f64>,
        scale: f64,
        diameter: f64,
        spacing: f64,
    ) -> PyResult<Self> {
        guarded(|| {
            let error = |m: String| model_error("model", m);
            let p = triples(&points, "points").map_err(error)?;
            let n = triples(&normals, "normals").map_err(error)?;
            let c = centre
                .as_slice()
                .map_err(|_| error("centre must be contiguous".into()))?;
            if p.is_empty() || p.len() != n.len() {
                return Err(error(format!(
                    "points and normals must be non-empty and equal in length, got {} and {}",
                    p.len(),
                    n.len()
                )));
            }
            let [x, y, z] = c else {
                return Err(error(format!("centre must have 3 values, got {}", c.len())));
            };
            if ![scale, diameter, spacing]
                .iter()
                .all(|v| v.is_finite() && *v > 0.0)
            {
                return Err(error(format!(
                    "scale, diameter and spacing must be positive, got {scale}, {diameter}, {spacing}"
                )));
            }
            Ok(Self {
                inner: StandardModel {
                    points: p.to_vec(),
                    normals: n.to_vec(),
                    centre: [*x, *y, *z],
                    scale,
                    diameter,
                    spacing,
                },
            })
        })
    }

    /// The standard model of a triangle mesh (`vertices` (V, 3) float64 in
    /// metres, `faces` (F, 3) uint32): `n_points` evenly spread surface
    /// points. `source` names the mesh in error messages.
    #[staticmethod]
    #[pyo3(signature = (vertices, faces, n_points, seed, source = "mesh"))]
    fn from_mesh(
        py: Python<'_>,
        vertices: PyReadonlyArray2<'_, f64>,
        faces: PyReadonlyArray2<'_, u32>,
        n_points: usize,
        seed: u64,
        source: &str,
    ) -> PyResult<Self> {
        guarded(|| {
            let v = triples(&vertices, "vertices").map_err(|m| model_error(source, m))?;
            let f = triples(&faces, "faces").map_err(|m| model_error(source, m))?;
            let inner = py
                .detach(|| StandardModel::from_mesh(v, f, n_points, seed))
                .map_err(|e| model_error(source, e))?;
            Ok(Self { inner })
        })
    }

    /// The standard model of surface `points` with `normals` ((N, 3) float32,
    /// metres), thinned to `n_points` by farthest-point sampling.
    #[staticmethod]
    #[pyo3(signature = (points, normals, n_points, source = "points"))]
    fn from_points(
        py: Python<'_>,
        points: PyReadonlyArray2<'_, f32>,
        normals: PyReadonlyArray2<'_, f32>,
        n_points: usize,
        source: &str,
    ) -> PyResult<Self> {
        guarded(|| {
            let p = triples(&points, "points").map_err(|m| model_error(source, m))?;
            let n = triples(&normals, "normals").map_err(|m| model_error(source, m))?;
            let inner = py
                .detach(|| StandardModel::from_points(p, n, n_points))
                .map_err(|e| model_error(source, e))?;
            Ok(Self { inner })
        })
    }

    fn __len__(&self) -> usize {
        self.inner.points.len()
    }

    /// (N, 3) float32 surface points, model frame, metres (a copy).
    #[getter]
    fn points<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f32>> {
        points_array(py, &self.inner.points)
    }

    /// (N, 3) float32 unit outward normals, model frame (a copy).
    #[getter]
    fn normals<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f32>> {
        points_array(py, &self.inner.normals)
    }

    /// (3,) float64 model-frame origin in the original mesh frame, metres.
    #[getter]
    fn centre<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.inner.centre.to_vec())
    }

    /// `1 / max‖p‖`: multiplies model-frame metres into the unit sphere.
    #[getter]
    fn scale(&self) -> f64 {
        self.inner.scale
    }

    /// Largest distance between two model points, metres.
    #[getter]
    fn diameter(&self) -> f64 {
        self.inner.diameter
    }

    /// Mean nearest-neighbour distance between model points, metres.
    #[getter]
    fn spacing(&self) -> f64 {
        self.inner.spacing
    }
}

/// Maps of every viewpoint of `model`, in parallel: `(maps (V, m, 3) f32,
/// centroids (V, 3) f64, visible (V,) u32)` for `rotations` (V, 3, 3).
#[pyfunction]
pub fn compute_maps<'py>(
    py: Python<'py>,
    model: &PyStandardModel,
    rotations: PyReadonlyArray3<'py, f64>,
    m: usize,
) -> PyResult<Bound<'py, PyAny>> {
    guarded(|| {
        if m == 0 {
            return Err(PyValueError::new_err("maps need at least one point"));
        }
        let rots = rotations_from(&rotations)?;
        let out = py.detach(|| maps::compute_maps(&model.inner, &rots, m));
        let v = rots.len();
        let map_points =
            Array::from_shape_vec((v, m, 3), out.points.into_flattened()).expect("V × m × 3");
        let centroids =
            Array::from_shape_vec((v, 3), out.centroids.into_flattened()).expect("V × 3");
        (
            map_points.into_pyarray(py),
            centroids.into_pyarray(py),
            PyArray1::from_vec(py, out.visible),
        )
            .into_pyobject(py)
            .map(|t| t.into_any())
    })
}
