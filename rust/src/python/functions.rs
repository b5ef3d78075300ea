//! The bindings' free functions: viewpoints, sampling, visibility, maps,
//! code search and segmentation of an observed cloud.

use numpy::ndarray::Array;
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArray3, PyArray4, PyReadonlyArray1, PyReadonlyArray2,
    PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::arrays::{
    indices_into, matrix_array, points_array, rotations_array, rotations_from, triples,
    vector3_from,
};
use super::{guarded, InvalidCloudError, InvalidModelError};
use crate::index::{ModelIndex, Pose};
use crate::query::{self, CleanSettings, Pinhole, QuerySettings};
use crate::scoring::SceneDepth;
use crate::segment::{segment, SegmentSettings};
use crate::support::{self, SupportSettings};
use crate::track::{self, TrackFrameSettings, TrackedFit, TrackedScene};
use crate::{grouping, hypotheses, maps, sampling, search, views, visibility, Point3};
use std::sync::Arc;

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(fibonacci_viewpoints, m)?)?;
    m.add_function(wrap_pyfunction!(farthest_point_sample, m)?)?;
    m.add_function(wrap_pyfunction!(visible_mask, m)?)?;
    m.add_function(wrap_pyfunction!(normalize_to_map, m)?)?;
    m.add_function(wrap_pyfunction!(map_features, m)?)?;
    m.add_function(wrap_pyfunction!(view_rotation, m)?)?;
    m.add_function(wrap_pyfunction!(top_k, m)?)?;
    m.add_function(wrap_pyfunction!(distinct_rotations, m)?)?;
    m.add_function(wrap_pyfunction!(usable_icp, m)?)?;
    m.add_function(wrap_pyfunction!(box_sides, m)?)?;
    m.add_class::<PySegmentSettings>()?;
    m.add_function(wrap_pyfunction!(segment_object, m)?)?;
    m.add_function(wrap_pyfunction!(back_project, m)?)?;
    m.add_function(wrap_pyfunction!(on_support_plane, m)?)?;
    m.add_class::<PyCleanSettings>()?;
    m.add_function(wrap_pyfunction!(clean_cloud, m)?)?;
    m.add_function(wrap_pyfunction!(clean_depth_cloud, m)?)?;
    m.add_function(wrap_pyfunction!(prepare_query, m)?)?;
    m.add_function(wrap_pyfunction!(ray_alignment, m)?)?;
    Ok(())
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
        Ok((
            Array::from_shape_vec((n, 3), d)
                .expect("n × 3")
                .into_pyarray(py),
            rotations_array(py, rotations.iter()),
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
        let p = triples(&points, "points").map_err(PyValueError::new_err)?;
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
        let p = triples(&points, "points").map_err(InvalidModelError::new_err)?;
        let n = triples(&normals, "normals").map_err(InvalidModelError::new_err)?;
        if p.len() != n.len() {
            return Err(InvalidModelError::new_err(
                "points and normals differ in length",
            ));
        }
        Ok(PyArray1::from_vec(
            py,
            py.detach(|| visibility::visible_mask(p, n, spacing)),
        ))
    })
}

/// The encoder's inputs for each map in `maps` (B, m, 3), in parallel over
/// maps ([`grouping::MapFeatures`]): edge features (B, centres, k, 6), the
/// centres' radius and depth (B, centres, 2), and cos(mφ), sin(mφ) of their
/// polar angles (B, centres, harmonics) each.
#[pyfunction]
#[allow(clippy::type_complexity)]
fn map_features<'py>(
    py: Python<'py>,
    maps: PyReadonlyArray3<'py, f32>,
    centres: usize,
    k: usize,
    harmonics: usize,
) -> PyResult<(
    Bound<'py, PyArray4<f32>>,
    Bound<'py, PyArray3<f32>>,
    Bound<'py, PyArray3<f32>>,
    Bound<'py, PyArray3<f32>>,
)> {
    guarded(|| {
        let [b, m, three] = maps.shape() else {
            unreachable!("a 3-D array")
        };
        let (b, m) = (*b, *m);
        if *three != 3 || m == 0 || centres > m || k > m || centres == 0 || k == 0 {
            return Err(PyValueError::new_err(format!(
                "maps of shape {:?} cannot give {centres} centres with {k} neighbours",
                maps.shape()
            )));
        }
        let flat = maps
            .as_slice()
            .map_err(|_| PyValueError::new_err("maps must be C-contiguous"))?;
        let points = flat.as_chunks::<3>().0;
        let f = py.detach(|| grouping::features_of_maps(points, m, centres, k, harmonics));
        let rows = |v: Vec<f32>, width: usize| {
            Array::from_shape_vec((b, centres, width), v)
                .expect("B × centres × width")
                .into_pyarray(py)
        };
        Ok((
            Array::from_shape_vec((b, centres, k, 6), f.edges)
                .expect("B × centres × k × 6")
                .into_pyarray(py),
            rows(f.own, 2),
            rows(f.cos, harmonics),
            rows(f.sin, harmonics),
        ))
    })
}

/// Centre, scale and resample a cloud to an `m`-point map: `(map (m, 3), centroid (3,))`.
#[pyfunction]
#[allow(clippy::type_complexity)]
fn normalize_to_map<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f32>,
    scale: f32,
    m: usize,
) -> PyResult<(Bound<'py, PyArray2<f32>>, Bound<'py, PyArray1<f32>>)> {
    guarded(|| {
        let p = triples(&points, "points").map_err(InvalidCloudError::new_err)?;
        if p.is_empty() {
            return Err(InvalidCloudError::new_err("cloud is empty"));
        }
        let (map, centroid) = py.detach(|| maps::normalize_to_map(p, scale, m));
        Ok((
            points_array(py, &map),
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
        Ok(matrix_array(py, &r))
    })
}

/// (H,) bool: which ICP results (`inliers` (H,), `rmse` (H,),
/// `translations` (H, 3) camera frame, metres) are usable, against the
/// observed `centroid` (3,): see the core's `hypotheses::usable_icp`.
#[pyfunction]
fn usable_icp<'py>(
    py: Python<'py>,
    inliers: PyReadonlyArray1<'py, u32>,
    rmse: PyReadonlyArray1<'py, f64>,
    translations: PyReadonlyArray2<'py, f64>,
    centroid: PyReadonlyArray1<'py, f64>,
    min_icp_inliers: usize,
    max_centre_offset: f64,
) -> PyResult<Bound<'py, PyArray1<bool>>> {
    guarded(|| {
        let t = triples(&translations, "translations").map_err(PyValueError::new_err)?;
        let (inliers, rmse) = (inliers.as_slice()?, rmse.as_slice()?);
        if inliers.len() != t.len() || rmse.len() != t.len() {
            return Err(PyValueError::new_err(
                "one inlier count, RMSE and translation per ICP result",
            ));
        }
        let centroid = vector3_from(&centroid, "centroid")?;
        let usable = (0..t.len())
            .map(|h| {
                hypotheses::usable_icp(
                    inliers[h] as usize,
                    rmse[h],
                    &nalgebra::Vector3::from(t[h]),
                    &centroid,
                    min_icp_inliers,
                    max_centre_offset,
                )
            })
            .collect();
        Ok(PyArray1::from_vec(py, usable))
    })
}

/// Up to `count` of `rotations` (V, 3, 3), taken in `order` (indices),
/// each less alike every one taken before than `cos_min` (the cosine of
/// the angle between two rotations): see the core's `hypotheses::distinct`.
#[pyfunction]
fn distinct_rotations(
    rotations: PyReadonlyArray3<'_, f64>,
    order: PyReadonlyArray1<'_, i64>,
    count: usize,
    cos_min: f64,
) -> PyResult<Vec<usize>> {
    guarded(|| {
        let rotations = rotations_from(&rotations)?;
        let order = indices_into(&order, rotations.len(), "rotations")?;
        Ok(hypotheses::distinct(&rotations, &order, count, cos_min))
    })
}

/// The `k` codes most similar to `query`: `(indices (k,) u32, similarities (k,) f32)`, best first.
#[pyfunction]
#[allow(clippy::type_complexity)]
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
/// removed, as `settings` tune it; see the core's `segment` module):
/// `(keep (N,) bool, spacing)`, spacing being the median nearest-neighbour
/// distance in metres.
#[pyfunction]
fn segment_object<'py>(
    py: Python<'py>,
    cloud: PyReadonlyArray2<'py, f32>,
    diameter: f64,
    settings: &PySegmentSettings,
) -> PyResult<(Bound<'py, PyArray1<bool>>, f64)> {
    guarded(|| {
        let c = triples(&cloud, "cloud").map_err(InvalidCloudError::new_err)?;
        if !(diameter.is_finite() && diameter > 0.0) {
            return Err(PyValueError::new_err(format!(
                "diameter must be a positive number of metres, got {diameter}"
            )));
        }
        let found = py.detach(|| segment(c, diameter, &settings.inner));
        Ok((PyArray1::from_vec(py, found.keep), found.spacing))
    })
}

/// Stage 1's segmentation ([`SegmentSettings`]): the core's defaults
/// (`SegmentSettings::default`, where each is defined) for the fields not
/// given by keyword; every field readable. Built once per setting on the
/// Python side (`edgepose.SegmentSettings`).
#[pyclass(frozen, name = "SegmentSettings", module = "edgepose._core")]
pub struct PySegmentSettings {
    inner: SegmentSettings,
}

/// The constructor and a getter of each field of [`PySegmentSettings`].
macro_rules! segment_settings_fields {
    ($($name:ident: $kind:ty),* $(,)?) => {
        #[pymethods]
        impl PySegmentSettings {
            #[new]
            #[pyo3(signature = (**fields))]
            fn new(fields: Option<&Bound<'_, PyDict>>) -> PyResult<Self> {
                let mut inner = SegmentSettings::default();
                for (key, value) in fields.into_iter().flat_map(|f| f.iter()) {
                    match key.extract::<String>()?.as_str() {
                        $(stringify!($name) => inner.$name = value.extract::<$kind>()?,)*
                        other => {
                            return Err(PyTypeError::new_err(format!(
                                "SegmentSettings has no field {other:?}"
                            )))
                        }
                    }
                }
                Ok(Self { inner })
            }

            $(
                #[getter]
                fn $name(&self) -> $kind {
                    self.inner.$name
                }
            )*

            fn __repr__(&self) -> String {
                format!("{:?}", self.inner)
            }
        }
    };
}

segment_settings_fields!(
    neighbours: usize,
    outlier_sigmas: f64,
    cluster_spacings: f64,
    min_component_fraction: f64,
    max_component_offset: f64,
    max_shadowed_fraction: f64,
    shadow_spacings: f64,
    occluder_points: usize,
    occluder_fraction: f64,
    occluder_margin: f64,
    steep_faces: bool,
    ramp_spacings: f64,
    ramp_neighbours: usize,
    ramp_noise: f64,
    ramp_min_noise_spacings: f64,
    ramp_link: f64,
);

/// The limits of [`query::clean_cloud`] ([`CleanSettings`]), built once on
/// the Python side (`edgepose.cloud`, where each is defined).
#[pyclass(frozen, name = "CleanSettings", module = "edgepose._core")]
pub struct PyCleanSettings {
    inner: CleanSettings,
}

#[pymethods]
impl PyCleanSettings {
    #[new]
    #[pyo3(signature = (*, max_points, seed, min_points, max_coordinate, max_extent_diameters, min_extent_diameters))]
    fn new(
        max_points: usize,
        seed: u64,
        min_points: usize,
        max_coordinate: f64,
        max_extent_diameters: f64,
        min_extent_diameters: f64,
    ) -> Self {
        Self {
            inner: CleanSettings {
                max_points,
                seed,
                min_points,
                max_coordinate,
                max_extent_diameters,
                min_extent_diameters,
            },
        }
    }

    fn __repr__(&self) -> String {
        format!("{:?}", self.inner)
    }
}

/// [`query::clean_cloud`] of an (N, 3) float32 or float64 cloud (camera
/// frame, metres; any strides): the points `estimate` matches, as an (n, 3)
/// float32 array; `InvalidCloudError` naming the problem otherwise.
#[pyfunction]
fn clean_cloud<'py>(
    py: Python<'py>,
    cloud: &Bound<'py, PyAny>,
    diameter: f64,
    settings: &PyCleanSettings,
) -> PyResult<Bound<'py, PyArray2<f32>>> {
    guarded(|| {
        let settings = &settings.inner;
        let cleaned = if let Ok(array) = cloud.extract::<PyReadonlyArray2<'py, f32>>() {
            clean_rows(py, &array, diameter, settings)?
        } else {
            let array = cloud.extract::<PyReadonlyArray2<'py, f64>>().map_err(|_| {
                InvalidCloudError::new_err(
                    "cloud must be a float32 or float64 array of shape (N, 3)",
                )
            })?;
            clean_rows(py, &array, diameter, settings)?
        };
        let points = cleaned.map_err(|problem| InvalidCloudError::new_err(problem.to_string()))?;
        Ok(points_array(py, &points))
    })
}

/// [`query::clean_cloud`] of an (N, 3) array of any strides, without the GIL.
fn clean_rows<T: numpy::Element + Copy + Into<f64> + Sync>(
    py: Python<'_>,
    array: &PyReadonlyArray2<'_, T>,
    diameter: f64,
    settings: &CleanSettings,
) -> PyResult<Result<Vec<crate::Point3>, query::CloudProblem>> {
    let rows = array.as_array();
    if rows.ncols() != 3 {
        return Err(InvalidCloudError::new_err(format!(
            "cloud must have shape (N, 3), got {:?}",
            rows.shape()
        )));
    }
    Ok(py.detach(|| {
        query::clean_cloud(
            rows.nrows(),
            |i| [0, 1, 2].map(|k| rows[[i, k]].into()),
            diameter,
            settings,
        )
    }))
}

/// [`query::prepare_query`] (stage 1) on cleaned (N, 3) float32 `points`:
/// `(points kept (n, 3) f32, spacing m, centroid (3,) f64, r_corr (3, 3)
/// f64, map (map_points, 3) f32, keypoints (keypoints, 3) f32, median depth
/// of the points kept m)`, the points segmented as `segmentation` tunes it;
/// None keeps every point (spacing 0).
#[pyfunction]
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
fn prepare_query<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f32>,
    diameter: f64,
    scale: f32,
    map_points: usize,
    keypoints: usize,
    min_points: usize,
    segmentation: Option<PyRef<'py, PySegmentSettings>>,
) -> PyResult<(
    Bound<'py, PyArray2<f32>>,
    f64,
    Bound<'py, PyArray1<f64>>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray2<f32>>,
    Bound<'py, PyArray2<f32>>,
    f64,
)> {
    guarded(|| {
        let p = triples(&points, "points").map_err(InvalidCloudError::new_err)?;
        if p.is_empty() {
            return Err(InvalidCloudError::new_err("cloud is empty"));
        }
        if !(diameter.is_finite() && diameter > 0.0 && scale.is_finite() && scale > 0.0) {
            return Err(PyValueError::new_err(format!(
                "diameter and scale must be positive, got {diameter} and {scale}"
            )));
        }
        let settings = QuerySettings {
            segment: segmentation.map(|s| s.inner),
            min_points,
            map_points,
            keypoints,
        };
        let prepared = py
            .detach(|| query::prepare_query(p.to_vec(), diameter, scale, &settings))
            .map_err(|problem| InvalidCloudError::new_err(problem.to_string()))?;
        Ok((
            points_array(py, &prepared.points),
            prepared.spacing,
            PyArray1::from_vec(py, prepared.centroid.as_slice().to_vec()),
            matrix_array(py, &prepared.r_corr),
            points_array(py, &prepared.map),
            points_array(py, &prepared.keypoints),
            prepared.median_depth,
        ))
    })
}

/// The side lengths of the bounding box of (N, 3) float32 points along
/// each axis, in their units: each largest minus smallest coordinate in
/// float32, as numpy's `ptp` of each column gives them (0 for no points).
#[pyfunction]
fn box_sides(points: PyReadonlyArray2<'_, f32>) -> PyResult<[f64; 3]> {
    guarded(|| {
        let p = triples(&points, "points").map_err(PyValueError::new_err)?;
        Ok(std::array::from_fn(|a| {
            let (lo, hi) = p
                .iter()
                .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), q| {
                    (lo.min(q[a]), hi.max(q[a]))
                });
            if p.is_empty() {
                0.0
            } else {
                (hi - lo) as f64
            }
        }))
    })
}

/// [`views::ray_alignment`] of a (3,) centroid (camera frame, metres);
/// `ValueError` when it is zero or not finite.
#[pyfunction]
fn ray_alignment<'py>(
    py: Python<'py>,
    centroid: PyReadonlyArray1<'py, f64>,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    guarded(|| {
        let c = centroid
            .as_slice()
            .map_err(|_| PyValueError::new_err("centroid must be contiguous"))?;
        let [x, y, z] = c else {
            return Err(PyValueError::new_err(format!(
                "centroid must have 3 values, got {}",
                c.len()
            )));
        };
        let r = views::ray_alignment(&nalgebra::Vector3::new(*x, *y, *z)).ok_or_else(|| {
            PyValueError::new_err(format!("centroid must be finite and non-zero, got {c:?}"))
        })?;
        Ok(matrix_array(py, &r))
    })
}

/// A checked depth image as `estimate` takes it: (H, W), C-contiguous,
/// uint16, float32 or float64 (`depth / depth_scale` metres).
enum DepthImage<'py> {
    U16(PyReadonlyArray2<'py, u16>),
    F32(PyReadonlyArray2<'py, f32>),
    F64(PyReadonlyArray2<'py, f64>),
}

impl<'py> DepthImage<'py> {
    fn from_any(depth: &Bound<'py, PyAny>) -> PyResult<Self> {
        if let Ok(image) = depth.extract() {
            Ok(Self::U16(image))
        } else if let Ok(image) = depth.extract() {
            Ok(Self::F32(image))
        } else {
            depth.extract().map(Self::F64).map_err(|_| {
                PyValueError::new_err("depth must be a uint16, float32 or float64 image")
            })
        }
    }

    fn shape(&self) -> &[usize] {
        match self {
            Self::U16(image) => image.shape(),
            Self::F32(image) => image.shape(),
            Self::F64(image) => image.shape(),
        }
    }
}

/// `$body` with `$pixels` the row-major pixels of a [`DepthImage`] (any of
/// its types), without the GIL.
macro_rules! with_pixels {
    ($py:expr, $image:expr, |$pixels:ident| $body:expr) => {{
        fn slice<'a, T: numpy::Element>(image: &'a PyReadonlyArray2<'_, T>) -> PyResult<&'a [T]> {
            image
                .as_slice()
                .map_err(|_| PyValueError::new_err("depth must be C-contiguous"))
        }
        match &$image {
            DepthImage::U16(image) => {
                let $pixels = slice(image)?;
                $py.detach(|| $body)
            }
            DepthImage::F32(image) => {
                let $pixels = slice(image)?;
                $py.detach(|| $body)
            }
            DepthImage::F64(image) => {
                let $pixels = slice(image)?;
                $py.detach(|| $body)
            }
        }
    }};
}

/// The scene test's [`SceneDepth`]: the `window` (rows `top..bottom`,
/// columns `left..right`; None: all of it) of a [`DepthImage`] frame in
/// `depth_scale` units per metre, `camera` the frame's intrinsics;
/// ValueError for a window beyond the frame.
pub(super) fn scene_of_frame(
    py: Python<'_>,
    depth: &Bound<'_, PyAny>,
    window: Option<[usize; 4]>,
    depth_scale: f64,
    camera: Pinhole,
    radius: usize,
) -> PyResult<SceneDepth> {
    let image = DepthImage::from_any(depth)?;
    let (height, width) = (image.shape()[0], image.shape()[1]);
    let window = window.unwrap_or([0, height, 0, width]);
    let scene = with_pixels!(py, image, |d| SceneDepth::from_frame(
        d,
        [height, width],
        window,
        depth_scale,
        camera,
        radius
    ));
    scene.ok_or_else(|| {
        PyValueError::new_err(format!(
            "scene_window {window:?} must lie within scene_depth of shape {:?}",
            image.shape()
        ))
    })
}

/// A tracked frame's depth image, its `K`, depth scale and the model's box corners.
pub(super) type TrackedDepth<'a, 'py> = (
    &'a Bound<'py, PyAny>,
    &'a PyReadonlyArray2<'py, f64>,
    f64,
    &'a [[f64; 3]],
);

/// [`track::track_frame`] with the frame's depth (`depth`, `k`,
/// `depth_scale`, and the model's `box_corners`) when given, without the GIL.
#[allow(clippy::too_many_arguments)]
pub(super) fn track_frame_of(
    py: Python<'_>,
    index: &Arc<ModelIndex>,
    points: &[Point3],
    seen: &[Point3],
    start: Pose,
    free_space_tolerance: f64,
    frame: Option<TrackedDepth<'_, '_>>,
    settings: &TrackFrameSettings,
) -> PyResult<TrackedFit> {
    let Some((depth, k, depth_scale, box_corners)) = frame else {
        return Ok(py.detach(|| {
            track::track_frame::<f32>(
                index,
                points,
                seen,
                start,
                free_space_tolerance,
                None,
                settings,
            )
        }));
    };
    let camera = pinhole(k)?;
    let image = DepthImage::from_any(depth)?;
    let shape = [image.shape()[0], image.shape()[1]];
    Ok(with_pixels!(py, image, |d| track::track_frame(
        index,
        points,
        seen,
        start,
        free_space_tolerance,
        Some(TrackedScene {
            pixels: d,
            shape,
            camera,
            depth_scale,
            box_corners,
        }),
        settings
    )))
}

/// Pinhole intrinsics of a 3 × 3 matrix `K`; ValueError for another shape.
fn pinhole(k: &PyReadonlyArray2<'_, f64>) -> PyResult<Pinhole> {
    if k.shape() != [3, 3] {
        return Err(PyValueError::new_err(format!(
            "K must be 3 × 3, got shape {:?}",
            k.shape()
        )));
    }
    let k = k.as_array();
    Ok(Pinhole {
        fx: k[[0, 0]],
        fy: k[[1, 1]],
        cx: k[[0, 2]],
        cy: k[[1, 2]],
    })
}

/// [`query::back_project`]: the (N, 3) float64 camera-frame points (metres)
/// of the measured pixels of `mask` in a [`DepthImage`] `depth`, `K` the
/// checked 3 × 3 pinhole matrix.
#[pyfunction]
fn back_project<'py>(
    py: Python<'py>,
    depth: &Bound<'py, PyAny>,
    mask: PyReadonlyArray2<'py, bool>,
    k: PyReadonlyArray2<'py, f64>,
    depth_scale: f64,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    guarded(|| {
        let (image, flags, camera) = masked_image(depth, &mask, &k)?;
        let width = image.shape()[1];
        let points = with_pixels!(py, image, |d| query::back_project(
            d,
            flags,
            width,
            &camera,
            depth_scale
        ));
        Ok(
            Array::from_shape_vec((points.len(), 3), points.into_flattened())
                .expect("n × 3")
                .into_pyarray(py),
        )
    })
}

/// [`clean_cloud`] of the cloud [`back_project`] makes of `mask` in `depth`,
/// in one call: the same points, without the whole cloud crossing to Python.
#[pyfunction]
fn clean_depth_cloud<'py>(
    py: Python<'py>,
    depth: &Bound<'py, PyAny>,
    mask: PyReadonlyArray2<'py, bool>,
    k: PyReadonlyArray2<'py, f64>,
    depth_scale: f64,
    diameter: f64,
    settings: &PyCleanSettings,
) -> PyResult<Bound<'py, PyArray2<f32>>> {
    guarded(|| {
        let settings = &settings.inner;
        let (image, flags, camera) = masked_image(depth, &mask, &k)?;
        let width = image.shape()[1];
        let cleaned = with_pixels!(py, image, |d| query::clean_depth_cloud(
            d,
            flags,
            width,
            &camera,
            depth_scale,
            diameter,
            settings
        ));
        let points = cleaned.map_err(|problem| InvalidCloudError::new_err(problem.to_string()))?;
        Ok(points_array(py, &points))
    })
}

/// A [`DepthImage`], its `mask`'s flags (same shape, C-contiguous) and the
/// camera of `k`; `InvalidCloudError` or `ValueError` otherwise.
fn masked_image<'py, 'a>(
    depth: &Bound<'py, PyAny>,
    mask: &'a PyReadonlyArray2<'py, bool>,
    k: &PyReadonlyArray2<'py, f64>,
) -> PyResult<(DepthImage<'py>, &'a [bool], Pinhole)> {
    let camera = pinhole(k)?;
    let image = DepthImage::from_any(depth)?;
    if image.shape() != mask.shape() {
        return Err(InvalidCloudError::new_err(format!(
            "mask shape {:?} differs from depth shape {:?}",
            mask.shape(),
            image.shape()
        )));
    }
    let flags = mask
        .as_slice()
        .map_err(|_| PyValueError::new_err("mask must be C-contiguous"))?;
    Ok((image, flags, camera))
}

/// [`support::on_support_plane`]: (n,) bool, the `points` ((n, 3) float32,
/// camera frame, metres) on the surface the object stands on or in front
/// of, found around them in a [`DepthImage`] `depth` (`K` the checked 3 × 3
/// pinhole matrix) of an object `diameter` metres across.
#[pyfunction]
fn on_support_plane<'py>(
    py: Python<'py>,
    points: PyReadonlyArray2<'py, f32>,
    depth: &Bound<'py, PyAny>,
    k: PyReadonlyArray2<'py, f64>,
    depth_scale: f64,
    diameter: f64,
) -> PyResult<Bound<'py, PyArray1<bool>>> {
    guarded(|| {
        let p = triples(&points, "points").map_err(InvalidCloudError::new_err)?;
        let camera = pinhole(&k)?;
        let image = DepthImage::from_any(depth)?;
        let width = image.shape()[1];
        let settings = SupportSettings::default();
        let on = with_pixels!(py, image, |d| support::on_support_plane(
            p,
            d,
            width,
            &camera,
            depth_scale,
            diameter,
            &settings
        ));
        Ok(PyArray1::from_vec(py, on))
    })
}
