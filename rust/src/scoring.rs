//! How well a candidate pose explains what the camera saw, with terms that
//! stay honest when part of the object is hidden or the mask spilled:
//!
//! * **fit**: mean distance from observed points to the posed model,
//!   each distance truncated at the inlier distance, so background points
//!   that the mask picked up cost a bounded amount instead of dominating;
//! * **inlier fraction**: the share of observed points within the inlier
//!   distance of the posed model;
//! * **free-space violation**: the camera sits at the cloud's origin, so
//!   every observed point says its ray was empty up to it. A camera-facing
//!   model point that lands in front of the nearest observation along its
//!   ray, by more than a tolerance, contradicts the view. Surface fit alone
//!   cannot tell a turned-over pose whose back hugs the observed surface
//!   while its other side sticks out towards the camera; this can. Hidden
//!   parts (behind an occluder, outside the mask) are unknown space and
//!   never count;
//! * **scene violation** (only when the frame's depth around the object is
//!   given, [`SceneDepth`]): a camera-facing model point off the object's
//!   observed silhouette is either hidden by something nearer (an occluder:
//!   fine) or it would stand in front of the background the camera saw there
//!   (a contradiction). A pose slid or turned out of an occluder's shadow
//!   shows itself this way.
//!
//! Camera frame (OpenCV), metres.

use std::sync::Arc;

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use crate::index::{as_queries, ModelIndex, Pose};
use crate::query::Pinhole;
use crate::threads;
use crate::Point3;

/// The frame's depth around the object (the whole scene there, not only the
/// object's mask), for the scene-violation test. A model point is compared
/// with the nearest measured depth within `radius` pixels of its pixel, so a
/// point on the object's own jittered edge is compared with the edge, not
/// with the background just beside it.
pub struct SceneDepth {
    pub(crate) camera: Pinhole,
    pub(crate) width: usize,
    pub(crate) height: usize,
    radius: usize,
    depth: Vec<f32>,
}

/// Rows `top..bottom`, columns `left..right` of the `width`-pixel `frame`,
/// each pixel `d as f32 / scale` metres (infinite where not finite or not
/// positive: no measurement), row by row. A window is a few hundred
/// thousand pixels: converted eight at a time where AVX2 is present (the
/// same operations, so the same bits).
fn window_in_metres<T: Copy + Into<f64>>(
    frame: &[T],
    width: usize,
    window: [usize; 4],
    scale: f32,
) -> Vec<f32> {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 is present (checked above).
        return unsafe { window_in_metres_avx2(frame, width, window, scale) };
    }
    window_in_metres_here(frame, width, window, scale)
}

/// [`window_in_metres`] compiled for AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn window_in_metres_avx2<T: Copy + Into<f64>>(
    frame: &[T],
    width: usize,
    window: [usize; 4],
    scale: f32,
) -> Vec<f32> {
    window_in_metres_here(frame, width, window, scale)
}

#[inline(always)]
fn window_in_metres_here<T: Copy + Into<f64>>(
    frame: &[T],
    width: usize,
    [top, bottom, left, right]: [usize; 4],
    scale: f32,
) -> Vec<f32> {
    let mut depth = Vec::with_capacity((bottom - top) * (right - left));
    for v in top..bottom {
        depth.extend(frame[v * width + left..v * width + right].iter().map(|&d| {
            let z = d.into() as f32 / scale;
            if z.is_finite() && z > 0.0 {
                z
            } else {
                f32::INFINITY
            }
        }));
    }
    depth
}

impl SceneDepth {
    /// From a row-major `width`-wide depth image in metres (0 or not finite:
    /// no measurement) and the intrinsics of its pixels; `radius` pixels of
    /// neighbourhood.
    pub fn new(depth: &[f32], width: usize, camera: Pinhole, radius: usize) -> Self {
        let height = depth.len().checked_div(width).unwrap_or(0);
        let whole = [0, height, 0, width];
        Self::from_frame(
            &depth[..width * height],
            [height, width],
            whole,
            1.0,
            camera,
            radius,
        )
        .expect("the whole frame is its own window")
    }

    /// From the `window` (rows `top..bottom`, columns `left..right`) of a
    /// row-major depth frame of `[height, width]` pixels in `depth_scale`
    /// units per metre (0 or not finite: no measurement), `camera` the
    /// frame's intrinsics; `radius` pixels of neighbourhood. Each pixel is
    /// converted in float32 (`depth as f32 / depth_scale as f32`), as numpy's
    /// float32 division would. None when the window is not within the frame
    /// or the frame does not hold `height` × `width` pixels.
    pub fn from_frame<T: Copy + Into<f64>>(
        frame: &[T],
        [height, width]: [usize; 2],
        [top, bottom, left, right]: [usize; 4],
        depth_scale: f64,
        camera: Pinhole,
        radius: usize,
    ) -> Option<Self> {
        if frame.len() != height * width
            || top > bottom
            || left > right
            || bottom > height
            || right > width
        {
            return None;
        }
        let depth = window_in_metres(frame, width, [top, bottom, left, right], depth_scale as f32);
        let camera = Pinhole {
            cx: camera.cx - left as f64,
            cy: camera.cy - top as f64,
            ..camera
        };
        Some(Self {
            camera,
            width: right - left,
            height: bottom - top,
            radius,
            depth,
        })
    }

    /// The pixel (column, row) of `p` (camera frame), if on the image.
    fn pixel(&self, p: &Vector3<f64>) -> Option<(usize, usize)> {
        if p.z <= 0.0 {
            return None;
        }
        let u = (self.camera.fx * p.x / p.z + self.camera.cx).round();
        let v = (self.camera.fy * p.y / p.z + self.camera.cy).round();
        (u >= 0.0 && v >= 0.0 && u < self.width as f64 && v < self.height as f64)
            .then_some((u as usize, v as usize))
    }

    /// The measured depths (infinite: none) within `radius` pixels of pixel (`u`, `v`).
    fn around(&self, u: usize, v: usize) -> impl Iterator<Item = f32> + '_ {
        let (a, b) = (
            u.saturating_sub(self.radius),
            (u + self.radius + 1).min(self.width),
        );
        (v.saturating_sub(self.radius)..(v + self.radius + 1).min(self.height)).flat_map(
            move |row| {
                self.depth[row * self.width + a..row * self.width + b]
                    .iter()
                    .copied()
            },
        )
    }

    /// Whether `p` (camera frame) stands in front of every measured depth
    /// within `radius` pixels of its pixel by more than `tolerance` metres,
    /// its own pixel measured: the model would hide what the camera saw.
    /// A pixel without a measurement (a dark or shiny patch, a steep face, an
    /// edge the sensor lost) is unknown space, even beside measured
    /// background. Stops at the first measurement that is not behind it.
    pub fn in_front(&self, p: &Vector3<f64>, tolerance: f64) -> bool {
        let Some((u, v)) = self.pixel(p) else {
            return false;
        };
        if !self.depth[v * self.width + u].is_finite() {
            return false;
        }
        let limit = (p.z + tolerance) as f32;
        self.around(u, v).all(|z| z > limit)
    }
}

/// The observed depth by viewing direction: the nearest observed depth in
/// each cell of a grid over the normalised image plane `(x/z, y/z)`, and
/// the frame's depth around the object when it is known ([`Self::with_scene`]).
pub struct DepthGrid {
    cell: f64,
    u0: f64,
    v0: f64,
    cols: usize,
    rows: usize,
    nearest: Vec<f32>,
    scene: Option<SceneDepth>,
}

/// Cells per side at most: bounds memory whatever the cloud's spread.
const MAX_GRID_SIDE: usize = 512;

impl DepthGrid {
    /// Grid of `cloud` (camera frame, metres) with cells of about `cells_per_point`
    /// times the cloud's point `spacing` (metres) at its median depth, so
    /// that an observed surface fills its cells without gaps.
    pub fn new(cloud: &[Point3], spacing: f64, cells_per_point: f64) -> Self {
        let front: Vec<(f64, f64, f32)> = cloud
            .iter()
            .filter(|p| p[2] > 0.0)
            .map(|p| (p[0] as f64 / p[2] as f64, p[1] as f64 / p[2] as f64, p[2]))
            .collect();
        if front.is_empty() {
            return Self {
                cell: 1.0,
                u0: 0.0,
                v0: 0.0,
                cols: 0,
                rows: 0,
                nearest: Vec::new(),
                scene: None,
            };
        }
        let mut depths: Vec<f32> = front.iter().map(|p| p.2).collect();
        let mid = depths.len() / 2;
        let median_depth = *depths.select_nth_unstable_by(mid, f32::total_cmp).1 as f64;
        let (mut u0, mut u1, mut v0, mut v1) = (
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
        );
        for &(u, v, _) in &front {
            (u0, u1, v0, v1) = (u0.min(u), u1.max(u), v0.min(v), v1.max(v));
        }
        let span = (u1 - u0).max(v1 - v0);
        let cell = (cells_per_point * spacing / median_depth)
            .max(span / MAX_GRID_SIDE as f64)
            .max(1e-9);
        let cols = ((u1 - u0) / cell) as usize + 1;
        let rows = ((v1 - v0) / cell) as usize + 1;
        let mut nearest = vec![f32::INFINITY; cols * rows];
        for &(u, v, z) in &front {
            let i = ((v - v0) / cell) as usize * cols + ((u - u0) / cell) as usize;
            nearest[i] = nearest[i].min(z);
        }
        Self {
            cell,
            u0,
            v0,
            cols,
            rows,
            nearest,
            scene: None,
        }
    }

    /// This grid with one cell of slack at the edge of the observed
    /// silhouette ([`nearest_around`]): a real sensor's right pose must not
    /// read as doubtful for its rim alone.
    pub fn with_edge_slack(self) -> Self {
        Self {
            nearest: nearest_around(&self.nearest, self.cols, self.rows),
            ..self
        }
    }

    /// This grid with the frame's depth around the object, for the scene-violation test.
    pub fn with_scene(self, scene: SceneDepth) -> Self {
        Self {
            scene: Some(scene),
            ..self
        }
    }

    /// The nearest observed depth (metres) along the ray through `p`
    /// (camera frame), or `None` where nothing was observed: one point's
    /// look-up, the tests' reference for the chunked free-space test.
    #[cfg(test)]
    fn observed_depth(&self, p: &Vector3<f64>) -> Option<f64> {
        if p.z <= 0.0 {
            return None;
        }
        let (cu, cv) = self.cell_of(p.x, p.y, p.z);
        self.depth_in_cell(cu, cv)
    }

    /// The grid coordinates (columns, rows; fractional) of the ray through
    /// the camera-frame point (`x`, `y`, `z`), `z` > 0. Branch-free, so the
    /// free-space loop computes it in vector lanes.
    #[inline(always)]
    fn cell_of(&self, x: f64, y: f64, z: f64) -> (f64, f64) {
        ((x / z - self.u0) / self.cell, (y / z - self.v0) / self.cell)
    }

    /// The nearest observed depth (metres) in the cell at grid coordinates
    /// ([`cell_of`](Self::cell_of)), or `None` off the grid or where nothing
    /// was observed.
    #[inline(always)]
    fn depth_in_cell(&self, cu: f64, cv: f64) -> Option<f64> {
        if cu < 0.0 || cv < 0.0 || cu >= self.cols as f64 || cv >= self.rows as f64 {
            return None;
        }
        let z = self.nearest[cv as usize * self.cols + cu as usize];
        z.is_finite().then_some(z as f64)
    }
}

/// Each observed cell at the edge of the observed silhouette (an unobserved
/// cell among its eight neighbours) takes the nearest observed depth among
/// it and its neighbours; the others keep their own. A real sensor's
/// silhouette is off by a pixel or two (depth and mask registered apart,
/// mixed depth at the edge): a correct pose's rim then stands just in front
/// of an edge cell's depth. One cell (two point spacings) of slack there
/// absorbs that; inside the silhouette the test stays as sharp. For the
/// doubt only: a wrong pose that shows only at the rim is still a worse fit.
fn nearest_around(nearest: &[f32], cols: usize, rows: usize) -> Vec<f32> {
    let mut out = nearest.to_vec();
    for r in 0..rows {
        for c in 0..cols {
            if !nearest[r * cols + c].is_finite() {
                continue;
            }
            let (mut z, mut edge) = (
                f32::INFINITY,
                r == 0 || c == 0 || r + 1 == rows || c + 1 == cols,
            );
            for rr in r.saturating_sub(1)..(r + 2).min(rows) {
                for cc in c.saturating_sub(1)..(c + 2).min(cols) {
                    let around = nearest[rr * cols + cc];
                    edge |= !around.is_finite();
                    z = z.min(around);
                }
            }
            if edge {
                out[r * cols + c] = z;
            }
        }
    }
    out
}

/// Distances of [`score_poses`], metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScoreSettings {
    /// An observed point within this distance of the posed model is an
    /// inlier; farther ones count this much in `fit`.
    pub inlier_distance: f64,
    /// A model point this much in front of the observed depth violates free space.
    pub free_space_tolerance: f64,
    /// Every `model_stride`-th model point takes part in the free-space
    /// test; 0: no free-space test (its terms read 0: the fit terms only).
    pub model_stride: usize,
}

/// The terms of one pose; see the module documentation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseScore {
    /// Mean truncated distance from the observed points to the model, metres.
    pub fit: f64,
    /// Share of observed points within the inlier distance, 0–1.
    pub inlier_fraction: f64,
    /// Share of the camera-facing model points on observed rays that lie in
    /// front of the observation, 0–1 (0 when no model point is on an observed ray).
    pub free_space_violation: f64,
    /// Share of the camera-facing model points that land where nothing was
    /// observed (off the observed silhouette: hidden by an occluder, or a
    /// wrong pose), 0–1 (0 when no model point faces the camera).
    pub off_silhouette: f64,
    /// Smallest eigenvalue of the mean `n nᵀ` over the model normals nearest
    /// to the inlier points: how firmly the seen surface pins the pose's
    /// translation. 0 when it could slide along some direction without
    /// leaving the surface (one face of a box, the side of a can), up to
    /// 1/3 for normals spread evenly; 0 with fewer than 3 inliers.
    pub translation_constraint: f64,
    /// Share of the camera-facing model points that land off the observed
    /// silhouette in front of the scene's measured depth there (by more than
    /// the free-space tolerance), 0–1; 0 when the grid has no scene.
    pub scene_violation: f64,
}

impl PoseScore {
    /// Explained share net of what contradicts the view: the inlier fraction
    /// minus the free-space and scene violations (how hypotheses compete).
    pub fn net(&self) -> f64 {
        self.inlier_fraction - self.free_space_violation - self.scene_violation
    }
}

/// Moves each pose's translation so the `observed` points (camera frame)
/// land on the model: `iterations` times, the mean offset from each point to
/// its nearest model point (pairs farther than `max_distance` metres
/// ignored) is added. A candidate's translation comes from centroids, which
/// an occluder or a cut mask shifts; its rotation is kept as retrieved.
pub fn align_translations(
    index: &ModelIndex,
    observed: &[Point3],
    poses: &[Pose],
    iterations: usize,
    max_distance: f64,
) -> Vec<Pose> {
    each_pose(poses, |start| {
        align_translation(index, observed, start, iterations, max_distance)
    })
}

/// [`align_translations`] of the poses, shared with one of the core's
/// threads when there are 2 to [`PARALLEL_FROM`] ([`threads::on_two_cores`]:
/// each thread takes the next pose not yet taken): the same translations,
/// sooner where a second core is free.
pub fn align_translations_on_two_cores(
    index: &Arc<ModelIndex>,
    observed: &[Point3],
    poses: &[Pose],
    iterations: usize,
    max_distance: f64,
) -> Vec<Pose> {
    if !(2..PARALLEL_FROM).contains(&poses.len()) {
        return align_translations(index, observed, poses, iterations, max_distance);
    }
    let (index, observed) = (Arc::clone(index), observed.to_vec());
    threads::on_two_cores(poses.to_vec(), move |start| {
        align_translation(&index, &observed, start, iterations, max_distance)
    })
}

/// One pose of [`align_translations`].
fn align_translation(
    index: &ModelIndex,
    observed: &[Point3],
    start: &Pose,
    iterations: usize,
    max_distance: f64,
) -> Pose {
    let mut pose = *start;
    for _ in 0..iterations {
        let to_model = pose.inverse();
        let (mut shift, mut paired) = (Vector3::zeros(), 0usize);
        let moved: Vec<Vector3<f64>> = observed.iter().map(|p| to_model.apply(p)).collect();
        let found = index.nearest_each_within(&as_queries(&moved), max_distance);
        for (&m, found) in moved.iter().zip(found) {
            if let Some((i, _)) = found {
                let q = index.points()[i];
                shift += Vector3::new(q[0] as f64, q[1] as f64, q[2] as f64) - m;
                paired += 1;
            }
        }
        if paired == 0 {
            break;
        }
        // p = R·m + t should become R·q + t, so t moves by −R·(q − m).
        pose.translation -= pose.rotation * (shift / paired as f64);
    }
    pose
}

/// Poses handled at once in parallel from this many on (the second search's
/// 64–256 candidates: several milliseconds of work). Fewer finish within a
/// millisecond, less than waking the thread pool can cost on a busy CPU.
const PARALLEL_FROM: usize = 64;

/// `f` of each pose, in order; in parallel for [`PARALLEL_FROM`] poses or
/// more (each pose's result is its own, so the results are the same).
fn each_pose<T: Send>(poses: &[Pose], f: impl Fn(&Pose) -> T + Sync + Send) -> Vec<T> {
    if poses.len() >= PARALLEL_FROM {
        threads::map(poses, 16, f)
    } else {
        poses.iter().map(f).collect()
    }
}

/// Every `stride`-th model point and its normal (model frame, metres), as
/// f64 columns: the free-space test transforms them in vector lanes. Empty
/// for stride 0 (no free-space test).
struct ModelSample {
    points: [Vec<f64>; 3],
    normals: [Vec<f64>; 3],
}

impl ModelSample {
    fn new(index: &ModelIndex, stride: usize) -> Self {
        let tested = if stride == 0 { 0 } else { index.points().len() };
        let column = |of: &[Point3], axis: usize| -> Vec<f64> {
            of[..tested]
                .iter()
                .step_by(stride.max(1))
                .map(|p| p[axis] as f64)
                .collect()
        };
        let normals = &index.normals()[..tested];
        Self {
            points: std::array::from_fn(|a| column(index.points(), a)),
            normals: std::array::from_fn(|a| column(normals, a)),
        }
    }
}

/// The free-space test's counts of one pose: the camera-facing model points
/// of the sample, those on observed rays, those of them in front of the
/// observation, and those off the rays in front of the scene.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct FreeSpaceCounts {
    facing: usize,
    on_rays: usize,
    violations: usize,
    in_front_of_scene: usize,
}

/// Model points posed a chunk at a time: the transform, the facing test and
/// the grid coordinates run over a chunk in vector lanes, the grid look-ups
/// after it.
const CHUNK: usize = 64;

/// [`FreeSpaceCounts`] of `pose` (model → camera) for the `sample`'s points
/// against the `grid`; a model point `tolerance` metres or more in front of
/// what was seen violates. The operations of `pose.apply` and of nalgebra's
/// products in the same order, so the same counts as point by point.
fn free_space_counts(
    sample: &ModelSample,
    grid: &DepthGrid,
    pose: &Pose,
    tolerance: f64,
) -> FreeSpaceCounts {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 is present (checked above).
        return unsafe { free_space_counts_avx2(sample, grid, pose, tolerance) };
    }
    counts_in(sample, grid, pose, tolerance)
}

/// [`free_space_counts`] compiled for AVX2: its lanes 4 f64 wide rather
/// than SSE2's 2; the same operations, so the same counts.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn free_space_counts_avx2(
    sample: &ModelSample,
    grid: &DepthGrid,
    pose: &Pose,
    tolerance: f64,
) -> FreeSpaceCounts {
    counts_in(sample, grid, pose, tolerance)
}

#[inline(always)]
fn counts_in(
    sample: &ModelSample,
    grid: &DepthGrid,
    pose: &Pose,
    tolerance: f64,
) -> FreeSpaceCounts {
    let mut counts = FreeSpaceCounts::default();
    let mut chunk = PosedChunk::default();
    for start in (0..sample.points[0].len()).step_by(CHUNK) {
        let len = chunk.pose(sample, start, pose, grid);
        let PosedChunk { x, y, z, dot, u, v } = &chunk;
        for k in 0..len {
            if dot[k] >= 0.0 {
                continue; // faces away from the camera: hidden by the object itself
            }
            counts.facing += 1;
            let observed = if z[k] > 0.0 {
                grid.depth_in_cell(u[k], v[k])
            } else {
                None
            };
            if let Some(depth) = observed {
                counts.on_rays += 1;
                if z[k] < depth - tolerance {
                    counts.violations += 1;
                }
            } else if let Some(scene) = &grid.scene {
                if scene.in_front(&Vector3::new(x[k], y[k], z[k]), tolerance) {
                    counts.in_front_of_scene += 1;
                }
            }
        }
    }
    counts
}

/// Up to [`CHUNK`] sample points posed in the camera frame (metres): their
/// coordinates, the dot product of each posed normal with its point (< 0:
/// the point faces the camera), and their depth-grid coordinates
/// ([`DepthGrid::cell_of`]; meaningless for `z` ≤ 0).
struct PosedChunk {
    x: [f64; CHUNK],
    y: [f64; CHUNK],
    z: [f64; CHUNK],
    dot: [f64; CHUNK],
    u: [f64; CHUNK],
    v: [f64; CHUNK],
}

impl Default for PosedChunk {
    fn default() -> Self {
        Self {
            x: [0.0; CHUNK],
            y: [0.0; CHUNK],
            z: [0.0; CHUNK],
            dot: [0.0; CHUNK],
            u: [0.0; CHUNK],
            v: [0.0; CHUNK],
        }
    }
}

impl PosedChunk {
    /// The sample's points `start..` (at most [`CHUNK`]) under `pose`; how
    /// many. Branch-free, so it runs in vector lanes; `R·p + t`, `R·n` and
    /// the dot product in nalgebra's order of operations
    /// (`((r₀x + r₁y) + r₂z) + t`), so each value is bit for bit what
    /// `pose.apply` and `Vector3::dot` give.
    #[inline(always)]
    fn pose(&mut self, sample: &ModelSample, start: usize, pose: &Pose, grid: &DepthGrid) -> usize {
        let (r, t) = (&pose.rotation, &pose.translation);
        let len = CHUNK.min(sample.points[0].len() - start);
        let [px, py, pz] = sample.points.each_ref().map(|c| &c[start..start + len]);
        let [nx, ny, nz] = sample.normals.each_ref().map(|c| &c[start..start + len]);
        for k in 0..len {
            let (a, b, c) = (px[k], py[k], pz[k]);
            let x = r[(0, 0)] * a + r[(0, 1)] * b + r[(0, 2)] * c + t.x;
            let y = r[(1, 0)] * a + r[(1, 1)] * b + r[(1, 2)] * c + t.y;
            let z = r[(2, 0)] * a + r[(2, 1)] * b + r[(2, 2)] * c + t.z;
            let (a, b, c) = (nx[k], ny[k], nz[k]);
            let n = [
                r[(0, 0)] * a + r[(0, 1)] * b + r[(0, 2)] * c,
                r[(1, 0)] * a + r[(1, 1)] * b + r[(1, 2)] * c,
                r[(2, 0)] * a + r[(2, 1)] * b + r[(2, 2)] * c,
            ];
            self.dot[k] = n[0] * x + n[1] * y + n[2] * z;
            (self.x[k], self.y[k], self.z[k]) = (x, y, z);
            (self.u[k], self.v[k]) = grid.cell_of(x, y, z);
        }
        len
    }
}

/// Scores each pose (model → camera) against `observed` points and the
/// `grid` of the whole observed cloud.
pub fn score_poses(
    index: &ModelIndex,
    observed: &[Point3],
    grid: &DepthGrid,
    poses: &[Pose],
    settings: &ScoreSettings,
) -> Vec<PoseScore> {
    let sample = ModelSample::new(index, settings.model_stride);
    each_pose(poses, |pose| {
        score_pose(index, &sample, observed, grid, pose, settings)
    })
}

/// [`score_poses`] of the poses, shared with one of the core's threads when
/// there are 2 to [`PARALLEL_FROM`] ([`threads::on_two_cores`]: each thread
/// takes the next pose not yet taken): the same scores, sooner where a
/// second core is free.
pub fn score_poses_on_two_cores(
    index: &Arc<ModelIndex>,
    observed: &[Point3],
    grid: &Arc<DepthGrid>,
    poses: &[Pose],
    settings: &ScoreSettings,
) -> Vec<PoseScore> {
    if !(2..PARALLEL_FROM).contains(&poses.len()) {
        return score_poses(index, observed, grid, poses, settings);
    }
    let sample = ModelSample::new(index, settings.model_stride);
    let (index, observed, grid, settings) = (
        Arc::clone(index),
        observed.to_vec(),
        Arc::clone(grid),
        *settings,
    );
    threads::on_two_cores(poses.to_vec(), move |pose| {
        score_pose(&index, &sample, &observed, &grid, pose, &settings)
    })
}

fn score_pose(
    index: &ModelIndex,
    sample: &ModelSample,
    observed: &[Point3],
    grid: &DepthGrid,
    pose: &Pose,
    settings: &ScoreSettings,
) -> PoseScore {
    let to_model = pose.inverse();
    let (mut total, mut inliers) = (0.0f64, 0usize);
    let mut normal_spread = Matrix3::<f64>::zeros();
    let moved: Vec<Vector3<f64>> = observed.iter().map(|p| to_model.apply(p)).collect();
    // Beyond the inlier distance a pair counts as that distance: its
    // nearest model point need not be found.
    for found in index.nearest_each_within(&as_queries(&moved), settings.inlier_distance) {
        match found {
            Some((i, sq)) => {
                inliers += 1;
                total += (sq as f64).sqrt();
                let n = index.normals()[i];
                let n = Vector3::new(n[0] as f64, n[1] as f64, n[2] as f64);
                normal_spread += n * n.transpose();
            }
            None => total += settings.inlier_distance,
        }
    }
    let translation_constraint = if inliers >= 3 {
        let eigen = SymmetricEigen::new(normal_spread / inliers as f64);
        eigen.eigenvalues.min().max(0.0)
    } else {
        0.0
    };
    let FreeSpaceCounts {
        facing,
        on_rays,
        violations,
        in_front_of_scene,
    } = free_space_counts(sample, grid, pose, settings.free_space_tolerance);
    let count = observed.len().max(1) as f64;
    PoseScore {
        fit: total / count,
        inlier_fraction: inliers as f64 / count,
        free_space_violation: if on_rays == 0 {
            0.0
        } else {
            violations as f64 / on_rays as f64
        },
        off_silhouette: if facing == 0 {
            0.0
        } else {
            (facing - on_rays) as f64 / facing as f64
        },
        translation_constraint,
        scene_violation: in_front_of_scene as f64 / facing.max(1) as f64,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;
    use nalgebra::Rotation3;

    /// Points and outward normals of an axis-aligned box's surface, `spacing` apart.
    fn box_surface(centre: [f32; 3], half: [f32; 3], spacing: f32) -> (Vec<Point3>, Vec<Point3>) {
        let (mut points, mut normals) = (Vec::new(), Vec::new());
        for axis in 0..3 {
            let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
            let (na, nb) = (
                (2.0 * half[a] / spacing) as usize + 1,
                (2.0 * half[b] / spacing) as usize + 1,
            );
            for sign in [-1.0f32, 1.0] {
                for i in 0..na {
                    for j in 0..nb {
                        let mut p = centre;
                        p[axis] += sign * half[axis];
                        p[a] += -half[a] + 2.0 * half[a] * i as f32 / (na - 1).max(1) as f32;
                        p[b] += -half[b] + 2.0 * half[b] * j as f32 / (nb - 1).max(1) as f32;
                        let mut n = [0.0f32; 3];
                        n[axis] = sign;
                        points.push(p);
                        normals.push(n);
                    }
                }
            }
        }
        (points, normals)
    }

    /// A 10 × 10 × 1 cm plate with a 2 × 2 × 3 cm knob on its +z face.
    /// Seen from −z (knob hidden behind), the plate turned over about y puts
    /// its other face exactly where the seen face was: every observed point
    /// still lies on the model, but the knob now juts towards the camera.
    fn plate_with_knob() -> (Vec<Point3>, Vec<Point3>) {
        let (mut points, mut normals) = box_surface([0.0; 3], [0.05, 0.05, 0.005], 0.002);
        let (p, n) = box_surface([0.0, 0.0, 0.02], [0.01, 0.01, 0.015], 0.002);
        points.extend(p);
        normals.extend(n);
        (points, normals)
    }

    /// The plate's model index and its camera-facing points posed by
    /// `truth` (model → camera): what a camera sees of it.
    fn plate_seen_at(truth: &Pose) -> (ModelIndex, Vec<Point3>) {
        let (points, normals) = plate_with_knob();
        let cloud = posed(&points, &normals, truth, true);
        (ModelIndex::new(points, normals), cloud)
    }

    fn posed(
        points: &[Point3],
        normals: &[Point3],
        pose: &Pose,
        camera_facing_only: bool,
    ) -> Vec<Point3> {
        points
            .iter()
            .zip(normals)
            .filter(|(p, n)| {
                let pc = pose.apply(p);
                let nc = pose.rotation * Vector3::new(n[0] as f64, n[1] as f64, n[2] as f64);
                !camera_facing_only || nc.dot(&pc) < 0.0
            })
            .map(|(p, _)| {
                let v = pose.apply(p);
                [v.x as f32, v.y as f32, v.z as f32]
            })
            .collect()
    }

    fn settings() -> ScoreSettings {
        ScoreSettings {
            inlier_distance: 0.005,
            free_space_tolerance: 0.005,
            model_stride: 1,
        }
    }

    #[test]
    fn the_grid_returns_the_nearest_depth_on_a_ray() {
        let cloud: Vec<Point3> = vec![[0.0, 0.0, 0.5], [0.0, 0.0, 0.7], [0.1, 0.0, 0.5]];
        let grid = DepthGrid::new(&cloud, 0.01, 2.0);
        assert_eq!(grid.observed_depth(&Vector3::new(0.0, 0.0, 0.3)), Some(0.5));
        assert_eq!(
            grid.observed_depth(&Vector3::new(0.0, 0.0, -0.3)),
            None,
            "behind the camera"
        );
        assert_eq!(
            grid.observed_depth(&Vector3::new(0.0, 0.5, 0.5)),
            None,
            "outside what was seen"
        );
    }

    #[test]
    fn free_space_rejects_a_flipped_pose_that_surface_fit_cannot() {
        let truth = Pose {
            rotation: Matrix3::identity(),
            translation: Vector3::new(0.0, 0.0, 0.5),
        };
        let (index, cloud) = plate_seen_at(&truth);
        let flip = Pose {
            rotation: *Rotation3::from_euler_angles(0.0, std::f64::consts::PI, 0.0).matrix(),
            ..truth
        };
        let grid = DepthGrid::new(&cloud, 0.002, 2.0);
        let scores = score_poses(&index, &cloud, &grid, &[truth, flip], &settings());
        assert!(
            scores[0].inlier_fraction > 0.999 && scores[1].inlier_fraction > 0.999,
            "{scores:?}"
        );
        assert!(
            (scores[0].fit - scores[1].fit).abs() < 1e-4,
            "surface fit alone should not tell them apart: {scores:?}"
        );
        assert!(scores[0].free_space_violation < 0.005, "{scores:?}");
        assert!(scores[1].free_space_violation > 0.03, "{scores:?}");
        // A model stride of 0 leaves the free-space test out: the fit terms alone.
        let fit_only = ScoreSettings {
            model_stride: 0,
            ..settings()
        };
        for (whole, fit) in scores.iter().zip(score_poses(
            &index,
            &cloud,
            &grid,
            &[truth, flip],
            &fit_only,
        )) {
            assert_eq!(
                (fit.fit, fit.inlier_fraction, fit.translation_constraint),
                (
                    whole.fit,
                    whole.inlier_fraction,
                    whole.translation_constraint
                )
            );
            assert_eq!(
                (
                    fit.free_space_violation,
                    fit.off_silhouette,
                    fit.scene_violation
                ),
                (0.0, 0.0, 0.0)
            );
        }
    }

    #[test]
    fn edge_slack_reads_the_rim_nearer_and_leaves_the_inside_alone() {
        // A 10 × 10 cm patch at 1 m, every 2 mm, whose outermost
        // two rings were measured 1 cm too far (mixed depth at a real silhouette).
        let mut cloud = Vec::new();
        for i in 0..=50 {
            for j in 0..=50 {
                let rim = i <= 1 || j <= 1 || i >= 49 || j >= 49;
                let z = if rim { 1.01 } else { 1.0 };
                let (x, y) = (-0.05 + 0.002 * i as f64, -0.05 + 0.002 * j as f64);
                cloud.push([(x * z) as f32, (y * z) as f32, z as f32]);
            }
        }
        let exact = DepthGrid::new(&cloud, 0.002, 2.0);
        let slack = DepthGrid::new(&cloud, 0.002, 2.0).with_edge_slack();
        let corner = Vector3::new(-0.0499, -0.0499, 1.0);
        let inside = Vector3::new(0.0, 0.0, 1.0);
        assert!((exact.observed_depth(&corner).unwrap() - 1.01).abs() < 1e-6);
        assert!((slack.observed_depth(&corner).unwrap() - 1.0).abs() < 1e-6);
        assert_eq!(exact.observed_depth(&inside), slack.observed_depth(&inside));
        // Unobserved space stays unobserved.
        let outside = Vector3::new(0.2, 0.2, 1.0);
        assert!(
            exact.observed_depth(&outside).is_none() && slack.observed_depth(&outside).is_none()
        );
    }

    /// The plate tilted half a metre in front of the camera.
    fn tilted() -> Pose {
        Pose {
            rotation: *Rotation3::from_euler_angles(0.3, -0.2, 0.5).matrix(),
            translation: Vector3::new(0.01, 0.0, 0.5),
        }
    }

    #[test]
    fn aligning_translations_undoes_a_shift() {
        let truth = tilted();
        let (index, cloud) = plate_seen_at(&truth);
        let shifted = Pose {
            translation: truth.translation + Vector3::new(0.006, -0.004, 0.008),
            ..truth
        };
        let aligned = align_translations(&index, &cloud, &[shifted], 10, 0.03)[0];
        // Depth (what free space judges) is resolved at once; sliding along
        // the plate's plane only converges slowly (edges alone constrain it).
        let error = aligned.translation - truth.translation;
        assert!(
            error.z.abs() < 0.001 && error.norm() < 0.5 * 0.0108,
            "{error:?}"
        );
        assert_eq!(aligned.rotation, truth.rotation);
    }

    #[test]
    fn two_cores_align_and_score_as_one() {
        let truth = tilted();
        let (index, cloud) = plate_seen_at(&truth);
        let index = Arc::new(index);
        let grid = Arc::new(DepthGrid::new(&cloud, 0.002, 2.0));
        // 1 pose (run as it is), a first search's 16, and 64 (all of the pool's threads).
        for count in [1, 16, PARALLEL_FROM] {
            let poses: Vec<Pose> = (0..count)
                .map(|i| Pose {
                    rotation: *Rotation3::from_euler_angles(0.3, -0.2, 0.5 + 0.05 * i as f64)
                        .matrix(),
                    translation: truth.translation + Vector3::new(0.001 * i as f64, -0.002, 0.004),
                })
                .collect();
            assert_eq!(
                align_translations_on_two_cores(&index, &cloud, &poses, 3, 0.03),
                align_translations(&index, &cloud, &poses, 3, 0.03)
            );
            assert_eq!(
                score_poses_on_two_cores(&index, &cloud, &grid, &poses, &settings()),
                score_poses(&index, &cloud, &grid, &poses, &settings())
            );
        }
    }

    #[test]
    fn hidden_model_parts_are_not_violations() {
        let (points, normals) = plate_with_knob();
        let index = ModelIndex::new(points.clone(), normals.clone());
        let truth = Pose {
            rotation: Matrix3::identity(),
            translation: Vector3::new(0.0, 0.0, 0.5),
        };
        // An occluder hides the half x > 0: those rays carry no observation.
        let cloud: Vec<Point3> = posed(&points, &normals, &truth, true)
            .into_iter()
            .filter(|p| p[0] < 0.0)
            .collect();
        let grid = DepthGrid::new(&cloud, 0.002, 2.0);
        let score = score_poses(&index, &cloud, &grid, &[truth], &settings())[0];
        assert!(
            score.free_space_violation < 0.01 && score.inlier_fraction > 0.99,
            "{score:?}"
        );
        // ... but they are off the observed silhouette: about half the plate.
        assert!(
            score.off_silhouette > 0.4 && score.off_silhouette < 0.6,
            "{score:?}"
        );
        let whole = posed(&points, &normals, &truth, true);
        let grid = DepthGrid::new(&whole, 0.002, 2.0);
        let seen = score_poses(&index, &whole, &grid, &[truth], &settings())[0];
        assert!(seen.off_silhouette < 0.05, "{seen:?}");
    }

    #[test]
    fn background_points_cost_a_bounded_amount() {
        let (points, normals) = plate_with_knob();
        let index = ModelIndex::new(points.clone(), normals.clone());
        let truth = Pose {
            rotation: Matrix3::identity(),
            translation: Vector3::new(0.0, 0.0, 0.5),
        };
        let mut cloud = posed(&points, &normals, &truth, true);
        let object = cloud.len();
        cloud.extend((0..object / 4).map(|i| [-0.1 + 0.0002 * i as f32, 0.08, 0.6]));
        let grid = DepthGrid::new(&cloud, 0.002, 2.0);
        let score = score_poses(&index, &cloud, &grid, &[truth], &settings())[0];
        assert!(
            (score.inlier_fraction - object as f64 / cloud.len() as f64).abs() < 0.01,
            "{score:?}"
        );
        assert!(score.fit <= 0.005 * 0.21, "{score:?}");
    }

    #[test]
    fn one_face_of_a_box_does_not_pin_the_translation_and_a_corner_does() {
        let (points, normals) = box_surface([0.0; 3], [0.05, 0.03, 0.02], 0.002);
        let index = ModelIndex::new(points.clone(), normals.clone());
        let pose = Pose {
            rotation: Matrix3::identity(),
            translation: Vector3::new(0.0, 0.0, 0.6),
        };
        let grid_of = |seen: &[Point3]| DepthGrid::new(seen, 0.002, 2.0);
        // The −z face alone (what a camera straight in front sees of the
        // box), inside its edges: the test box's edge points sit on two faces.
        let face: Vec<Point3> = posed(&points, &normals, &pose, true)
            .into_iter()
            .filter(|p| p[0].abs() < 0.045 && p[1].abs() < 0.025)
            .collect();
        let flat = score_poses(&index, &face, &grid_of(&face), &[pose], &settings())[0];
        assert!(flat.translation_constraint < 1e-3, "{flat:?}");
        // Turned so that three faces face the camera: normals in 3 directions.
        let turned = Pose {
            rotation: *Rotation3::from_euler_angles(0.6, -0.7, 0.3).matrix(),
            translation: pose.translation,
        };
        let corner: Vec<Point3> = posed(&points, &normals, &turned, true);
        let pinned = score_poses(&index, &corner, &grid_of(&corner), &[turned], &settings())[0];
        assert!(
            pinned.translation_constraint > 0.05
                && pinned.translation_constraint <= 1.0 / 3.0 + 1e-9,
            "{pinned:?}"
        );
    }

    /// The free-space counts point by point, as nalgebra computes each
    /// point's pose: what the chunked lanes must reproduce.
    fn counts_point_by_point(
        index: &ModelIndex,
        grid: &DepthGrid,
        pose: &Pose,
        stride: usize,
        tolerance: f64,
    ) -> FreeSpaceCounts {
        let mut counts = FreeSpaceCounts::default();
        for (p, n) in index.points().iter().zip(index.normals()).step_by(stride) {
            let pc = pose.apply(p);
            let nc = pose.rotation * Vector3::new(n[0] as f64, n[1] as f64, n[2] as f64);
            if nc.dot(&pc) >= 0.0 {
                continue;
            }
            counts.facing += 1;
            if let Some(z) = grid.observed_depth(&pc) {
                counts.on_rays += 1;
                counts.violations += usize::from(pc.z < z - tolerance);
            } else if let Some(scene) = &grid.scene {
                counts.in_front_of_scene += usize::from(scene.in_front(&pc, tolerance));
            }
        }
        counts
    }

    #[test]
    fn a_posed_chunk_holds_nalgebras_values_bit_for_bit() {
        let (points, normals) = plate_with_knob();
        let index = ModelIndex::new(points, normals);
        let grid = DepthGrid::new(&[[0.0, 0.0, 0.5], [0.01, 0.0, 0.5]], 0.002, 2.0);
        let sample = ModelSample::new(&index, 3);
        let mut rng = SplitMix64::new(8);
        let mut chunk = PosedChunk::default();
        for _ in 0..20 {
            let mut angle = || (rng.next_f64() - 0.5) * 6.0;
            let pose = Pose {
                rotation: *Rotation3::from_euler_angles(angle(), angle(), angle()).matrix(),
                translation: Vector3::new(0.1 * angle(), 0.1 * angle(), 0.5 + 0.1 * angle()),
            };
            for start in (0..sample.points[0].len()).step_by(CHUNK) {
                let len = chunk.pose(&sample, start, &pose, &grid);
                for k in 0..len {
                    let i = start + k;
                    let p = Vector3::from(sample.points.each_ref().map(|c| c[i]));
                    let n = Vector3::from(sample.normals.each_ref().map(|c| c[i]));
                    let pc = pose.rotation * p + pose.translation;
                    let nc = pose.rotation * n;
                    let bits = |v: [f64; 3]| v.map(f64::to_bits);
                    assert_eq!(bits([chunk.x[k], chunk.y[k], chunk.z[k]]), bits(pc.into()));
                    assert_eq!(chunk.dot[k].to_bits(), nc.dot(&pc).to_bits());
                    let (u, v) = grid.cell_of(pc.x, pc.y, pc.z);
                    assert_eq!(bits([chunk.u[k], chunk.v[k], 0.0]), bits([u, v, 0.0]));
                }
            }
        }
    }

    #[test]
    fn the_chunked_free_space_test_counts_as_point_by_point() {
        // A plate with a knob (300 of its points seen) posed at random near
        // the seen pose, a scene behind it, strides that leave partial chunks.
        let (index, seen) = plate_seen_at(&Pose {
            rotation: *Rotation3::from_euler_angles(0.3, -0.2, 0.1).matrix(),
            translation: Vector3::new(0.01, -0.02, 0.45),
        });
        let cloud: Vec<Point3> = seen.into_iter().step_by(7).take(300).collect();
        let camera = Pinhole {
            fx: 300.0,
            fy: 300.0,
            cx: 80.0,
            cy: 60.0,
        };
        let depth: Vec<f32> = (0..160 * 120)
            .map(|i| {
                if i % 13 == 0 {
                    0.0
                } else {
                    0.4 + (i % 160) as f32 * 0.001
                }
            })
            .collect();
        let mut rng = SplitMix64::new(5);
        let mut angle = || (rng.next_f64() - 0.5) * 1.5;
        // The first pose puts the model partly behind the camera.
        let poses: Vec<Pose> = (0..40)
            .map(|k| {
                let depth = if k == 0 { 0.0 } else { 0.45 + 0.05 * angle() };
                Pose {
                    rotation: *Rotation3::from_euler_angles(angle(), angle(), angle()).matrix(),
                    translation: Vector3::new(0.02 * angle(), 0.02 * angle(), depth),
                }
            })
            .collect();
        let mut seen = FreeSpaceCounts::default();
        for scene in [false, true] {
            let mut grid = DepthGrid::new(&cloud, 0.002, 2.0);
            if scene {
                grid = grid.with_scene(SceneDepth::new(&depth, 160, camera, 2));
            }
            for stride in [1, 3, 4, 7] {
                let sample = ModelSample::new(&index, stride);
                for pose in &poses {
                    let tolerance = 0.003;
                    let chunked = free_space_counts(&sample, &grid, pose, tolerance);
                    assert_eq!(chunked, counts_in(&sample, &grid, pose, tolerance));
                    seen.facing += chunked.facing;
                    seen.on_rays += chunked.on_rays;
                    seen.violations += chunked.violations;
                    seen.in_front_of_scene += chunked.in_front_of_scene;
                    assert_eq!(
                        chunked,
                        counts_point_by_point(&index, &grid, pose, stride, tolerance),
                        "stride {stride}, scene {scene}"
                    );
                }
            }
        }
        // Every branch was taken: off the rays, on them, violating, before the scene.
        let FreeSpaceCounts {
            facing,
            on_rays,
            violations,
            in_front_of_scene,
        } = seen;
        assert!(
            facing > on_rays && on_rays > violations && violations > 0,
            "{seen:?}"
        );
        assert!(in_front_of_scene > 0, "{seen:?}");
        assert_eq!(ModelSample::new(&index, 0).points[0].len(), 0);
    }

    #[test]
    fn a_frame_window_reads_as_the_same_scene_as_the_window_cut_out() {
        // A 20 × 10 frame in millimetres; the window rows 2..8, columns 5..15.
        let camera = Pinhole {
            fx: 50.0,
            fy: 50.0,
            cx: 9.7,
            cy: 4.3,
        };
        let frame: Vec<u16> = (0..200u16)
            .map(|i| if i % 7 == 0 { 0 } else { 600 + i })
            .collect();
        let window =
            SceneDepth::from_frame(&frame, [10, 20], [2, 8, 5, 15], 1000.0, camera, 1).unwrap();
        let cut: Vec<f32> = (2..8)
            .flat_map(|v| frame[v * 20 + 5..v * 20 + 15].iter())
            .map(|&d| d as f32 / 1000.0)
            .collect();
        let shifted = Pinhole {
            cx: camera.cx - 5.0,
            cy: camera.cy - 2.0,
            ..camera
        };
        let alone = SceneDepth::new(&cut, 10, shifted, 1);
        assert_eq!(window.depth, alone.depth);
        assert_eq!(window.camera, alone.camera);
        for (x, y, z) in [(0.0, 0.0, 0.5), (0.01, -0.01, 0.7), (0.5, 0.0, 0.5)] {
            let p = Vector3::new(x, y, z);
            assert_eq!(window.pixel(&p), alone.pixel(&p));
            assert_eq!(window.in_front(&p, 0.01), alone.in_front(&p, 0.01));
        }
        assert!(
            SceneDepth::from_frame(&frame, [10, 20], [2, 11, 5, 15], 1000.0, camera, 1).is_none()
        );
        assert!(
            SceneDepth::from_frame(&frame, [10, 20], [2, 8, 15, 5], 1000.0, camera, 1).is_none()
        );
        // A frame without columns holds an empty window of any height.
        let empty = SceneDepth::from_frame::<u16>(&[], [66, 0], [0, 66, 0, 0], 1000.0, camera, 1);
        let empty = empty.unwrap();
        assert_eq!((empty.width, empty.height), (0, 66));
    }

    #[test]
    fn a_window_converts_eight_at_a_time_as_one_at_a_time() {
        // 13 × 11 pixels (rows of odd length: partial chunks), with every
        // kind of missing measurement among ordinary depths.
        let odd = [
            0.0,
            -0.5,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            1e-300,
            3.0e38 * 10.0,
        ];
        let frame: Vec<f64> = (0..143)
            .map(|i| {
                if i % 5 == 0 {
                    odd[(i / 5) % odd.len()]
                } else {
                    0.4 + i as f64 * 0.013
                }
            })
            .collect();
        let frame_mm: Vec<u16> = (0..143u16)
            .map(|i| if i % 6 == 0 { 0 } else { 500 + 7 * i })
            .collect();
        for window in [[0, 13, 0, 11], [2, 9, 1, 10], [4, 4, 3, 8]] {
            let here = window_in_metres_here(&frame, 11, window, 1.7);
            assert_eq!(window_in_metres(&frame, 11, window, 1.7), here);
            assert!(here.iter().all(|&z| z > 0.0), "{here:?}");
            let here = window_in_metres_here(&frame_mm, 11, window, 1000.0);
            assert_eq!(window_in_metres(&frame_mm, 11, window, 1000.0), here);
        }
    }

    #[test]
    fn the_scene_tells_a_pose_hidden_by_an_occluder_from_one_before_the_background() {
        // 100 × 100 px image: background 1 m away, an occluder 0.5 m away over its left half.
        let camera = Pinhole {
            fx: 100.0,
            fy: 100.0,
            cx: 50.0,
            cy: 50.0,
        };
        let depth: Vec<f32> = (0..100 * 100)
            .map(|i| if i % 100 < 50 { 0.5 } else { 1.0 })
            .collect();
        let (points, normals) = box_surface([0.0; 3], [0.05, 0.05, 0.05], 0.005);
        let index = ModelIndex::new(points, normals);
        let nothing_seen = |scene: Option<SceneDepth>| {
            let grid = DepthGrid::new(&[], 0.01, 2.0);
            match scene {
                Some(s) => grid.with_scene(s),
                None => grid,
            }
        };
        let at = |x: f64| Pose {
            rotation: Matrix3::identity(),
            translation: Vector3::new(x, 0.0, 0.8),
        };
        let (hidden, in_front) = (at(-0.2), at(0.2));
        let scene = || Some(SceneDepth::new(&depth, 100, camera, 2));
        let scores = score_poses(
            &index,
            &[],
            &nothing_seen(scene()),
            &[hidden, in_front],
            &settings(),
        );
        assert_eq!(
            scores[0].scene_violation, 0.0,
            "behind the occluder: unknown space"
        );
        assert!(
            scores[1].scene_violation > 0.95,
            "{}: it would hide the background",
            scores[1].scene_violation
        );
        let blind = score_poses(&index, &[], &nothing_seen(None), &[in_front], &settings());
        assert_eq!(blind[0].scene_violation, 0.0, "no scene, no test");
        // Within `radius` pixels of a nearer measurement, a point is behind it.
        let edge = SceneDepth::new(&depth, 100, camera, 2);
        assert!(!edge.in_front(&Vector3::new(0.006, 0.0, 0.8), 0.01));
        assert!(edge.in_front(&Vector3::new(0.04, 0.0, 0.8), 0.01));
        assert!(
            !edge.in_front(&Vector3::new(0.04, 0.0, 0.995), 0.01),
            "within the tolerance"
        );
        assert!(
            !edge.in_front(&Vector3::new(0.9, 0.0, 0.8), 0.01),
            "off the image"
        );
        let unmeasured = SceneDepth::new(&[0.0; 100], 10, camera, 2);
        assert!(
            !unmeasured.in_front(&Vector3::new(-0.45, -0.45, 1.0), 0.01),
            "nothing measured"
        );
        // A hole in the depth (no measurement at the point's own pixel, the
        // background measured beside it) is unknown space too.
        let mut holed = depth.clone();
        holed[50 * 100 + 54] = 0.0;
        let hole = SceneDepth::new(&holed, 100, camera, 2);
        assert!(!hole.in_front(&Vector3::new(0.032, 0.0, 0.8), 0.01));
        assert!(hole.in_front(&Vector3::new(0.024, 0.0, 0.8), 0.01));
    }
}
