//! `ModelIndex`: the model's kd-tree for verification, scoring and ICP, and
//! `IcpResults`, ICP's typed outcome.

use numpy::{
    PyArray1, PyArray2, PyArray3, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2,
    PyReadonlyArray3,
};
use pyo3::exceptions::{PyIndexError, PyValueError};
use pyo3::prelude::*;
use std::sync::{Arc, Mutex};

use super::arrays::{
    indices_into, poses_from, rotations_array, translations_array, triples, vector3_from,
};
use super::functions::{scene_of_frame, track_frame_of};
use super::model::PyStandardModel;
use super::{guarded, InvalidCloudError};
use crate::flips::{flip_margin, pose_distances, FlipMargin, FlipSettings};
use crate::hypotheses::{distinct_poses, pick, PickRules};
use crate::index::{ModelIndex, Pose};
use crate::pairs::PairSettings;
use crate::query::Pinhole;
use crate::refine::{IcpResult, CONVERGED};
use crate::scoring::{
    align_translations, align_translations_on_two_cores, score_poses, score_poses_on_two_cores,
    DepthGrid, PoseScore, ScoreSettings,
};
use crate::threads::{self, Handed};
use crate::track::TrackFrameSettings;
use crate::{search, Point3};

/// What `FlipMarginSearch.result` hands Python: the margin and its best
/// rival, if any (rotations (R, 3, 3), translations (R, 3), fits (R,), R ≤ 1).
type FlipMarginResult<'py> = (
    f64,
    Bound<'py, PyArray3<f64>>,
    Bound<'py, PyArray2<f64>>,
    Bound<'py, PyArray1<f64>>,
);

/// Borrows an observed cloud (N, 3) float32, camera frame; a bad shape is an
/// `InvalidCloudError`.
fn cloud_triples<'a>(array: &'a PyReadonlyArray2<'_, f32>, name: &str) -> PyResult<&'a [Point3]> {
    triples(array, name).map_err(InvalidCloudError::new_err)
}

/// The nearest observed depth along each ray of an observed cloud (camera
/// frame, metres): what scoring's free-space test reads. Built once per
/// query, with cells of about two point `spacing`s. With `scene_depth`
/// (the frame: (H, W) uint16, float32 or float64, C-contiguous, in
/// `scene_depth_scale` units per metre; 0: none), `scene_camera` (fx, fy,
/// cx, cy of its pixels) and `scene_window` (rows top..bottom, columns
/// left..right: the part around the object; the whole frame when None),
/// scoring also tests the model points off the object's silhouette against
/// the scene, each pixel read as the nearest depth within `scene_radius`
/// pixels. With `edge_slack`, the silhouette's edge cells read the nearest
/// depth within one cell (the doubt's test: a real sensor's rim). Immutable.
#[pyclass(frozen, name = "DepthGrid", module = "edgepose._core")]
pub struct PyDepthGrid {
    inner: Arc<DepthGrid>,
}

#[pymethods]
impl PyDepthGrid {
    #[new]
    #[pyo3(signature = (
        cloud, spacing, scene_depth=None, scene_camera=None, scene_radius=2, edge_slack=false,
        scene_window=None, scene_depth_scale=1.0
    ))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        cloud: PyReadonlyArray2<'_, f32>,
        spacing: f64,
        scene_depth: Option<&Bound<'_, PyAny>>,
        scene_camera: Option<[f64; 4]>,
        scene_radius: usize,
        edge_slack: bool,
        scene_window: Option<[usize; 4]>,
        scene_depth_scale: f64,
    ) -> PyResult<Self> {
        guarded(|| {
            let c = cloud_triples(&cloud, "cloud")?;
            if !(spacing.is_finite() && spacing >= 0.0) {
                return Err(PyValueError::new_err(format!(
                    "spacing must be finite and non-negative, got {spacing}"
                )));
            }
            let scene = match (scene_depth, scene_camera) {
                (None, None) => None,
                (Some(depth), Some([fx, fy, cx, cy])) => {
                    if ![fx, fy, cx, cy].iter().all(|v| v.is_finite()) || fx <= 0.0 || fy <= 0.0 {
                        return Err(PyValueError::new_err(
                            "scene_camera must be finite (fx, fy, cx, cy) with positive focal lengths",
                        ));
                    }
                    if !(scene_depth_scale.is_finite() && scene_depth_scale > 0.0) {
                        return Err(PyValueError::new_err(
                            "scene_depth_scale must be a positive number",
                        ));
                    }
                    Some(scene_of_frame(
                        py,
                        depth,
                        scene_window,
                        scene_depth_scale,
                        Pinhole { fx, fy, cx, cy },
                        scene_radius,
                    )?)
                }
                _ => {
                    return Err(PyValueError::new_err(
                        "scene_depth and scene_camera go together: give both or neither",
                    ))
                }
            };
            Ok(Self {
                inner: Arc::new(py.detach(|| {
                    let grid = DepthGrid::new(c, spacing, 2.0);
                    let grid = if edge_slack {
                        grid.with_edge_slack()
                    } else {
                        grid
                    };
                    match scene {
                        Some(scene) => grid.with_scene(scene),
                        None => grid,
                    }
                })),
            })
        })
    }
}

/// A model's points and normals (model frame, metres) with a kd-tree, for
/// verification, scoring and ICP. Immutable: safe to share between threads.
#[pyclass(frozen, name = "ModelIndex", module = "edgepose._core")]
pub struct PyModelIndex {
    inner: Arc<ModelIndex>,
}

#[pymethods]
impl PyModelIndex {
    #[new]
    fn new(py: Python<'_>, model: &PyStandardModel) -> PyResult<Self> {
        guarded(|| {
            let (points, normals) = (model.inner.points.clone(), model.inner.normals.clone());
            Ok(Self {
                inner: Arc::new(py.detach(|| ModelIndex::new(points, normals))),
            })
        })
    }

    /// This index with `model`'s normals, sharing its kd-tree and cells
    /// (no rebuild): `model` must have exactly these points, bit for bit.
    fn with_model(&self, model: &PyStandardModel) -> PyResult<Self> {
        guarded(|| {
            let same = model.inner.points.len() == self.inner.len()
                && model
                    .inner
                    .points
                    .iter()
                    .zip(self.inner.points())
                    .all(|(a, b)| a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits()));
            if !same {
                return Err(PyValueError::new_err(
                    "the model's points differ from the index's: build a ModelIndex of it instead",
                ));
            }
            Ok(Self {
                inner: Arc::new(self.inner.with_normals(model.inner.normals.clone())),
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
            let k = cloud_triples(&keypoints, "keypoints")?;
            let poses = poses_from(&rotations, &translations)?;
            Ok(PyArray1::from_vec(
                py,
                py.detach(|| search::verify(&self.inner, k, &poses)),
            ))
        })
    }

    /// Distance (metres) from each of `points` (N, 3) to the model surface,
    /// for each pose (model → camera: `rotations` (C, 3, 3), `translations`
    /// (C, 3)): `(C, N)`; `along_normal`: to the nearest model point's
    /// tangent plane. `stop_above` (metres): a pose whose mean distance is
    /// plainly above it is not finished, the rest of its row reads inf
    /// (callers that only compare means with it lose nothing). Poses run in
    /// parallel.
    #[pyo3(signature = (points, rotations, translations, along_normal = false, stop_above = None))]
    fn distances<'py>(
        &self,
        py: Python<'py>,
        points: PyReadonlyArray2<'py, f32>,
        rotations: PyReadonlyArray3<'py, f64>,
        translations: PyReadonlyArray2<'py, f64>,
        along_normal: bool,
        stop_above: Option<f64>,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        guarded(|| {
            let p = cloud_triples(&points, "points")?;
            let poses = poses_from(&rotations, &translations)?;
            if let Some(stop) = stop_above.filter(|s| !(s.is_finite() && *s >= 0.0)) {
                return Err(PyValueError::new_err(format!(
                    "stop_above must be finite and non-negative, got {stop}"
                )));
            }
            let flat = py.detach(|| {
                search::point_distances(&self.inner, p, &poses, along_normal, stop_above)
            });
            PyArray1::from_vec(py, flat).reshape([poses.len(), p.len()])
        })
    }

    /// Each pose's translation moved so the `observed` points (camera frame)
    /// land on the model (rotations kept): `translations (C, 3)`; with
    /// `two_cores`, the poses shared with one of the core's threads (the
    /// same translations).
    #[pyo3(signature = (observed, rotations, translations, iterations, max_distance, two_cores = false))]
    #[allow(clippy::too_many_arguments)]
    fn align_translations<'py>(
        &self,
        py: Python<'py>,
        observed: PyReadonlyArray2<'py, f32>,
        rotations: PyReadonlyArray3<'py, f64>,
        translations: PyReadonlyArray2<'py, f64>,
        iterations: usize,
        max_distance: f64,
        two_cores: bool,
    ) -> PyResult<Bound<'py, PyArray2<f64>>> {
        guarded(|| {
            let o = cloud_triples(&observed, "observed")?;
            let poses = poses_from(&rotations, &translations)?;
            if !(max_distance.is_finite() && max_distance >= 0.0) {
                return Err(PyValueError::new_err(format!(
                    "max_distance must be finite and non-negative, got {max_distance}"
                )));
            }
            let out = py.detach(|| {
                if two_cores {
                    align_translations_on_two_cores(
                        &self.inner,
                        o,
                        &poses,
                        iterations,
                        max_distance,
                    )
                } else {
                    align_translations(&self.inner, o, &poses, iterations, max_distance)
                }
            });
            Ok(translations_array(py, out.iter().map(|p| &p.translation)))
        })
    }

    /// Scores each candidate pose (model → camera: `rotations` (C, 3, 3),
    /// `translations` (C, 3)) against the `observed` points and the whole
    /// observed cloud's `free_space` grid: [`PyScoreResults`] (see the
    /// core's `scoring` module); with `two_cores`, the poses shared with one
    /// of the core's threads (the same scores).
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (
        observed, free_space, rotations, translations, inlier_distance, free_space_tolerance,
        model_stride, two_cores = false,
    ))]
    fn score<'py>(
        &self,
        py: Python<'py>,
        observed: PyReadonlyArray2<'py, f32>,
        free_space: &Bound<'py, PyDepthGrid>,
        rotations: PyReadonlyArray3<'py, f64>,
        translations: PyReadonlyArray2<'py, f64>,
        inlier_distance: f64,
        free_space_tolerance: f64,
        model_stride: usize,
        two_cores: bool,
    ) -> PyResult<PyScoreResults> {
        guarded(|| {
            let o = cloud_triples(&observed, "observed")?;
            let grid = &free_space.get().inner;
            let poses = poses_from(&rotations, &translations)?;
            if ![inlier_distance, free_space_tolerance]
                .iter()
                .all(|v| v.is_finite() && *v >= 0.0)
            {
                return Err(PyValueError::new_err(
                    "distances must be finite and non-negative",
                ));
            }
            let settings = ScoreSettings {
                inlier_distance,
                free_space_tolerance,
                model_stride,
            };
            let scores = py.detach(|| {
                if two_cores {
                    score_poses_on_two_cores(&self.inner, o, grid, &poses, &settings)
                } else {
                    score_poses(&self.inner, o, grid, &poses, &settings)
                }
            });
            Ok(PyScoreResults { scores })
        })
    }

    /// Stage 5's pick among refined hypotheses (model → camera:
    /// `rotations` (H, 3, 3), `translations` (H, 3); their coarse ICP's
    /// `inliers` (H,) and `rmse` (H,)), scored on the `observed` points
    /// against the `free_space` grid by `rules` (see the core's
    /// `hypotheses` module); `centroid` (3,) is the observed one (camera
    /// frame). A near tie's hypotheses (a list of indices, the pick first)
    /// go to `polish_tie`, which returns their polishes as `IcpResults`.
    /// `(pick, its tie polish or None, scores (ScoreResults), usable (H,)
    /// bool, margin, rmse_ratio)`, or None when no hypothesis is usable.
    #[allow(clippy::too_many_arguments, clippy::type_complexity)]
    fn pick_hypothesis<'py>(
        &self,
        py: Python<'py>,
        observed: PyReadonlyArray2<'py, f32>,
        free_space: &Bound<'py, PyDepthGrid>,
        rotations: PyReadonlyArray3<'py, f64>,
        translations: PyReadonlyArray2<'py, f64>,
        inliers: PyReadonlyArray1<'py, u32>,
        rmse: PyReadonlyArray1<'py, f64>,
        centroid: PyReadonlyArray1<'py, f64>,
        rules: &PyPickRules,
        polish_tie: Bound<'py, PyAny>,
    ) -> PyResult<
        Option<(
            usize,
            Option<PyIcpResults>,
            PyScoreResults,
            Bound<'py, PyArray1<bool>>,
            f64,
            f64,
        )>,
    > {
        guarded(|| {
            let o = cloud_triples(&observed, "observed")?;
            let grid = &free_space.get().inner;
            let poses = poses_from(&rotations, &translations)?;
            let inliers: Vec<usize> = inliers.as_array().iter().map(|&i| i as usize).collect();
            let rmse = rmse.as_slice()?;
            let centroid = vector3_from(&centroid, "centroid")?;
            if inliers.len() != poses.len() || rmse.len() != poses.len() {
                return Err(PyValueError::new_err(
                    "one inlier count and RMSE per hypothesis",
                ));
            }
            let polish_tie = polish_tie.unbind();
            let polish = |tie: &[usize]| -> PyResult<Vec<IcpResult>> {
                Python::attach(|py| {
                    let out = polish_tie.bind(py).call1((tie.to_vec(),))?;
                    let results = &out.cast::<PyIcpResults>()?.get().results;
                    if results.len() != tie.len() {
                        return Err(PyValueError::new_err(
                            "polish_tie must return one result per hypothesis",
                        ));
                    }
                    Ok(results.clone())
                })
            };
            let rules = rules.inner;
            let index = &self.inner;
            let picked = py.detach(|| {
                pick(
                    index, o, grid, &poses, &inliers, rmse, &centroid, &rules, polish,
                )
            })?;
            Ok(picked.map(|p| {
                (
                    p.pick,
                    p.polish.map(|r| PyIcpResults { results: vec![r] }),
                    PyScoreResults { scores: p.scores },
                    PyArray1::from_vec(py, p.usable),
                    p.margin,
                    p.rmse_ratio,
                )
            }))
        })
    }

    /// Up to `count` of the poses (model → camera: `rotations` (H, 3, 3),
    /// `translations` (H, 3)), taken in `order` where `allowed` (H,), each
    /// farther than `rival_distance` metres (ADD, or ADD-S when
    /// `symmetric`, on the model's first `points` points) from pose 0 and
    /// from those taken before: see the core's `hypotheses::distinct_poses`.
    #[allow(clippy::too_many_arguments)]
    fn distinct_poses(
        &self,
        py: Python<'_>,
        rotations: PyReadonlyArray3<'_, f64>,
        translations: PyReadonlyArray2<'_, f64>,
        order: PyReadonlyArray1<'_, i64>,
        allowed: PyReadonlyArray1<'_, bool>,
        count: usize,
        rival_distance: f64,
        symmetric: bool,
        points: usize,
    ) -> PyResult<Vec<usize>> {
        guarded(|| {
            let poses = poses_from(&rotations, &translations)?;
            let allowed = allowed.as_slice()?;
            if allowed.len() != poses.len() {
                return Err(PyValueError::new_err("one allowed flag per pose"));
            }
            let order = indices_into(&order, poses.len(), "poses")?;
            Ok(py.detach(|| {
                distinct_poses(
                    &self.inner,
                    &poses,
                    &order,
                    allowed,
                    count,
                    rival_distance,
                    symmetric,
                    points,
                )
            }))
        })
    }

    /// ADD (ADD-S when `symmetric`) of each pose (model → camera:
    /// `rotations` (H, 3, 3), `translations` (H, 3)) from pose `reference`
    /// of them, on the model's first `points` points, metres: (H,) float64.
    fn pose_distances<'py>(
        &self,
        py: Python<'py>,
        rotations: PyReadonlyArray3<'py, f64>,
        translations: PyReadonlyArray2<'py, f64>,
        reference: usize,
        symmetric: bool,
        points: usize,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        guarded(|| {
            let poses = poses_from(&rotations, &translations)?;
            let Some(target) = poses.get(reference) else {
                return Err(PyValueError::new_err(format!(
                    "reference {reference} is not one of the {} poses",
                    poses.len()
                )));
            };
            let d = py.detach(|| pose_distances(&self.inner, &poses, target, symmetric, points));
            Ok(PyArray1::from_vec(py, d))
        })
    }

    /// The search for the flip margin of the pose (`rotation` (3, 3),
    /// `translation` (3,), model → camera) whose inlier fraction minus
    /// free-space violation on the `observed` points is `own_net`: see the
    /// core's `flips` module. `keypoints`, `observed` and `free_space` are
    /// the query's; `turn_rotations` (K, 3, 3) and `turn_translations`
    /// (K, 3) the model's turns tried (model frame); `settings` how they
    /// are aligned, scored, compared and settled. Its `result()` is found in
    /// the thread that asks for it, or, with `beside`, on one of the core's
    /// threads from now on while the caller goes on (`threads::hand_over`;
    /// the caller runs it when it asks before any thread has started it):
    /// the same either way.
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (
        keypoints, observed, free_space, rotation, translation, own_net, turn_rotations,
        turn_translations, settings, beside = false,
    ))]
    fn flip_margin<'py>(
        &self,
        keypoints: PyReadonlyArray2<'py, f32>,
        observed: PyReadonlyArray2<'py, f32>,
        free_space: &Bound<'py, PyDepthGrid>,
        rotation: PyReadonlyArray2<'py, f64>,
        translation: PyReadonlyArray1<'py, f64>,
        own_net: f64,
        turn_rotations: PyReadonlyArray3<'py, f64>,
        turn_translations: PyReadonlyArray2<'py, f64>,
        settings: &PyFlipSettings,
        beside: bool,
    ) -> PyResult<PyFlipMarginSearch> {
        guarded(|| {
            // Copies (a few KB) the search owns: it may outlive this call.
            let keypoints = cloud_triples(&keypoints, "keypoints")?.to_vec();
            let observed = cloud_triples(&observed, "observed")?.to_vec();
            let grid = Arc::clone(&free_space.get().inner);
            let index = Arc::clone(&self.inner);
            let vector =
                |a: &PyReadonlyArray1<'py, f64>, name: &str| -> PyResult<nalgebra::Vector3<f64>> {
                    match a.as_slice() {
                        Ok([x, y, z]) => Ok(nalgebra::Vector3::new(*x, *y, *z)),
                        _ => Err(PyValueError::new_err(format!(
                            "{name} must be 3 contiguous values"
                        ))),
                    }
                };
            let matrix =
                |a: &PyReadonlyArray2<'py, f64>, name: &str| -> PyResult<nalgebra::Matrix3<f64>> {
                    let view = a.as_array();
                    if view.shape() != [3, 3] {
                        return Err(PyValueError::new_err(format!("{name} must be 3 × 3")));
                    }
                    Ok(nalgebra::Matrix3::from_fn(|i, j| view[[i, j]]))
                };
            let pose = Pose {
                rotation: matrix(&rotation, "rotation")?,
                translation: vector(&translation, "translation")?,
            };
            let turns = poses_from(&turn_rotations, &turn_translations)?;
            let settings = settings.inner;
            let search = move || {
                flip_margin(
                    &index, &keypoints, &observed, &grid, &pose, own_net, &turns, &settings,
                )
            };
            let handed = if beside {
                threads::hand_over(search)
            } else {
                threads::later(search)
            };
            Ok(PyFlipMarginSearch {
                state: Mutex::new(FlipSearchState::Searching(Some(handed))),
            })
        })
    }

    /// Pose hypotheses voted for by point pairs of the observed `cloud`
    /// (camera frame, metres): `(rotations (H, 3, 3), translations (H, 3),
    /// votes (H,))`, model → camera, most votes first; at most `poses`.
    /// `scene_points` of the cloud vote, every `reference_stride`-th of
    /// them as a reference point. The model's pair table is built on the
    /// first call.
    fn pair_poses<'py>(
        &self,
        py: Python<'py>,
        cloud: PyReadonlyArray2<'py, f32>,
        scene_points: usize,
        reference_stride: usize,
        poses: usize,
    ) -> PyResult<Bound<'py, PyAny>> {
        guarded(|| {
            let c = cloud_triples(&cloud, "cloud")?;
            if scene_points == 0 || reference_stride == 0 {
                return Err(PyValueError::new_err(
                    "scene_points and reference_stride must be positive",
                ));
            }
            let settings = PairSettings {
                scene_points,
                reference_stride,
                poses,
                ..PairSettings::default()
            };
            let found = py.detach(|| self.inner.pair_poses(c, &settings));
            (
                rotations_array(py, found.iter().map(|v| &v.pose.rotation)),
                translations_array(py, found.iter().map(|v| &v.pose.translation)),
                PyArray1::from_vec(py, found.iter().map(|v| v.votes).collect()),
            )
                .into_pyobject(py)
                .map(|t| t.into_any())
        })
    }

    /// One tracked frame ([`crate::track::track_frame`]): ICP of the
    /// subsampled observed `points` from the predicted pose (model → camera:
    /// `rotations` (1, 3, 3), `translations` (1, 3)), then the result scored
    /// against every observed `seen` point's free space with
    /// `free_space_tolerance` metres, and against the scene around it given
    /// the frame (`depth` as `estimate` takes it, `k`, `depth_scale`, and the
    /// model's `box_corners` (8, 3), model frame): a [`PyTrackedFit`].
    #[pyo3(signature = (
        points, seen, rotations, translations, free_space_tolerance, settings,
        depth=None, k=None, depth_scale=1.0, box_corners=None
    ))]
    #[allow(clippy::too_many_arguments)]
    fn track_frame(
        &self,
        py: Python<'_>,
        points: PyReadonlyArray2<'_, f32>,
        seen: PyReadonlyArray2<'_, f32>,
        rotations: PyReadonlyArray3<'_, f64>,
        translations: PyReadonlyArray2<'_, f64>,
        free_space_tolerance: f64,
        settings: &PyTrackFrameSettings,
        depth: Option<&Bound<'_, PyAny>>,
        k: Option<PyReadonlyArray2<'_, f64>>,
        depth_scale: f64,
        box_corners: Option<PyReadonlyArray2<'_, f64>>,
    ) -> PyResult<PyTrackedFit> {
        guarded(|| {
            let p = cloud_triples(&points, "points")?;
            let s = cloud_triples(&seen, "seen")?;
            let starts = poses_from(&rotations, &translations)?;
            let [start] = starts[..] else {
                return Err(PyValueError::new_err("track_frame takes one start pose"));
            };
            if !(free_space_tolerance.is_finite() && free_space_tolerance >= 0.0) {
                return Err(PyValueError::new_err(
                    "free_space_tolerance must be finite and non-negative",
                ));
            }
            let corners = match &box_corners {
                Some(c) => Some(triples(c, "box_corners").map_err(PyValueError::new_err)?),
                None => None,
            };
            let frame = match (depth, &k, corners) {
                (None, None, None) => None,
                (Some(depth), Some(k), Some(corners)) => Some((depth, k, depth_scale, corners)),
                _ => {
                    return Err(PyValueError::new_err(
                        "depth, k and box_corners go together: give all or none",
                    ))
                }
            };
            let fit = track_frame_of(
                py,
                &self.inner,
                p,
                s,
                start,
                free_space_tolerance,
                frame,
                &settings.inner,
            )?;
            Ok(PyTrackedFit {
                icp: Py::new(
                    py,
                    PyIcpResults {
                        results: vec![fit.icp],
                    },
                )?,
                loose: Py::new(
                    py,
                    PyScoreResults {
                        scores: vec![fit.loose],
                    },
                )?,
                tight: Py::new(
                    py,
                    PyScoreResults {
                        scores: vec![fit.tight],
                    },
                )?,
                sides: fit.sides,
                with_scene: fit.with_scene,
            })
        })
    }

    /// Point-to-plane ICP of `cloud` (camera frame) from each start pose
    /// (model → camera: `rotations` (H, 3, 3), `translations` (H, 3)): one
    /// result per start, in order. A few starts run one after another, or
    /// with `two_cores` split between this thread and one of the core's;
    /// many in parallel (`ModelIndex::refine_each`). Each stops when an
    /// update moves less than `converged` (radians and metres together; an
    /// estimate's `CONVERGED` by default).
    #[pyo3(signature = (cloud, rotations, translations, max_iterations, max_distance, two_cores = false, converged = CONVERGED))]
    #[allow(clippy::too_many_arguments)]
    fn refine(
        &self,
        py: Python<'_>,
        cloud: PyReadonlyArray2<'_, f32>,
        rotations: PyReadonlyArray3<'_, f64>,
        translations: PyReadonlyArray2<'_, f64>,
        max_iterations: usize,
        max_distance: f64,
        two_cores: bool,
        converged: f64,
    ) -> PyResult<PyIcpResults> {
        guarded(|| {
            let c = cloud_triples(&cloud, "cloud")?;
            let starts = poses_from(&rotations, &translations)?;
            let results = py.detach(|| {
                self.inner.refine_each(
                    c,
                    &starts,
                    max_iterations,
                    max_distance,
                    two_cores,
                    converged,
                )
            });
            Ok(PyIcpResults { results })
        })
    }
}

/// `ModelIndex.flip_margin`'s search: found once, on the first `result()`
/// (or beside the caller, handed to one of the core's threads).
#[pyclass(frozen, name = "FlipMarginSearch", module = "edgepose._core")]
pub struct PyFlipMarginSearch {
    state: Mutex<FlipSearchState>,
}

enum FlipSearchState {
    /// `None` only while a thread takes it (a panic there leaves it so).
    Searching(Option<Handed<FlipMargin>>),
    Found(FlipMargin),
}

#[pymethods]
impl PyFlipMarginSearch {
    /// `(margin, rotations (R, 3, 3), translations (R, 3), fits (R,))`: the
    /// best rival (model → camera; R = 1) and its mean truncated distance
    /// to the observed points (metres), or none (R = 0) when no turned pose
    /// is one. Waits for the search while a core thread runs it, or runs it
    /// in this thread (without the GIL).
    fn result<'py>(&self, py: Python<'py>) -> PyResult<FlipMarginResult<'py>> {
        guarded(|| {
            let found = py.detach(|| {
                let mut state = self.state.lock().unwrap_or_else(|p| p.into_inner());
                match &mut *state {
                    FlipSearchState::Found(found) => Ok(*found),
                    FlipSearchState::Searching(handed) => match handed.take() {
                        Some(handed) => {
                            let found = handed.take();
                            *state = FlipSearchState::Found(found);
                            Ok(found)
                        }
                        None => Err(PyValueError::new_err(
                            "this flip margin search failed before (see the first error)",
                        )),
                    },
                }
            })?;
            let rivals: Vec<Pose> = found.rival.into_iter().collect();
            let fits = vec![found.rival_fit; rivals.len()];
            Ok((
                found.margin,
                rotations_array(py, rivals.iter().map(|p| &p.rotation)),
                translations_array(py, rivals.iter().map(|p| &p.translation)),
                PyArray1::from_vec(py, fits),
            ))
        })
    }
}

/// How [`PyModelIndex::flip_margin`] aligns, scores, compares and settles
/// the turned poses ([`FlipSettings`]; distances in metres), built on the
/// Python side (`edgepose.stages.refine`, where each is chosen).
#[pyclass(frozen, name = "FlipSettings", module = "edgepose._core")]
pub struct PyFlipSettings {
    inner: FlipSettings,
}

#[pymethods]
impl PyFlipSettings {
    #[new]
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (
        *, align_iterations, align_distance, inlier_distance, free_space_tolerance, model_stride,
        rival_distance, rival_points, symmetric, settled, settle_iterations, settle_distance,
    ))]
    fn new(
        align_iterations: usize,
        align_distance: f64,
        inlier_distance: f64,
        free_space_tolerance: f64,
        model_stride: usize,
        rival_distance: f64,
        rival_points: usize,
        symmetric: bool,
        settled: usize,
        settle_iterations: usize,
        settle_distance: f64,
    ) -> Self {
        Self {
            inner: FlipSettings {
                align_iterations,
                align_distance,
                score: ScoreSettings {
                    inlier_distance,
                    free_space_tolerance,
                    model_stride,
                },
                rival_distance,
                rival_points,
                symmetric,
                settled,
                settle_iterations,
                settle_distance,
            },
        }
    }

    fn __repr__(&self) -> String {
        format!("{:?}", self.inner)
    }
}

/// How [`PyModelIndex::pick_hypothesis`] picks among refined hypotheses
/// ([`PickRules`]; distances in metres), built on the Python side
/// (`edgepose.stages.refine`, from `EstimateSettings.refine`).
#[pyclass(frozen, name = "PickRules", module = "edgepose._core")]
pub struct PyPickRules {
    inner: PickRules,
}

#[pymethods]
impl PyPickRules {
    #[new]
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (
        *, min_icp_inliers, max_centre_offset, inlier_distance, free_space_tolerance, model_stride,
        inlier_ratio, free_space_margin, tie_polish_within, rival_distance, rival_points, symmetric,
    ))]
    fn new(
        min_icp_inliers: usize,
        max_centre_offset: f64,
        inlier_distance: f64,
        free_space_tolerance: f64,
        model_stride: usize,
        inlier_ratio: f64,
        free_space_margin: f64,
        tie_polish_within: f64,
        rival_distance: f64,
        rival_points: usize,
        symmetric: bool,
    ) -> Self {
        Self {
            inner: PickRules {
                min_icp_inliers,
                max_centre_offset,
                score: ScoreSettings {
                    inlier_distance,
                    free_space_tolerance,
                    model_stride,
                },
                inlier_ratio,
                free_space_margin,
                tie_polish_within,
                rival_distance,
                rival_points,
                symmetric,
            },
        }
    }

    fn __repr__(&self) -> String {
        format!("{:?}", self.inner)
    }
}

/// The scoring terms of each of C poses, in order, as arrays (see the
/// core's `scoring` module). Immutable; every getter returns a new array.
#[pyclass(frozen, name = "ScoreResults", module = "edgepose._core")]
pub struct PyScoreResults {
    scores: Vec<PoseScore>,
}

impl PyScoreResults {
    fn column<'py>(
        &self,
        py: Python<'py>,
        term: impl Fn(&PoseScore) -> f64,
    ) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.scores.iter().map(term).collect())
    }
}

#[pymethods]
impl PyScoreResults {
    fn __len__(&self) -> usize {
        self.scores.len()
    }

    /// (C,) float64 mean distance of the observed points to the posed
    /// model, each at most the inlier distance, metres.
    #[getter]
    fn fit<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.column(py, |s| s.fit)
    }

    /// (C,) float64 share of the observed points within the inlier distance.
    #[getter]
    fn inlier_fraction<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.column(py, |s| s.inlier_fraction)
    }

    /// (C,) float64 share of the camera-facing model points on observed
    /// rays that stand in front of the observed depth (0 with model stride 0).
    #[getter]
    fn free_space_violation<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.column(py, |s| s.free_space_violation)
    }

    /// (C,) float64 share of the camera-facing model points off the observed silhouette.
    #[getter]
    fn off_silhouette<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.column(py, |s| s.off_silhouette)
    }

    /// (C,) float64 smallest eigenvalue of the inliers' mean model n nᵀ.
    #[getter]
    fn translation_constraint<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.column(py, |s| s.translation_constraint)
    }

    /// (C,) float64 share of the camera-facing model points off the
    /// silhouette in front of the scene's depth (0 without a scene).
    #[getter]
    fn scene_violation<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.column(py, |s| s.scene_violation)
    }

    /// Every term at once, as `edgepose.stages.PoseScores` orders them:
    /// `(fit, inlier_fraction, free_space_violation, cost, off_silhouette,
    /// translation_constraint, scene_violation)`, where cost is
    /// `fit / inlier_distance + free_space_weight × (free-space + scene
    /// violations)` (`inlier_distance` in metres), in numpy's order of
    /// operations, so the same values bit for bit.
    #[allow(clippy::type_complexity)]
    fn terms<'py>(
        &self,
        py: Python<'py>,
        inlier_distance: f64,
        free_space_weight: f64,
    ) -> (
        Bound<'py, PyArray1<f64>>,
        Bound<'py, PyArray1<f64>>,
        Bound<'py, PyArray1<f64>>,
        Bound<'py, PyArray1<f64>>,
        Bound<'py, PyArray1<f64>>,
        Bound<'py, PyArray1<f64>>,
        Bound<'py, PyArray1<f64>>,
    ) {
        (
            self.column(py, |s| s.fit),
            self.column(py, |s| s.inlier_fraction),
            self.column(py, |s| s.free_space_violation),
            self.column(py, |s| {
                s.fit / inlier_distance
                    + free_space_weight * (s.free_space_violation + s.scene_violation)
            }),
            self.column(py, |s| s.off_silhouette),
            self.column(py, |s| s.translation_constraint),
            self.column(py, |s| s.scene_violation),
        )
    }
}

/// ICP's outcome for each of H start poses, in order, as arrays.
/// Immutable; every getter returns a new array.
#[pyclass(frozen, name = "IcpResults", module = "edgepose._core")]
pub struct PyIcpResults {
    results: Vec<IcpResult>,
}

#[pymethods]
impl PyIcpResults {
    fn __len__(&self) -> usize {
        self.results.len()
    }

    /// The outcome of start pose ``index`` alone, as results of one.
    fn row(&self, index: usize) -> PyResult<Self> {
        let result = self.results.get(index).ok_or_else(|| {
            PyIndexError::new_err(format!(
                "ICP result {index} asked for, but there are {}",
                self.results.len()
            ))
        })?;
        Ok(Self {
            results: vec![*result],
        })
    }

    /// (H, 3, 3) float64 refined rotations, model → camera.
    #[getter]
    fn rotations<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray3<f64>> {
        rotations_array(py, self.results.iter().map(|r| &r.pose.rotation))
    }

    /// (H, 3) float64 refined translations, metres.
    #[getter]
    fn translations<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        translations_array(py, self.results.iter().map(|r| &r.pose.translation))
    }

    /// (H,) uint32 iterations run.
    #[getter]
    fn iterations<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<u32>> {
        PyArray1::from_vec(
            py,
            self.results.iter().map(|r| r.iterations as u32).collect(),
        )
    }

    /// (H,) bool: the last update moved less than the convergence threshold.
    #[getter]
    fn converged<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<bool>> {
        PyArray1::from_vec(py, self.results.iter().map(|r| r.converged).collect())
    }

    /// (H,) uint32 cloud points paired with the model in the last iteration.
    #[getter]
    fn inliers<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<u32>> {
        PyArray1::from_vec(py, self.results.iter().map(|r| r.inliers as u32).collect())
    }

    /// (H,) float64 root-mean-square point-to-plane distance of the inliers,
    /// metres (NaN when ICP found too few pairs to run).
    #[getter]
    fn rmse<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.results.iter().map(|r| r.rmse).collect())
    }
}

/// The tuning of `ModelIndex.track_frame` ([`TrackFrameSettings`]), built
/// once per tracker on the Python side (`edgepose.track`), distances in metres.
#[pyclass(frozen, name = "TrackFrameSettings", module = "edgepose._core")]
pub struct PyTrackFrameSettings {
    inner: TrackFrameSettings,
}

#[pymethods]
impl PyTrackFrameSettings {
    #[new]
    #[pyo3(signature = (
        *, icp_iterations, icp_max_distance, inlier_distance, tight_inlier_distance, model_stride,
        diameter, scene_radius, scene_margin
    ))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        icp_iterations: usize,
        icp_max_distance: f64,
        inlier_distance: f64,
        tight_inlier_distance: f64,
        model_stride: usize,
        diameter: f64,
        scene_radius: usize,
        scene_margin: f64,
    ) -> PyResult<Self> {
        let distances = [
            icp_max_distance,
            inlier_distance,
            tight_inlier_distance,
            diameter,
            scene_margin,
        ];
        if !distances.iter().all(|v| v.is_finite() && *v >= 0.0) {
            return Err(PyValueError::new_err(
                "track frame distances must be finite and non-negative",
            ));
        }
        Ok(Self {
            inner: TrackFrameSettings {
                icp_iterations,
                icp_max_distance,
                inlier_distance,
                tight_inlier_distance,
                model_stride,
                diameter,
                scene_radius,
                scene_margin,
            },
        })
    }

    fn __repr__(&self) -> String {
        format!("{:?}", self.inner)
    }
}

/// What `ModelIndex.track_frame` found: the ICP result (`icp`, one row),
/// the refined pose's scores at the check's inlier distance (`loose`) and
/// its fit terms at the tight one (`tight`), the observed points'
/// bounding-box `sides` (metres) and whether the scene was read.
#[pyclass(frozen, name = "TrackedFit", module = "edgepose._core")]
pub struct PyTrackedFit {
    icp: Py<PyIcpResults>,
    loose: Py<PyScoreResults>,
    tight: Py<PyScoreResults>,
    sides: [f64; 3],
    with_scene: bool,
}

#[pymethods]
impl PyTrackedFit {
    #[getter]
    fn icp(&self, py: Python<'_>) -> Py<PyIcpResults> {
        self.icp.clone_ref(py)
    }

    #[getter]
    fn loose(&self, py: Python<'_>) -> Py<PyScoreResults> {
        self.loose.clone_ref(py)
    }

    #[getter]
    fn tight(&self, py: Python<'_>) -> Py<PyScoreResults> {
        self.tight.clone_ref(py)
    }

    #[getter]
    fn sides(&self) -> (f64, f64, f64) {
        (self.sides[0], self.sides[1], self.sides[2])
    }

    #[getter]
    fn with_scene(&self) -> bool {
        self.with_scene
    }
}
