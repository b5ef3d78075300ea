//! How far apart two poses are, and how much better a pose explains a view
//! than itself turned by each of a few turns of the model (the confidence's
//! flip margin): the mistakes a search makes on a near-symmetric view (a
//! banana end for end, a box whose telling details are hidden). Poses are
//! model frame → camera, metres.

use nalgebra::Vector3;

use crate::index::{ModelIndex, Pose};
use crate::scoring::{align_translations, score_poses, DepthGrid, PoseScore, ScoreSettings};
use crate::Point3;

/// ADD of each of `poses` from `reference` on the model's first `points`
/// points (the first farthest-point samples: spread over the model),
/// metres; ADD-S (each point to the nearest point of the other pose) when
/// the object is `symmetric`.
pub fn pose_distances(
    index: &ModelIndex,
    poses: &[Pose],
    reference: &Pose,
    symmetric: bool,
    points: usize,
) -> Vec<f64> {
    let model = &index.points()[..points.min(index.len())];
    let target: Vec<Vector3<f64>> = model.iter().map(|p| reference.apply(p)).collect();
    poses
        .iter()
        .map(|pose| {
            let total: f64 = model
                .iter()
                .zip(&target)
                .map(|(p, own)| {
                    let moved = pose.apply(p);
                    if symmetric {
                        let nearest = target
                            .iter()
                            .map(|t| (moved - t).norm_squared())
                            .fold(f64::INFINITY, f64::min);
                        nearest.sqrt()
                    } else {
                        (moved - own).norm()
                    }
                })
                .sum();
            total / model.len().max(1) as f64
        })
        .collect()
}

/// The rival turned poses to settle are picked on every `SCREEN_STRIDE`-th
/// observed point and `SCREEN_STRIDE` times fewer model points than they
/// are scored on.
const SCREEN_STRIDE: usize = 4;

/// Tuning of [`flip_margin`]; distances in metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FlipSettings {
    /// Keypoint alignment of each turned pose: iterations and pairing distance.
    pub align_iterations: usize,
    pub align_distance: f64,
    /// How the turned poses are scored (as the hypotheses are).
    pub score: ScoreSettings,
    /// A turned pose farther than this from the pose is a rival ...
    pub rival_distance: f64,
    /// ... measured on this many model points ([`pose_distances`]) ...
    pub rival_points: usize,
    /// ... with ADD-S for a symmetric object (its turns may be symmetries).
    pub symmetric: bool,
    /// The rivals that screen best, this many, are settled onto the view by
    /// ICP on the observed points ...
    pub settled: usize,
    /// ... in this many iterations (0: not settled) ...
    pub settle_iterations: usize,
    /// ... pairing points this close.
    pub settle_distance: f64,
}

/// What [`flip_margin`] finds.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FlipMargin {
    /// The pose's net minus its best rival's (1 when there is none).
    pub margin: f64,
    /// That rival: the pose turned, moved onto the view and settled.
    pub rival: Option<Pose>,
    /// Its mean truncated distance to the observed points, metres (as
    /// [`PoseScore::fit`]; NaN when there is no rival): set against the
    /// pose's own, it says whether fine detail tells the two apart.
    pub rival_fit: f64,
}

/// How much better `pose` explains the view than itself turned by each of
/// `turns` (rigid turns of the model, model frame: half turns about its
/// principal axes, its near turns), each turned pose moved (not turned) so
/// the query's `keypoints` land on the model (as candidates are), and the
/// few that screen best settled by a short ICP: `own_net` (the pose's
/// inlier fraction minus its free-space violation on the `observed` points
/// and the `grid` of the whole cloud) minus the best turned pose's that is
/// a different pose, and that best rival (settled). 1 and no rival when
/// none is (every turn is a symmetry, or there are none).
#[allow(clippy::too_many_arguments)]
pub fn flip_margin(
    index: &ModelIndex,
    keypoints: &[Point3],
    observed: &[Point3],
    grid: &DepthGrid,
    pose: &Pose,
    own_net: f64,
    turns: &[Pose],
    settings: &FlipSettings,
) -> FlipMargin {
    let turned: Vec<Pose> = turns
        .iter()
        .map(|turn| Pose {
            rotation: pose.rotation * turn.rotation,
            translation: pose.translation + pose.rotation * turn.translation,
        })
        .collect();
    let turned = align_translations(
        index,
        keypoints,
        &turned,
        settings.align_iterations,
        settings.align_distance,
    );
    let distances = pose_distances(
        index,
        &turned,
        pose,
        settings.symmetric,
        settings.rival_points,
    );
    let rivals: Vec<Pose> = turned
        .into_iter()
        .zip(distances)
        .filter(|(_, distance)| *distance > settings.rival_distance)
        .map(|(turned, _)| turned)
        .collect();
    if rivals.is_empty() {
        return FlipMargin {
            margin: 1.0,
            rival: None,
            rival_fit: f64::NAN,
        };
    }
    // The rivals worth settling are picked on a quarter of the points and
    // model points (each look-up is a likely cache miss).
    let chosen: Vec<usize> = if rivals.len() > settings.settled.max(1) {
        let few: Vec<Point3> = observed.iter().step_by(SCREEN_STRIDE).copied().collect();
        let screen = ScoreSettings {
            model_stride: settings.score.model_stride * SCREEN_STRIDE,
            ..settings.score
        };
        let nets: Vec<f64> = score_poses(index, &few, grid, &rivals, &screen)
            .iter()
            .map(PoseScore::net)
            .collect();
        let mut order: Vec<usize> = (0..rivals.len()).collect();
        order.sort_by(|&a, &b| nets[b].total_cmp(&nets[a]));
        order.truncate(settings.settled.max(1));
        order
    } else {
        (0..rivals.len()).collect()
    };
    // Each is settled by a short ICP, as the pose was by its own: a turned
    // pose that is the truth, left a degree or a millimetre off, would lose
    // to a wrong but polished pose. One that ICP slides back onto the pose
    // is the pose; its turned start stays the rival.
    let starts: Vec<Pose> = chosen.iter().map(|&i| rivals[i]).collect();
    let settled: Vec<Pose> = if settings.settle_iterations > 0 {
        let icp: Vec<Pose> = starts
            .iter()
            .map(|start| {
                let result = index.refine(
                    observed,
                    *start,
                    settings.settle_iterations,
                    settings.settle_distance,
                );
                if result.rmse.is_finite() {
                    result.pose
                } else {
                    *start
                }
            })
            .collect();
        let distances =
            pose_distances(index, &icp, pose, settings.symmetric, settings.rival_points);
        icp.into_iter()
            .zip(distances)
            .zip(&starts)
            .map(|((moved, distance), start)| {
                if distance > settings.rival_distance {
                    moved
                } else {
                    *start
                }
            })
            .collect()
    } else {
        starts
    };
    let scores = score_poses(index, observed, grid, &settled, &settings.score);
    let (best, best_net) = scores
        .iter()
        .map(PoseScore::net)
        .enumerate()
        .fold((0, f64::NEG_INFINITY), |a, b| if b.1 > a.1 { b } else { a });
    FlipMargin {
        margin: own_net - best_net,
        rival: Some(settled[best]),
        rival_fit: scores[best].fit,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix3, Rotation3};
    use std::f64::consts::PI;

    /// An elongated model: a 20 × 6 × 2 cm block of points with a post at one end.
    fn bar() -> ModelIndex {
        let mut points = Vec::new();
        for i in 0..40 {
            for j in 0..12 {
                for k in 0..4 {
                    let (x, y, z) = (
                        i as f32 * 0.005 - 0.1,
                        j as f32 * 0.005 - 0.03,
                        k as f32 * 0.005,
                    );
                    points.push([x, y, z]);
                }
            }
        }
        for i in 0..300 {
            // The telling bump: a 2 × 2 × 5 cm post at one end.
            let (x, y, z) = ((i % 5) as f32, ((i / 5) % 5) as f32, (i / 25) as f32);
            points.push([0.08 + 0.004 * x, -0.01 + 0.004 * y, 0.02 + 0.004 * z]);
        }
        let normals = vec![[0.0, 0.0, 1.0]; points.len()];
        ModelIndex::new(points, normals)
    }

    #[test]
    fn add_and_add_s_between_poses() {
        let index = bar();
        let at = |x: f64| Pose {
            rotation: Matrix3::identity(),
            translation: Vector3::new(x, 0.0, 0.5),
        };
        let d = pose_distances(&index, &[at(0.0), at(0.01)], &at(0.0), false, 64);
        assert!(d[0].abs() < 1e-12 && (d[1] - 0.01).abs() < 1e-9, "{d:?}");
        let half_turn = Pose {
            rotation: *Rotation3::from_axis_angle(&Vector3::z_axis(), PI).matrix(),
            translation: Vector3::new(0.0, 0.0, 0.5),
        };
        // Turned half about z, the bar lies on itself (all but the post).
        let all = index.len();
        let plain = pose_distances(&index, &[half_turn], &at(0.0), false, all)[0];
        let symmetric = pose_distances(&index, &[half_turn], &at(0.0), true, all)[0];
        assert!(symmetric < 0.2 * plain, "ADD-S {symmetric} vs ADD {plain}");
    }

    #[test]
    fn the_true_pose_beats_its_flips_and_a_flip_loses_to_the_truth() {
        let index = bar();
        let truth = Pose {
            rotation: Matrix3::identity(),
            translation: Vector3::new(0.0, 0.0, 0.6),
        };
        // The camera sees the model as posed (every point, the bump included).
        let observed: Vec<Point3> = index
            .points()
            .iter()
            .step_by(3)
            .map(|p| {
                let q = truth.apply(p);
                [q.x as f32, q.y as f32, q.z as f32]
            })
            .collect();
        let grid = DepthGrid::new(&observed, 0.005, 2.0);
        let score = ScoreSettings {
            inlier_distance: 0.004,
            free_space_tolerance: 0.006,
            model_stride: 4,
        };
        let settings = FlipSettings {
            align_iterations: 3,
            align_distance: 0.02,
            score,
            rival_distance: 0.02,
            rival_points: 64,
            symmetric: false,
            settled: 2,
            settle_iterations: 2,
            settle_distance: 0.02,
        };
        let model: Vec<Vector3<f64>> = index
            .points()
            .iter()
            .map(|p| Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64))
            .collect();
        let centroid = model.iter().sum::<Vector3<f64>>() / model.len() as f64;
        // Half turns about the axes through the centroid.
        let half_turns: Vec<Pose> = [Vector3::x_axis(), Vector3::y_axis(), Vector3::z_axis()]
            .iter()
            .map(|axis| {
                let turn = Rotation3::from_axis_angle(axis, PI);
                Pose {
                    rotation: *turn.matrix(),
                    translation: centroid - turn * centroid,
                }
            })
            .collect();
        let keypoints = &observed[..32];
        let net = |pose: &Pose| {
            let s = score_poses(&index, &observed, &grid, &[*pose], &score)[0];
            s.inlier_fraction - s.free_space_violation
        };
        let margin_of = |pose: &Pose, settings: &FlipSettings| {
            flip_margin(
                &index,
                keypoints,
                &observed,
                &grid,
                pose,
                net(pose),
                &half_turns,
                settings,
            )
            .margin
        };
        let margin = margin_of(&truth, &settings);
        assert!(margin > 0.05, "true pose margin {margin}");
        let half_turn = Rotation3::from_axis_angle(&Vector3::z_axis(), PI);
        let flipped = Pose {
            rotation: *half_turn.matrix(),
            translation: truth.translation + centroid - half_turn * centroid,
        };
        let margin = margin_of(&flipped, &settings);
        assert!(margin < 0.0, "flipped pose margin {margin}");
        let symmetric = FlipSettings {
            rival_distance: 1.0,
            ..settings
        };
        assert_eq!(margin_of(&truth, &symmetric), 1.0);
        let no_turns = flip_margin(
            &index,
            keypoints,
            &observed,
            &grid,
            &truth,
            net(&truth),
            &[],
            &settings,
        );
        assert_eq!(no_turns.margin, 1.0);
        assert!(no_turns.rival.is_none() && no_turns.rival_fit.is_nan());

        // A turn a few degrees off (a near turn is never exact) leaves the
        // flipped pose's rival, the truth, tilted: unsettled it explains
        // less of the view than the flipped pose; settled by ICP, more.
        let tilt = Rotation3::from_axis_angle(&Vector3::y_axis(), 6f64.to_radians());
        let off_turn = Pose {
            rotation: *(half_turn * tilt).matrix(),
            translation: centroid - half_turn * tilt * centroid,
        };
        let flipped_margin = |settings: &FlipSettings| {
            flip_margin(
                &index,
                keypoints,
                &observed,
                &grid,
                &flipped,
                net(&flipped),
                &[off_turn],
                settings,
            )
        };
        let unsettled = flipped_margin(&FlipSettings {
            settle_iterations: 0,
            ..settings
        })
        .margin;
        let found = flipped_margin(&settings);
        let settled = found.margin;
        // The settled rival is the truth, nearly: what a search that took
        // the flipped pose should switch to.
        let rival = found.rival.expect("a rival");
        let off = pose_distances(&index, &[rival], &truth, false, 64)[0];
        assert!(off < 0.004, "settled rival {off} m from the truth");
        // Its fit (the confidence sets it against the pose's) is the rival's own.
        let rival_score = score_poses(&index, &observed, &grid, &[rival], &settings.score)[0];
        assert_eq!(found.rival_fit, rival_score.fit);
        assert!(
            settled < 0.0 && unsettled > 0.0,
            "settled {settled}, unsettled {unsettled}"
        );
    }
}
