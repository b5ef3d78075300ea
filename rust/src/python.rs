//! pyo3 bindings: the private `edgepose._core` module. Thin by design: it
//! checks shapes, borrows numpy buffers without copying, releases the GIL
//! for the Rust work, and turns errors into `ValueError`. The public, typed
//! API is the Python package around it.
//!
//! Every entry point runs inside [`guarded`]: a Rust panic (a bug, never an
//! input error) unwinds to there and is raised as
//! `edgepose.errors.InternalError`, an `EdgePoseError`, instead of pyo3's
//! `PanicException` (a `BaseException` that `except Exception` misses). This
//! needs `panic = "unwind"`, Rust's default, which the workspace profiles keep.

use std::panic::{catch_unwind, AssertUnwindSafe};

use numpy::ndarray::Array;
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArray3, PyReadonlyArray1, PyReadonlyArray2,
    PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use rayon::prelude::*;

use crate::error::GeometryError;
use crate::refine::{ModelIndex, Pose};
use crate::scoring::{align_translations, score_poses, DepthGrid, ScoreSettings};
use crate::segment::{segment, SegmentSettings};
use crate::views::Rotation;
use crate::{grouping, maps, model, sampling, search, views, visibility, Point3};

pyo3::import_exception!(edgepose.errors, InternalError);

fn value_error(e: GeometryError) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// Runs a binding's body; a panic anywhere in it (with the GIL released or
/// in a rayon worker too: both unwind back to this thread) becomes an
/// `InternalError` carrying the panic message.
fn guarded<T>(body: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    catch_unwind(AssertUnwindSafe(body)).unwrap_or_else(|payload| {
        let message = payload
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| payload.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "unknown panic payload".into());
        Err(InternalError::new_err(format!(
            "edgepose core bug (Rust panic): {message}"
        )))
    })
}

/// TEST HOOK, not API: panics on purpose so the tests can check that a Rust
/// panic reaches Python as `InternalError`. `where_` is "attached" (GIL
/// held), "detached" (GIL released) or "rayon" (in a worker thread).
#[pyfunction]
fn _panic_for_tests(py: Python<'_>, message: String, where_: &str) -> PyResult<()> {
    guarded(|| match where_ {
        "attached" => panic!("{message}"),
        "detached" => py.detach(|| -> PyResult<()> { panic!("{message}") }),
        "rayon" => {
            py.detach(|| {
                (0..64)
                    .into_par_iter()
                    .for_each(|i| assert!(i < 63, "{message}"))
            });
            Ok(())
        }
        _ => Err(PyValueError::new_err(format!("unknown place {where_:?}"))),
    })
}

/// Borrows an (N, 3) C-contiguous array as N triples, without copying.
fn triples<'a, T: numpy::Element>(
    array: &'a PyReadonlyArray2<'_, T>,
    name: &str,
) -> PyResult<&'a [[T; 3]]> {
    let shape = array.shape();
    if shape[1] != 3 {
        return Err(PyValueError::new_err(format!(
            "{name} must have shape (N, 3), got {shape:?}"
        )));
    }
    let flat = array
        .as_slice()
        .map_err(|_| PyValueError::new_err(format!("{name} must be C-contiguous")))?;
    Ok(flat.as_chunks::<3>().0)
}

fn rotations_from(array: &PyReadonlyArray3<'_, f64>) -> PyResult<Vec<Rotation>> {
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
fn poses_from(
    rotations: &PyReadonlyArray3<'_, f64>,
    translations: &PyReadonlyArray2<'_, f64>,
) -> PyResult<Vec<Pose>> {
    let r = rotations_from(rotations)?;
    let t = triples(translations, "translations")?;
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

/// Translations (metres) as a (C, 3) float64 array.
fn translations_array<'a, 'py>(
    py: Python<'py>,
    translations: impl ExactSizeIterator<Item = &'a nalgebra::Vector3<f64>>,
) -> Bound<'py, PyArray2<f64>> {
    let c = translations.len();
    let flat: Vec<f64> = translations.flat_map(|t| [t.x, t.y, t.z]).collect();
    Array::from_shape_vec((c, 3), flat)
        .expect("C × 3")
        .into_pyarray(py)
}

fn points_array<'py>(py: Python<'py>, points: Vec<Point3>) -> Bound<'py, PyArray2<f32>> {
    let n = points.len();
    Array::from_shape_vec((n, 3), points.into_flattened())
        .expect("n × 3 elements")
        .into_pyarray(py)
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
    guarded(|| {
        let v = triples(&vertices, "vertices")?;
        let f = triples(&faces, "faces")?;
        let m = py
            .detach(|| model::StandardModel::from_mesh(v, f, n_points, seed))
            .map_err(value_error)?;
        model_tuple(py, m)
    })
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
    guarded(|| {
        let p = triples(&points, "points")?;
        let n = triples(&normals, "normals")?;
        let m = py
            .detach(|| model::StandardModel::from_points(p, n, n_points))
            .map_err(value_error)?;
        model_tuple(py, m)
    })
}

fn model_tuple<'py>(py: Python<'py>, m: model::StandardModel) -> PyResult<Bound<'py, PyAny>> {
    let centre = PyArray1::from_vec(py, m.centre.to_vec());
    (
        points_array(py, m.points),
        points_array(py, m.normals),
        centre,
        m.scale,
        m.diameter,
        m.spacing,
    )
        .into_pyobject(py)
        .map(|t| t.into_any())
}

/// `n` Fibonacci-sphere viewpoints: `(directions (n, 3), rotations (n, 3, 3))`.
#[pyfunction]
#[allow(clippy::type_complexity)]
fn fibonacci_viewpoints(
    py: Python<'_>,
    n: usize,
) -> PyResult<(Bound<'_, PyArray2<f64>>, Bound<'_, PyArray3<f64>>)> {
    guarded(|| {
        let (directions, rotations) = py.detach(|| views::viewpoints(n));
        let d: Vec<f64> = directions.iter().flat_map(|d| [d.x, d.y, d.z]).collect();
        let r: Vec<f64> = rotations
            .iter()
            .flat_map(|r| r.transpose().as_slice().to_vec())
            .collect();
        Ok((
            Array::from_shape_vec((n, 3), d)
                .expect("n × 3")
                .into_pyarray(py),
            Array::from_shape_vec((n, 3, 3), r)
                .expect("n × 3 × 3")
                .into_pyarray(py),
        ))
    })
}

/// Farthest-point sampling: indices of `m` points of an (N, 3) cloud.
#[pyfunction]
fn farthest_point_sample<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f32>,
    m: usize,
) -> PyResult<Bound<'py, PyArray1<u32>>> {
    guarded(|| {
        let p = triples(&points, "points")?;
        let idx = py.detach(|| sampling::farthest_point_sample(p, m));
        Ok(PyArray1::from_vec(py, idx))
    })
}

/// Visibility flags of view-frame points and normals (camera looks along +z).
#[pyfunction]
fn visible_mask<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f32>,
    normals: PyReadonlyArray2<'py, f32>,
    spacing: f32,
) -> PyResult<Bound<'py, PyArray1<bool>>> {
    guarded(|| {
        let p = triples(&points, "points")?;
        let n = triples(&normals, "normals")?;
        if p.len() != n.len() {
            return Err(PyValueError::new_err("points and normals differ in length"));
        }
        Ok(PyArray1::from_vec(
            py,
            py.detach(|| visibility::visible_mask(p, n, spacing)),
        ))
    })
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
    guarded(|| {
        let p = triples(&points, "points")?;
        let n = triples(&normals, "normals")?;
        if p.len() != n.len() || p.is_empty() {
            return Err(PyValueError::new_err(
                "model points and normals must be non-empty and equal in length",
            ));
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

/// The encoder's neighbour groups of each map in `maps` (B, m, 3): for each
/// map's first `centres` points, the indices of their `k` nearest map points
/// (B, centres, k), in parallel over maps.
#[pyfunction]
fn map_neighbours<'py>(
    py: Python<'py>,
    maps: PyReadonlyArray3<'py, f32>,
    centres: usize,
    k: usize,
) -> PyResult<Bound<'py, PyArray3<u32>>> {
    guarded(|| {
        let [b, m, three] = maps.shape() else {
            unreachable!("a 3-D array")
        };
        let (b, m) = (*b, *m);
        if *three != 3 || centres > m || k > m || centres == 0 || k == 0 {
            return Err(PyValueError::new_err(format!(
                "maps of shape {:?} cannot give {centres} centres with {k} neighbours",
                maps.shape()
            )));
        }
        let flat = maps
            .as_slice()
            .map_err(|_| PyValueError::new_err("maps must be C-contiguous"))?;
        let points = flat.as_chunks::<3>().0;
        let groups = py.detach(|| grouping::neighbours_of_maps(points, m, centres, k));
        Ok(Array::from_shape_vec((b, centres, k), groups)
            .expect("B × centres × k")
            .into_pyarray(py))
    })
}

/// Centre, scale and resample a cloud to an `m`-point map: `(map (m, 3), centroid (3,))`.
#[pyfunction]
fn normalize_to_map<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f32>,
    scale: f32,
    m: usize,
) -> PyResult<(Bound<'py, PyArray2<f32>>, Bound<'py, PyArray1<f32>>)> {
    guarded(|| {
        let p = triples(&points, "points")?;
        if p.is_empty() {
            return Err(PyValueError::new_err("cloud is empty"));
        }
        let (map, centroid) = py.detach(|| maps::normalize_to_map(p, scale, m));
        Ok((
            points_array(py, map),
            PyArray1::from_vec(py, centroid.to_vec()),
        ))
    })
}

/// Rotation object → view frame for one direction (object frame, towards the camera).
#[pyfunction]
fn view_rotation<'py>(
    py: Python<'py>,
    direction: PyReadonlyArray1<'py, f64>,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    guarded(|| {
        let d = direction
            .as_slice()
            .map_err(|_| PyValueError::new_err("direction must be contiguous"))?;
        if d.len() != 3 || !d.iter().all(|v| v.is_finite()) || d.iter().all(|v| *v == 0.0) {
            return Err(PyValueError::new_err(
                "direction must be 3 finite values, not all zero",
            ));
        }
        let r = views::view_rotation(&nalgebra::Vector3::new(d[0], d[1], d[2]));
        Ok(
            Array::from_shape_vec((3, 3), r.transpose().as_slice().to_vec())
                .expect("3 × 3")
                .into_pyarray(py),
        )
    })
}

/// The `k` codes most similar to `query`: `(indices (k,) u32, similarities (k,) f32)`, best first.
#[pyfunction]
fn top_k<'py>(
    py: Python<'py>,
    codes: PyReadonlyArray2<'py, f32>,
    query: PyReadonlyArray1<'py, f32>,
    k: usize,
) -> PyResult<(Bound<'py, PyArray1<u32>>, Bound<'py, PyArray1<f32>>)> {
    guarded(|| {
        let dim = codes.shape()[1];
        let c = codes
            .as_slice()
            .map_err(|_| PyValueError::new_err("codes must be C-contiguous"))?;
        let q = query
            .as_slice()
            .map_err(|_| PyValueError::new_err("query must be contiguous"))?;
        if q.len() != dim || dim == 0 {
            return Err(PyValueError::new_err(format!(
                "query has {} values, codes have {dim}",
                q.len()
            )));
        }
        let best = py.detach(|| search::top_k(c, dim, q, k));
        let (idx, sim): (Vec<u32>, Vec<f32>) = best.into_iter().map(|(i, s)| (i as u32, s)).unzip();
        Ok((PyArray1::from_vec(py, idx), PyArray1::from_vec(py, sim)))
    })
}

/// Which points of an observed cloud (camera frame, metres) belong to an
/// object `diameter` metres across (outliers and background components
/// removed; see the core's `segment` module for `shadow_spacings` and
/// `max_shadowed_fraction`): `(keep (N,) bool, spacing)`, spacing being the
/// median nearest-neighbour distance in metres.
#[pyfunction]
#[pyo3(signature = (cloud, diameter, shadow_spacings = 4.0, max_shadowed_fraction = 0.5, min_component_fraction = 0.01, max_component_offset = 0.8))]
fn segment_object<'py>(
    py: Python<'py>,
    cloud: PyReadonlyArray2<'py, f32>,
    diameter: f64,
    shadow_spacings: f64,
    max_shadowed_fraction: f64,
    min_component_fraction: f64,
    max_component_offset: f64,
) -> PyResult<(Bound<'py, PyArray1<bool>>, f64)> {
    guarded(|| {
        let c = triples(&cloud, "cloud")?;
        if !(diameter.is_finite() && diameter > 0.0) {
            return Err(PyValueError::new_err(format!(
                "diameter must be a positive number of metres, got {diameter}"
            )));
        }
        let settings = SegmentSettings {
            shadow_spacings,
            max_shadowed_fraction,
            min_component_fraction,
            max_component_offset,
            ..SegmentSettings::default()
        };
        let found = py.detach(|| segment(c, diameter, &settings));
        Ok((PyArray1::from_vec(py, found.keep), found.spacing))
    })
}

/// A model's points and normals (model frame, metres) with a kd-tree, for
/// verification and ICP. Immutable: safe to share between threads.
#[pyclass(frozen, name = "ModelIndex", module = "edgepose._core")]
struct PyModelIndex {
    inner: ModelIndex,
}

#[pymethods]
impl PyModelIndex {
    #[new]
    fn new(
        py: Python<'_>,
        points: PyReadonlyArray2<'_, f32>,
        normals: PyReadonlyArray2<'_, f32>,
    ) -> PyResult<Self> {
        guarded(|| {
            let p = triples(&points, "points")?.to_vec();
            let n = triples(&normals, "normals")?.to_vec();
            if p.len() != n.len() || p.is_empty() {
                return Err(PyValueError::new_err(
                    "points and normals must be non-empty and equal in length",
                ));
            }
            Ok(Self {
                inner: py.detach(|| ModelIndex::new(p, n)),
            })
        })
    }

    fn __len__(&self) -> usize {
        self.inner.len()
    }

    /// Mean keypoint-to-model distance (metres) for each candidate pose
    /// (model → camera: `rotations` (C, 3, 3), `translations` (C, 3)).
    fn verify<'py>(
        &self,
        py: Python<'py>,
        keypoints: PyReadonlyArray2<'py, f32>,
        rotations: PyReadonlyArray3<'py, f64>,
        translations: PyReadonlyArray2<'py, f64>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        guarded(|| {
            let k = triples(&keypoints, "keypoints")?;
            let poses = poses_from(&rotations, &translations)?;
            Ok(PyArray1::from_vec(
                py,
                py.detach(|| search::verify(&self.inner, k, &poses)),
            ))
        })
    }

    /// Each pose's translation moved so the `observed` points (camera frame)
    /// land on the model (rotations kept): `translations (C, 3)`.
    fn align_translations<'py>(
        &self,
        py: Python<'py>,
        observed: PyReadonlyArray2<'py, f32>,
        rotations: PyReadonlyArray3<'py, f64>,
        translations: PyReadonlyArray2<'py, f64>,
        iterations: usize,
        max_distance: f64,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        guarded(|| {
            let o = triples(&observed, "observed")?;
            let poses = poses_from(&rotations, &translations)?;
            if !(max_distance.is_finite() && max_distance >= 0.0) {
                return Err(PyValueError::new_err(format!(
                    "max_distance must be finite and non-negative, got {max_distance}"
                )));
            }
            let out =
                py.detach(|| align_translations(&self.inner, o, &poses, iterations, max_distance));
            Ok(translations_array(py, out.iter().map(|p| &p.translation)))
        })
    }

    /// Scores each candidate pose (model → camera: `rotations` (C, 3, 3),
    /// `translations` (C, 3)) against the `observed` points and the whole
    /// observed `cloud` (camera frame, metres; its point `spacing` sizes the
    /// free-space grid): `(fit (C,) metres, inlier_fraction (C,),
    /// free_space_violation (C,))` (see the core's `scoring` module).
    #[allow(clippy::too_many_arguments)]
    fn score<'py>(
        &self,
        py: Python<'py>,
        observed: PyReadonlyArray2<'py, f32>,
        cloud: PyReadonlyArray2<'py, f32>,
        spacing: f64,
        rotations: PyReadonlyArray3<'py, f64>,
        translations: PyReadonlyArray2<'py, f64>,
        inlier_distance: f64,
        free_space_tolerance: f64,
        model_stride: usize,
    ) -> PyResult<Bound<'py, PyAny>> {
        guarded(|| {
            let o = triples(&observed, "observed")?;
            let c = triples(&cloud, "cloud")?;
            let poses = poses_from(&rotations, &translations)?;
            if ![spacing, inlier_distance, free_space_tolerance]
                .iter()
                .all(|v| v.is_finite() && *v >= 0.0)
            {
                return Err(PyValueError::new_err(
                    "spacing and distances must be finite and non-negative",
                ));
            }
            let settings = ScoreSettings {
                inlier_distance,
                free_space_tolerance,
                model_stride,
            };
            let scores = py.detach(|| {
                let grid = DepthGrid::new(c, spacing, 2.0);
                score_poses(&self.inner, o, &grid, &poses, &settings)
            });
            (
                PyArray1::from_vec(py, scores.iter().map(|s| s.fit).collect()),
                PyArray1::from_vec(py, scores.iter().map(|s| s.inlier_fraction).collect()),
                PyArray1::from_vec(py, scores.iter().map(|s| s.free_space_violation).collect()),
            )
                .into_pyobject(py)
                .map(|t| t.into_any())
        })
    }

    /// Point-to-plane ICP of `cloud` (camera frame) from each start pose
    /// (model → camera: `rotations` (H, 3, 3), `translations` (H, 3)), one
    /// after another: `(R (H, 3, 3), t (H, 3), iterations (H,),
    /// converged (H,), inliers (H,), rmse (H,))`.
    fn refine<'py>(
        &self,
        py: Python<'py>,
        cloud: PyReadonlyArray2<'py, f32>,
        rotations: PyReadonlyArray3<'py, f64>,
        translations: PyReadonlyArray2<'py, f64>,
        max_iterations: usize,
        max_distance: f64,
    ) -> PyResult<Bound<'py, PyAny>> {
        guarded(|| {
            let c = triples(&cloud, "cloud")?;
            let starts = poses_from(&rotations, &translations)?;
            let out = py.detach(|| {
                self.inner
                    .refine_each(c, &starts, max_iterations, max_distance)
            });
            let h = out.len();
            let rot: Vec<f64> = out
                .iter()
                .flat_map(|o| o.pose.rotation.transpose().as_slice().to_vec())
                .collect();
            (
                Array::from_shape_vec((h, 3, 3), rot)
                    .expect("H × 3 × 3")
                    .into_pyarray(py),
                translations_array(py, out.iter().map(|o| &o.pose.translation)),
                PyArray1::from_vec(py, out.iter().map(|o| o.iterations as u32).collect()),
                PyArray1::from_vec(py, out.iter().map(|o| o.converged).collect()),
                PyArray1::from_vec(py, out.iter().map(|o| o.inliers as u32).collect()),
                PyArray1::from_vec(py, out.iter().map(|o| o.rmse).collect()),
            )
                .into_pyobject(py)
                .map(|t| t.into_any())
        })
    }
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
    m.add_function(wrap_pyfunction!(map_neighbours, m)?)?;
    m.add_function(wrap_pyfunction!(view_rotation, m)?)?;
    m.add_function(wrap_pyfunction!(top_k, m)?)?;
    m.add_function(wrap_pyfunction!(segment_object, m)?)?;
    m.add_class::<PyModelIndex>()?;
    m.add_function(wrap_pyfunction!(_panic_for_tests, m)?)?;
    Ok(())
}
