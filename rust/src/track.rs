//! One tracked frame's geometry in one call: the last pose (predicted onto
//! this frame) refined by ICP onto the object's observed points, then
//! scored as the tracker's check reads it (the free-space and scene terms
//! at the tracker's inlier distance, the fit terms at the search's tighter
//! one). A tracked frame is a millisecond or two of work; as a chain of
//! calls from Python, each converting its arrays, it cost a third more.
//!
//! Camera frame (OpenCV), metres; poses model frame → camera.

use std::sync::Arc;

use nalgebra::Vector3;

use crate::index::{ModelIndex, Pose};
use crate::query::Pinhole;
use crate::refine::IcpResult;
use crate::scoring::{score_poses, DepthGrid, PoseScore, SceneDepth, ScoreSettings};
use crate::Point3;

/// Tuning of [`track_frame`], metres where a distance (the Python layer's
/// `edgepose.TrackSettings` and `EstimateSettings`, scaled by the diameter).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackFrameSettings {
    pub icp_iterations: usize,
    /// ICP ignores pairs farther apart.
    pub icp_max_distance: f64,
    /// The check's inlier distance: its free-space and scene terms are read here.
    pub inlier_distance: f64,
    /// The search's hypothesis distance: the fit terms the evidence reads.
    pub tight_inlier_distance: f64,
    /// Every `model_stride`-th model point takes part in the free-space test.
    pub model_stride: usize,
    /// The object's diameter.
    pub diameter: f64,
    /// The scene test reads each pixel as the nearest depth within this many.
    pub scene_radius: usize,
    /// Without a whole box in front of the camera, the scene window reaches
    /// this many diameters beyond the observed points.
    pub scene_margin: f64,
}

/// The depth frame around a tracked object: a row-major image of `[height,
/// width]` pixels in `depth_scale` units per metre, its intrinsics, and the
/// model's bounding-box corners (model frame) that place the window.
pub struct TrackedScene<'a, T> {
    pub pixels: &'a [T],
    pub shape: [usize; 2],
    pub camera: Pinhole,
    pub depth_scale: f64,
    pub box_corners: &'a [[f64; 3]],
}

/// What a tracked frame's check and evidence read.
pub struct TrackedFit {
    pub icp: IcpResult,
    /// The refined pose scored at the check's inlier distance.
    pub loose: PoseScore,
    /// Its fit terms at the tight distance (free-space terms 0).
    pub tight: PoseScore,
    /// Bounding-box sides of the observed points, metres.
    pub sides: [f64; 3],
    /// Whether the scene window was read (a frame was given).
    pub with_scene: bool,
}

/// ICP of the subsampled `points` from `start`, then the scores of the
/// result against all observed `seen` points' free space (and the scene
/// around the pose, given a frame), with `free_space_tolerance` metres.
pub fn track_frame<T: Copy + Into<f64>>(
    index: &Arc<ModelIndex>,
    points: &[Point3],
    seen: &[Point3],
    start: Pose,
    free_space_tolerance: f64,
    scene: Option<TrackedScene<'_, T>>,
    settings: &TrackFrameSettings,
) -> TrackedFit {
    let icp = index.refine(
        points,
        start,
        settings.icp_iterations,
        settings.icp_max_distance,
    );
    let pose = icp.pose;
    let sides = box_sides(seen);
    let mut grid = DepthGrid::new(seen, spacing(sides, seen.len()), 2.0);
    let with_scene = scene.is_some();
    if let Some(scene) = scene {
        if let Some(depth) = scene_window(&scene, &pose, seen, settings) {
            grid = grid.with_scene(depth);
        }
    }
    let score = |inlier_distance, model_stride| {
        let settings = ScoreSettings {
            inlier_distance,
            free_space_tolerance,
            model_stride,
        };
        score_poses(index, points, &grid, &[pose], &settings)[0]
    };
    TrackedFit {
        loose: score(settings.inlier_distance, settings.model_stride.max(1)),
        tight: score(settings.tight_inlier_distance, 0),
        icp,
        sides,
        with_scene,
    }
}

/// The scene depth a pose projects into: the window over its bounding box's
/// corners, grown by the scene test's radius and a pixel; when a corner is
/// not in front of the camera, the window over the observed points grown by
/// `scene_margin` diameters at their nearest depth. None for a window the
/// frame does not hold (it never is: windows are clipped to the frame).
fn scene_window<T: Copy + Into<f64>>(
    scene: &TrackedScene<'_, T>,
    pose: &Pose,
    seen: &[Point3],
    settings: &TrackFrameSettings,
) -> Option<SceneDepth> {
    let corners: Vec<Vector3<f64>> = scene
        .box_corners
        .iter()
        .map(|c| pose.rotation * Vector3::new(c[0], c[1], c[2]) + pose.translation)
        .collect();
    let camera = scene.camera;
    let (points, grow_u, grow_v) = if corners.iter().all(|c| c.z > 1e-6) {
        let grow = (settings.scene_radius + 1) as f64;
        (corners, grow, grow)
    } else {
        let nearest = seen
            .iter()
            .map(|p| p[2] as f64)
            .fold(f64::INFINITY, f64::min);
        let grow = settings.scene_margin * settings.diameter / nearest.max(1e-6);
        let points = seen
            .iter()
            .map(|p| Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64))
            .collect();
        (points, grow * camera.fx, grow * camera.fy)
    };
    let [height, width] = scene.shape;
    let (mut u0, mut u1, mut v0, mut v1) = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    for p in &points {
        let z = p.z.max(1e-6);
        let (u, v) = (
            camera.fx * p.x / z + camera.cx,
            camera.fy * p.y / z + camera.cy,
        );
        (u0, u1, v0, v1) = (u0.min(u), u1.max(u), v0.min(v), v1.max(v));
    }
    let (left, right) = pixel_span(u0 - grow_u, u1 + grow_u + 1.0, width);
    let (top, bottom) = pixel_span(v0 - grow_v, v1 + grow_v + 1.0, height);
    SceneDepth::from_frame(
        scene.pixels,
        scene.shape,
        [top, bottom, left, right],
        scene.depth_scale,
        camera,
        settings.scene_radius,
    )
}

/// Pixels `[lo, hi)` within `[0, size]`; all of them when a bound is not
/// finite (absurd intrinsics put the points at infinity).
fn pixel_span(lo: f64, hi: f64, size: usize) -> (usize, usize) {
    if !(lo.is_finite() && hi.is_finite()) {
        return (0, size);
    }
    let clip = |x: f64| x.max(0.0).min(size as f64) as usize;
    (clip(lo), clip(hi))
}

/// Bounding-box side lengths of `points`, metres (0 for none).
fn box_sides(points: &[Point3]) -> [f64; 3] {
    [0, 1, 2].map(|k| {
        let (lo, hi) = points
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), p| {
                (lo.min(p[k]), hi.max(p[k]))
            });
        if lo <= hi {
            (hi - lo) as f64
        } else {
            0.0
        }
    })
}

/// Typical distance between neighbouring points of a surface patch of
/// `count` points with bounding-box `sides`, metres: the square root of its
/// area (the two larger sides) per point. Sizes the free-space grid.
fn spacing(sides: [f64; 3], count: usize) -> f64 {
    let mut ordered = sides;
    ordered.sort_by(f64::total_cmp);
    (ordered[1] * ordered[2] / count.max(1) as f64).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::refine::tests::bracket;
    use nalgebra::Matrix3;

    fn settings() -> TrackFrameSettings {
        TrackFrameSettings {
            icp_iterations: 10,
            icp_max_distance: 0.03,
            inlier_distance: 0.008,
            tight_inlier_distance: 0.004,
            model_stride: 4,
            diameter: 0.2,
            scene_radius: 2,
            scene_margin: 0.75,
        }
    }

    /// `points` (model frame) under `pose`, camera frame.
    fn posed(points: &[Point3], pose: &Pose) -> Vec<Point3> {
        points
            .iter()
            .map(|p| {
                let c = pose.apply(p);
                [c.x as f32, c.y as f32, c.z as f32]
            })
            .collect()
    }

    #[test]
    fn a_frame_off_by_a_little_is_tracked_back_onto_its_points() {
        let model = bracket();
        let index = Arc::new(ModelIndex::new(model.points.clone(), model.normals.clone()));
        let truth = Pose {
            rotation: Matrix3::identity(),
            translation: Vector3::new(0.0, 0.0, 0.6),
        };
        let seen = posed(&model.points, &truth);
        let start = Pose {
            translation: truth.translation + Vector3::new(0.004, -0.003, 0.002),
            ..truth
        };
        let fit = track_frame::<f32>(&index, &seen[..512], &seen, start, 0.005, None, &settings());
        assert!((fit.icp.pose.translation - truth.translation).norm() < 1e-4);
        assert!(fit.loose.inlier_fraction > 0.99 && fit.tight.inlier_fraction > 0.99);
        assert_eq!(fit.tight.free_space_violation, 0.0);
        assert!(!fit.with_scene);
        assert!(fit.sides.iter().all(|s| *s > 0.01));
    }

    #[test]
    fn the_scene_window_covers_the_posed_model_and_falls_back_to_the_points() {
        let model = bracket();
        let (lo, hi) = model
            .points
            .iter()
            .fold(([f64::MAX; 3], [f64::MIN; 3]), |(lo, hi), p| {
                (
                    [0, 1, 2].map(|k| lo[k].min(p[k] as f64)),
                    [0, 1, 2].map(|k| hi[k].max(p[k] as f64)),
                )
            });
        let corners: Vec<[f64; 3]> = (0..8)
            .map(|i| [0, 1, 2].map(|k| if i >> k & 1 == 1 { hi[k] } else { lo[k] }))
            .collect();
        let pixels = vec![0u16; 640 * 480];
        let scene = TrackedScene {
            pixels: &pixels,
            shape: [480, 640],
            camera: Pinhole {
                fx: 572.4,
                fy: 573.6,
                cx: 325.3,
                cy: 242.0,
            },
            depth_scale: 1000.0,
            box_corners: &corners,
        };
        let pose = Pose {
            rotation: *nalgebra::Rotation3::from_euler_angles(0.4, -0.7, 1.1).matrix(),
            translation: Vector3::new(0.03, -0.02, 0.6),
        };
        let seen = posed(&model.points, &pose);
        let window = scene_window(&scene, &pose, &seen, &settings()).unwrap();
        let r = settings().scene_radius as f64;
        for p in &seen {
            let (x, y, z) = (p[0] as f64, p[1] as f64, p[2] as f64);
            let u = window.camera.fx * x / z + window.camera.cx;
            let v = window.camera.fy * y / z + window.camera.cy;
            assert!(u - r >= 0.0 && v - r >= 0.0, "{u} {v}");
            assert!(
                u + r < window.width as f64 && v + r < window.height as f64,
                "{u} {v}"
            );
        }
        assert!(
            window.width < 320 && window.height < 240,
            "little else of the frame"
        );
        // A box reaching behind the camera: the window around the observed
        // points, grown by the margin, instead.
        let behind = Pose {
            translation: Vector3::new(0.0, 0.0, 0.01),
            ..pose
        };
        let around = scene_window(&scene, &behind, &seen, &settings()).unwrap();
        assert!(around.width > window.width && around.height > window.height);
    }

    #[test]
    fn the_scene_window_is_clipped_to_the_frame() {
        assert_eq!(pixel_span(-5.0, 20.0, 10), (0, 10));
        assert_eq!(pixel_span(2.7, 7.2, 10), (2, 7));
        assert_eq!(pixel_span(f64::NAN, 7.2, 10), (0, 10));
        assert_eq!(box_sides(&[]), [0.0; 3]);
        assert_eq!(spacing([0.1, 0.2, 0.0], 8), (0.1f64 * 0.2 / 8.0).sqrt());
    }
}
