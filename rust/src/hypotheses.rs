//! Stage 5's pick among an estimate's refined hypotheses (poses model →
//! camera, metres, after their coarse ICP): which are usable, their scores
//! on the hypotheses' observed points, the one that wins, near ties broken
//! by the final polish, and how far the winner stands above its rivals.
//! The Python layer (`edgepose.stages.refine_hypotheses`) runs the ICPs
//! and keeps them between an estimate's searches; this is the arithmetic
//! between them, in one call.

use nalgebra::{Matrix3, Vector3};

use crate::flips::pose_distances;
use crate::index::{ModelIndex, Pose};
use crate::refine::IcpResult;
use crate::scoring::{score_poses, DepthGrid, PoseScore, ScoreSettings};
use crate::Point3;

/// The rules of the pick (`edgepose.settings.RefineSettings`; distances in metres).
#[derive(Clone, Copy, Debug)]
pub struct PickRules {
    /// An ICP result with fewer inlier pairs is not trusted ...
    pub min_icp_inliers: usize,
    /// ... nor one that puts the model's centre farther than this from the
    /// observed centroid.
    pub max_centre_offset: f64,
    /// How the hypotheses are scored (no free-space weight: the pick reads
    /// the terms themselves).
    pub score: ScoreSettings,
    /// Hypotheses compete when they explain at least this fraction of the
    /// best usable one's inliers ...
    pub inlier_ratio: f64,
    /// ... and violate free space (and the scene) at most this much more
    /// than the least violating usable one.
    pub free_space_margin: f64,
    /// Competing rivals whose coarse RMSE is within this fraction of the
    /// pick's are polished with it, the lowest polished RMSE winning (0:
    /// never; nor when there is no polish).
    pub tie_polish_within: f64,
    /// Hypotheses farther apart than this (ADD, or ADD-S for a `symmetric`
    /// object, on the model's first `rival_points` points) are different
    /// poses: rivals.
    pub rival_distance: f64,
    pub rival_points: usize,
    pub symmetric: bool,
}

/// What [`pick`] found.
#[derive(Clone, Debug)]
pub struct Picked {
    /// The winning hypothesis.
    pub pick: usize,
    /// Its polish, when a near tie was broken by polishing (the winner's row).
    pub polish: Option<IcpResult>,
    /// Every hypothesis's scores, in order.
    pub scores: Vec<PoseScore>,
    /// Which hypotheses are usable.
    pub usable: Vec<bool>,
    /// The winner's net (inlier fraction minus violations) minus the best
    /// usable rival's; 1 without one.
    pub margin: f64,
    /// The winner's coarse RMSE over the lowest of the competing rivals'; 0
    /// without one.
    pub rmse_ratio: f64,
}

impl PickRules {
    /// [`usable_icp`] by these rules' inlier count and centre offset.
    pub fn usable(
        &self,
        inliers: usize,
        rmse: f64,
        t: &Vector3<f64>,
        centroid: &Vector3<f64>,
    ) -> bool {
        usable_icp(
            inliers,
            rmse,
            t,
            centroid,
            self.min_icp_inliers,
            self.max_centre_offset,
        )
    }
}

/// Whether an ICP result (its inlier pairs, RMSE and translation `t`,
/// camera frame, metres) is usable: at least `min_icp_inliers` inliers, a
/// finite RMSE, and the model's centre within `max_centre_offset` metres of
/// the observed `centroid` (numpy's norm: the squares summed in order). The
/// one rule for stage 5's hypotheses, the polish and the turned pose
/// (`edgepose.stages.usable_icp`).
pub fn usable_icp(
    inliers: usize,
    rmse: f64,
    t: &Vector3<f64>,
    centroid: &Vector3<f64>,
    min_icp_inliers: usize,
    max_centre_offset: f64,
) -> bool {
    let d = t - centroid;
    rmse.is_finite()
        && inliers >= min_icp_inliers
        && (d.x * d.x + d.y * d.y + d.z * d.z).sqrt() <= max_centre_offset
}

/// Up to `count` of `rotations`, taken in `order` (indices into them),
/// each whose cosine of the angle to every one taken before,
/// (trace(Raᵀ Rb) − 1) / 2, is below `cos_min`: the hypotheses' starts,
/// distinct poses rather than neighbouring views of one.
pub fn distinct(
    rotations: &[Matrix3<f64>],
    order: &[usize],
    count: usize,
    cos_min: f64,
) -> Vec<usize> {
    let cosine = |a: &Matrix3<f64>, b: &Matrix3<f64>| {
        let mut trace = 0.0;
        for i in 0..3 {
            for j in 0..3 {
                trace += a[(i, j)] * b[(i, j)];
            }
        }
        (trace - 1.0) / 2.0
    };
    let mut kept: Vec<usize> = Vec::with_capacity(count);
    for &j in order {
        if kept.len() == count {
            break;
        }
        if kept
            .iter()
            .all(|&k| cosine(&rotations[j], &rotations[k]) < cos_min)
        {
            kept.push(j);
        }
    }
    kept
}

/// Up to `count` of `poses`, taken in `order` (indices into them) where
/// `allowed`, each farther than `rival_distance` (ADD, or ADD-S for a
/// `symmetric` object, on the model's first `rival_points` points) from
/// pose 0 and from each taken before: distinct alternatives to pose 0.
#[allow(clippy::too_many_arguments)]
pub fn distinct_poses(
    index: &ModelIndex,
    poses: &[Pose],
    order: &[usize],
    allowed: &[bool],
    count: usize,
    rival_distance: f64,
    symmetric: bool,
    rival_points: usize,
) -> Vec<usize> {
    if count == 0 || !allowed.iter().skip(1).any(|a| *a) {
        return Vec::new(); // only pose 0 itself may qualify: no distances needed
    }
    let apart_from = |p: usize| {
        pose_distances(index, poses, &poses[p], symmetric, rival_points)
            .into_iter()
            .map(|d| d > rival_distance)
    };
    let mut apart: Vec<bool> = allowed
        .iter()
        .zip(apart_from(0))
        .map(|(a, b)| *a && b)
        .collect();
    let mut taken = Vec::with_capacity(count);
    for &i in order {
        if taken.len() == count {
            break;
        }
        if apart[i] {
            taken.push(i);
            for (a, b) in apart.iter_mut().zip(apart_from(i)) {
                *a &= b;
            }
        }
    }
    taken
}

/// Inlier fraction minus free-space and scene violations: how hypotheses compete.
pub fn net(score: &PoseScore) -> f64 {
    score.inlier_fraction - (score.free_space_violation + score.scene_violation)
}

/// The index of the least of `values` where `chosen` (the first on ties);
/// 0 when none is chosen (numpy's argmin over infinities).
fn least(values: &[f64], chosen: impl Fn(usize) -> bool) -> usize {
    let mut best = (0, f64::INFINITY);
    for (i, &v) in values.iter().enumerate() {
        if chosen(i) && v < best.1 {
            best = (i, v);
        }
    }
    best.0
}

/// Stage 5's pick among `hypotheses` (their coarse ICP's `inliers` and
/// `rmse`), scored on the `observed` points against the `grid`; None when
/// none is usable. Hypotheses that explain nearly as many points as the
/// best and violate free space little more than the least violating
/// compete; the lowest RMSE wins. Competing rivals within
/// `tie_polish_within` of its RMSE are handed with it (the pick first) to
/// `polish_tie`, which returns their polishes; the lowest polished RMSE of
/// a usable polish wins (the pick when none is usable).
#[allow(clippy::too_many_arguments)]
pub fn pick<E>(
    index: &ModelIndex,
    observed: &[Point3],
    grid: &DepthGrid,
    hypotheses: &[Pose],
    inliers: &[usize],
    rmse: &[f64],
    centroid: &Vector3<f64>,
    rules: &PickRules,
    polish_tie: impl FnOnce(&[usize]) -> Result<Vec<IcpResult>, E>,
) -> Result<Option<Picked>, E> {
    let n = hypotheses.len();
    let usable: Vec<bool> = (0..n)
        .map(|h| rules.usable(inliers[h], rmse[h], &hypotheses[h].translation, centroid))
        .collect();
    if !usable.iter().any(|u| *u) {
        return Ok(None);
    }
    let scores = score_poses(index, observed, grid, hypotheses, &rules.score);
    let usable_scores = || (0..n).filter(|&h| usable[h]).map(|h| &scores[h]);
    let violation = |s: &PoseScore| s.free_space_violation + s.scene_violation;
    let most_explained = rules.inlier_ratio
        * usable_scores()
            .map(|s| s.inlier_fraction)
            .fold(f64::NEG_INFINITY, f64::max);
    let least_violation =
        usable_scores().map(violation).fold(f64::INFINITY, f64::min) + rules.free_space_margin;
    let competing: Vec<bool> = (0..n)
        .map(|h| {
            usable[h]
                && scores[h].inlier_fraction >= most_explained
                && violation(&scores[h]) <= least_violation
        })
        .collect();
    let mut pick = least(rmse, |h| competing[h]);
    let distances_from = |p: usize| {
        pose_distances(
            index,
            hypotheses,
            &hypotheses[p],
            rules.symmetric,
            rules.rival_points,
        )
    };
    let mut distances = distances_from(pick);
    let mut polish = None;
    if rules.tie_polish_within > 0.0 {
        let within = rmse[pick] * (1.0 + rules.tie_polish_within);
        let tie: Vec<usize> = std::iter::once(pick)
            .chain((0..n).filter(|&h| {
                competing[h] && distances[h] > rules.rival_distance && rmse[h] <= within
            }))
            .collect();
        if tie.len() > 1 {
            let fine = polish_tie(&tie)?;
            let fine_rmse: Vec<f64> = fine.iter().map(|r| r.rmse).collect();
            let fine_usable: Vec<bool> = fine
                .iter()
                .map(|r| rules.usable(r.inliers, r.rmse, &r.pose.translation, centroid))
                .collect();
            let won = least(&fine_rmse, |k| fine_usable[k]);
            if tie[won] != pick {
                pick = tie[won];
                distances = distances_from(pick);
            }
            polish = Some(fine[won]);
        }
    }
    let rivals: Vec<bool> = (0..n)
        .map(|h| usable[h] && distances[h] > rules.rival_distance)
        .collect();
    let best_rival = (0..n)
        .filter(|&h| rivals[h])
        .map(|h| net(&scores[h]))
        .reduce(f64::max);
    let margin = best_rival.map_or(1.0, |b| net(&scores[pick]) - b);
    let lowest_competitor = (0..n)
        .filter(|&h| rivals[h] && competing[h])
        .map(|h| rmse[h])
        .reduce(f64::min);
    let rmse_ratio = lowest_competitor.map_or(0.0, |low| rmse[pick] / low);
    Ok(Some(Picked {
        pick,
        polish,
        scores,
        usable,
        margin,
        rmse_ratio,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Rotation3;
    use std::convert::Infallible;

    /// Points and outward normals of a 10 × 6 × 3 cm box's surface, 2 mm apart.
    fn box_surface() -> (Vec<Point3>, Vec<Point3>) {
        let half = [0.05f32, 0.03, 0.015];
        let (mut points, mut normals) = (Vec::new(), Vec::new());
        for axis in 0..3 {
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            for side in [-1.0f32, 1.0] {
                let steps = |a: usize| (half[a] / 0.001) as i32;
                for i in -steps(u)..=steps(u) {
                    for j in -steps(v)..=steps(v) {
                        if (i + j) % 2 != 0 {
                            continue;
                        }
                        let mut p = [0.0f32; 3];
                        p[axis] = side * half[axis];
                        p[u] = i as f32 * 0.001;
                        p[v] = j as f32 * 0.001;
                        let mut n = [0.0f32; 3];
                        n[axis] = side;
                        points.push(p);
                        normals.push(n);
                    }
                }
            }
        }
        (points, normals)
    }

    fn rules(tie_polish_within: f64) -> PickRules {
        PickRules {
            min_icp_inliers: 16,
            max_centre_offset: 0.1,
            score: ScoreSettings {
                inlier_distance: 0.004,
                free_space_tolerance: 0.005,
                model_stride: 1,
            },
            // Every usable hypothesis competes.
            inlier_ratio: 0.0,
            free_space_margin: 1.0,
            tie_polish_within,
            rival_distance: 0.01,
            rival_points: 64,
            symmetric: false,
        }
    }

    #[test]
    fn distinct_rotations_skip_those_near_one_taken_before() {
        let about_z = |deg: f64| *Rotation3::from_euler_angles(0.0, 0.0, deg.to_radians()).matrix();
        let rotations: Vec<Matrix3<f64>> = [0.0, 10.0, 30.0, 35.0, 70.0].map(about_z).to_vec();
        let cos_min = 20f64.to_radians().cos();
        assert_eq!(
            distinct(&rotations, &[0, 1, 2, 3, 4], 3, cos_min),
            [0, 2, 4]
        );
        assert_eq!(distinct(&rotations, &[4, 3, 2, 1, 0], 2, cos_min), [4, 3]);
        assert_eq!(
            distinct(&rotations, &[0, 1, 2, 3, 4], 9, cos_min),
            [0, 2, 4]
        );
    }

    #[test]
    fn distinct_poses_are_apart_from_pose_zero_and_each_other() {
        let (points, normals) = box_surface();
        let index = ModelIndex::new(points, normals);
        let at = |x: f64| Pose {
            rotation: Matrix3::identity(),
            translation: Vector3::new(x, 0.0, 0.5),
        };
        let poses = [at(0.0), at(0.002), at(0.03), at(0.032), at(-0.03)];
        let all = [true; 5];
        let distinct = |order: &[usize], allowed: &[bool], count: usize| {
            distinct_poses(&index, &poses, order, allowed, count, 0.01, false, 64)
        };
        assert_eq!(distinct(&[1, 2, 3, 4], &all, 3), [2, 4]);
        assert_eq!(distinct(&[3, 2, 4], &all, 3), [3, 4]);
        assert_eq!(distinct(&[1, 2, 3, 4], &all, 1), [2]);
        assert_eq!(
            distinct(&[1, 2, 3, 4], &[true, true, false, true, false], 3),
            [3]
        );
        assert!(distinct(&[1, 2, 3, 4], &all, 0).is_empty());
    }

    #[test]
    fn a_near_tie_goes_to_the_lower_polished_rmse_and_the_rival_sets_the_margin() {
        let (points, normals) = box_surface();
        let truth = Pose {
            rotation: Matrix3::identity(),
            translation: Vector3::new(0.0, 0.0, 0.5),
        };
        let seen: Vec<Point3> = points
            .iter()
            .zip(&normals)
            .filter(|(_, n)| n[2] < 0.0) // the face towards the camera
            .map(|(p, _)| {
                let v = truth.apply(p);
                [v.x as f32, v.y as f32, v.z as f32]
            })
            .collect();
        let index = ModelIndex::new(points, normals);
        let grid = DepthGrid::new(&seen, 0.002, 2.0);
        let shifted = Pose {
            translation: truth.translation + Vector3::new(0.03, 0.0, 0.0),
            ..truth
        };
        let hypotheses = [truth, shifted];
        let centroid = truth.translation;
        let polish = |rmse: [f64; 2]| -> Vec<IcpResult> {
            hypotheses
                .iter()
                .rev() // the pick (the shifted pose) first
                .zip(rmse)
                .map(|(pose, rmse)| IcpResult {
                    pose: *pose,
                    iterations: 3,
                    converged: true,
                    inliers: 100,
                    rmse,
                })
                .collect()
        };
        let pick_in =
            |hypotheses: &[Pose],
             inliers: [usize; 2],
             rmse: [f64; 2],
             within: f64,
             polish_tie: &mut dyn FnMut(&[usize]) -> Vec<IcpResult>| {
                let rules = rules(within);
                pick(
                    &index,
                    &seen,
                    &grid,
                    hypotheses,
                    &inliers,
                    &rmse,
                    &centroid,
                    &rules,
                    |tie| Ok::<_, Infallible>(polish_tie(tie)),
                )
                .unwrap()
            };
        let mut asked = Vec::new();
        let picked = pick_in(&hypotheses, [100, 100], [1e-3, 0.99e-3], 0.1, &mut |tie| {
            asked.push(tie.to_vec());
            polish([2e-3, 1e-3])
        })
        .unwrap();
        assert_eq!(asked, [vec![1, 0]]);
        assert_eq!(picked.pick, 0);
        assert_eq!(picked.polish.map(|p| p.rmse), Some(1e-3));
        assert_eq!(picked.usable, [true, true]);
        assert!(net(&picked.scores[0]) > net(&picked.scores[1]));
        assert_eq!(
            picked.margin,
            net(&picked.scores[0]) - net(&picked.scores[1])
        );
        assert_eq!(picked.rmse_ratio, 1e-3 / 0.99e-3);
        // No tie polish: the lower coarse RMSE stands, nothing polished.
        let untied = pick_in(&hypotheses, [100, 100], [1e-3, 0.99e-3], 0.0, &mut |_| {
            panic!("no tie")
        })
        .unwrap();
        assert_eq!((untied.pick, untied.polish.is_none()), (1, true));
        // Too few inliers, or the model's centre far from the cloud: not usable.
        let far = [
            truth,
            Pose {
                translation: Vector3::new(0.0, 0.0, 0.9),
                ..truth
            },
        ];
        let outcome = |hypotheses: &[Pose], inliers: [usize; 2]| {
            pick_in(hypotheses, inliers, [1e-3, 1e-3], 0.1, &mut |_| {
                panic!("no tie")
            })
            .map(|p| (p.pick, p.usable))
        };
        assert_eq!(outcome(&hypotheses, [3, 3]), None);
        assert_eq!(outcome(&far, [100, 100]), Some((0, vec![true, false])));
        assert_eq!(outcome(&hypotheses, [3, 100]), Some((1, vec![false, true])));
    }
}
