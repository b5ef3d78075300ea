//! Point-to-plane ICP against the standard model: polishes a pose found by
//! viewpoint search. Works in the model frame, where the model's kd-tree is
//! built once per codebook.

use std::sync::Arc;

use nalgebra::{Matrix6, Rotation3, Vector3, Vector6};

use crate::index::{as_queries, ModelIndex, Pose};
use crate::threads;
use crate::Point3;

/// An estimate's ICP has converged when an update's rotation (radians) and
/// translation (metres) together move less than this: 0.3 mm (or 0.3 mrad),
/// a tenth of a depth camera's noise at a metre; smaller steps made no pose
/// right or wrong on the tuning parts (`docs/tuning.md`, "The Rust core's
/// constants"). The symmetry search, whose turns a codebook stores, stops
/// at finer steps ([`ModelIndex::refine_until`]).
pub const CONVERGED: f64 = 3e-4;

/// Damping of ICP's normal equations, relative to their mean diagonal: far
/// below any constrained direction's curvature, enough to make a view's
/// unconstrained directions solvable (a zero step along them).
const DAMPING: f64 = 1e-9;

/// [`ModelIndex::refine_each`] runs this many starts or more in parallel on
/// the core's pool (a second search's new hypotheses, when it has 4 or
/// more); fewer (the first search's 3) one after another, or split between
/// the caller and one worker when asked (`two_cores`).
pub const PARALLEL_STARTS: usize = 4;

/// One ICP correspondence, model frame: the moved cloud point, its nearest
/// model point, that point's normal, and their distance (metres).
type Pair = (Vector3<f64>, Vector3<f64>, Vector3<f64>, f64);

#[derive(Clone, Copy, Debug)]
pub struct IcpResult {
    /// Refined pose, model frame → camera frame.
    pub pose: Pose,
    pub iterations: usize,
    /// The last update moved less than the convergence threshold.
    pub converged: bool,
    /// Cloud points paired with the model in the last iteration.
    pub inliers: usize,
    /// Root-mean-square point-to-plane distance of the inliers, metres.
    pub rmse: f64,
}

impl ModelIndex {
    /// [`refine_until`](Self::refine_until) `converged` from each of several
    /// `starts`: one result per start, in order. Refining a few distinct hypotheses and keeping the
    /// best fit resolves near-symmetric objects whose turned-over pose
    /// verifies almost as well as the true one. Fewer than
    /// [`PARALLEL_STARTS`] starts run in the calling thread (a few
    /// sub-millisecond ICPs gain nothing from a whole pool, and waking one
    /// can cost milliseconds on a busy CPU) or, with `two_cores`, shared
    /// with one of the pool's threads ([`threads::on_two_cores`]: each
    /// takes the next start not yet taken, so a thread slow to wake costs
    /// at most the start it took). Each start's result is its own either
    /// way.
    pub fn refine_each(
        self: &Arc<Self>,
        cloud: &[Point3],
        starts: &[Pose],
        max_iterations: usize,
        max_distance: f64,
        two_cores: bool,
        converged: f64,
    ) -> Vec<IcpResult> {
        let icp = |start: &Pose| {
            self.refine_until(cloud, *start, max_iterations, max_distance, converged)
        };
        if starts.len() >= PARALLEL_STARTS {
            threads::map(starts, 1, icp)
        } else if two_cores && starts.len() >= 2 {
            // The loop owns its inputs: the index shared, the cloud (a few
            // hundred points) and the starts copied.
            let (index, points) = (Arc::clone(self), cloud.to_vec());
            threads::on_two_cores(starts.to_vec(), move |start| {
                index.refine_until(&points, *start, max_iterations, max_distance, converged)
            })
        } else {
            starts.iter().map(icp).collect()
        }
    }

    /// Point-to-plane ICP of an observed `cloud` (camera frame, metres) onto
    /// the model, starting from `initial` (model → camera). Pairs farther
    /// than `max_distance` metres, or than 3× the median pair distance, are
    /// ignored. Stops after `max_iterations` or when an update moves less
    /// than [`CONVERGED`].
    pub fn refine(
        &self,
        cloud: &[Point3],
        initial: Pose,
        max_iterations: usize,
        max_distance: f64,
    ) -> IcpResult {
        self.refine_until(cloud, initial, max_iterations, max_distance, CONVERGED)
    }

    /// [`refine`](Self::refine) that stops when an update moves less than
    /// `converged` (radians and metres together).
    pub fn refine_until(
        &self,
        cloud: &[Point3],
        initial: Pose,
        max_iterations: usize,
        max_distance: f64,
        converged: f64,
    ) -> IcpResult {
        let mut to_model = initial.inverse();
        let mut result = IcpResult {
            pose: initial,
            iterations: 0,
            converged: false,
            inliers: 0,
            rmse: f64::NAN,
        };
        let mut pairs: Vec<Pair> = Vec::with_capacity(cloud.len());
        for iteration in 1..=max_iterations {
            pairs.clear();
            let sources: Vec<Vector3<f64>> = cloud.iter().map(|p| to_model.apply(p)).collect();
            let found = self.nearest_each_within(&as_queries(&sources), max_distance);
            for (&source, found) in sources.iter().zip(found) {
                if let Some((i, sq)) = found {
                    let d = (sq as f64).sqrt();
                    let q = self.points()[i];
                    let n = self.normals()[i];
                    pairs.push((
                        source,
                        Vector3::new(q[0] as f64, q[1] as f64, q[2] as f64),
                        Vector3::new(n[0] as f64, n[1] as f64, n[2] as f64),
                        d,
                    ));
                }
            }
            if pairs.len() < 6 {
                break;
            }
            let mut distances: Vec<f64> = pairs.iter().map(|p| p.3).collect();
            let mid = distances.len() / 2;
            let median = *distances.select_nth_unstable_by(mid, f64::total_cmp).1;
            let cutoff = (3.0 * median).max(1e-4);

            // Linearised: residual (s + ω×s + δt − q)·n = 0 for the update (ω, δt).
            // JᵀJ is symmetric: its upper triangle is summed (each entry the
            // same products in the same order as the whole outer product's).
            let mut jtj = Matrix6::<f64>::zeros();
            let mut jtr = Vector6::<f64>::zeros();
            let (mut inliers, mut sum_sq) = (0usize, 0.0f64);
            for (s, q, n, d) in &pairs {
                if *d > cutoff {
                    continue;
                }
                let r = (s - q).dot(n);
                let c = s.cross(n);
                let j = Vector6::new(c.x, c.y, c.z, n.x, n.y, n.z);
                for a in 0..6 {
                    for b in a..6 {
                        jtj[(a, b)] += j[a] * j[b];
                    }
                }
                jtr += j * r;
                inliers += 1;
                sum_sq += r * r;
            }
            jtj.fill_lower_triangle_with_upper_triangle();
            // A view that leaves a direction unconstrained (one face of a
            // box: no normal along it) makes JᵀJ singular; a little damping
            // keeps the step at zero along that direction instead of ending
            // ICP with no result (Levenberg–Marquardt with a fixed λ).
            let damping = DAMPING * (jtj.trace() / 6.0).max(f64::MIN_POSITIVE);
            let Some(chol) = (jtj + Matrix6::identity() * damping).cholesky() else {
                break;
            };
            let x = chol.solve(&(-jtr));
            let omega = Vector3::new(x[0], x[1], x[2]);
            let delta = Pose {
                rotation: *Rotation3::new(omega).matrix(),
                translation: Vector3::new(x[3], x[4], x[5]),
            };
            to_model = Pose {
                rotation: delta.rotation * to_model.rotation,
                translation: delta.rotation * to_model.translation + delta.translation,
            };
            result = IcpResult {
                pose: to_model.inverse(),
                iterations: iteration,
                converged: false,
                inliers,
                rmse: (sum_sq / inliers.max(1) as f64).sqrt(),
            };
            if x.norm() < converged {
                result.converged = true;
                break;
            }
        }
        result
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::model::tests::cube_mesh;
    use crate::model::StandardModel;

    /// An L-shaped bracket of boxes: no symmetry, so ICP has one answer.
    pub(crate) fn bracket() -> StandardModel {
        let (v1, f1) = cube_mesh(0.05);
        let (v2, f2) = cube_mesh(0.02);
        let mut vertices: Vec<[f64; 3]> =
            v1.iter().map(|p| [p[0] * 1.6, p[1] * 0.6, p[2]]).collect();
        vertices.extend(v2.iter().map(|p| [p[0] + 0.06, p[1] + 0.03, p[2] + 0.07]));
        let mut faces = f1.clone();
        faces.extend(f2.iter().map(|f| f.map(|i| i + 8)));
        StandardModel::from_mesh(&vertices, &faces, 4096, 11).unwrap()
    }

    pub(crate) fn pose(axis: Vector3<f64>, angle: f64, t: Vector3<f64>) -> Pose {
        Pose {
            rotation: *Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis), angle)
                .matrix(),
            translation: t,
        }
    }

    #[test]
    fn recovers_a_known_transform_from_a_perturbed_start() {
        let model = bracket();
        let index = ModelIndex::new(model.points.clone(), model.normals.clone());
        let truth = pose(
            Vector3::new(0.3, -1.0, 0.5),
            2.0,
            Vector3::new(0.05, -0.02, 0.7),
        );
        let cloud: Vec<Point3> = model
            .points
            .iter()
            .step_by(3)
            .map(|p| {
                let v = truth.apply(p);
                [v.x as f32, v.y as f32, v.z as f32]
            })
            .collect();
        let nudge = pose(
            Vector3::new(1.0, 1.0, 0.0),
            0.12,
            Vector3::new(0.008, -0.006, 0.01),
        );
        let start = Pose {
            rotation: nudge.rotation * truth.rotation,
            translation: truth.translation + nudge.translation,
        };
        let out = index.refine(&cloud, start, 30, 0.05);
        let angle =
            Rotation3::from_matrix(&(out.pose.rotation * truth.rotation.transpose())).angle();
        assert!(
            angle.to_degrees() < 0.05,
            "rotation error {}°",
            angle.to_degrees()
        );
        assert!((out.pose.translation - truth.translation).norm() < 1e-4);
        assert!(
            out.converged && out.rmse < 1e-4 && out.inliers > 1000,
            "{out:?}"
        );
    }

    #[test]
    fn refining_several_starts_gives_each_start_its_own_result() {
        let model = bracket();
        let index = Arc::new(ModelIndex::new(model.points.clone(), model.normals.clone()));
        let truth = pose(
            Vector3::new(1.0, 0.2, -0.4),
            0.7,
            Vector3::new(0.0, 0.03, 0.6),
        );
        let cloud: Vec<Point3> = model
            .points
            .iter()
            .step_by(5)
            .map(|p| {
                let v = truth.apply(p);
                [v.x as f32, v.y as f32, v.z as f32]
            })
            .collect();
        // Six starts: refined in parallel (PARALLEL_STARTS), as the second
        // search's are; the first three are checked for what they find.
        let starts: Vec<Pose> = [0.05, 0.1, 2.5, 0.07, 0.3, 1.2]
            .iter()
            .map(|&a| {
                let n = pose(Vector3::new(0.0, 1.0, 1.0), a, Vector3::zeros());
                Pose {
                    rotation: n.rotation * truth.rotation,
                    ..truth
                }
            })
            .collect();
        let each = index.refine_each(&cloud, &starts, 25, 0.05, false, CONVERGED);
        assert_eq!(each.len(), starts.len());
        for (start, out) in starts.iter().zip(&each) {
            let alone = index.refine(&cloud, *start, 25, 0.05);
            assert_eq!(
                out.pose, alone.pose,
                "several starts at once and one at a time must agree exactly"
            );
        }
        // Every field of each result, bit for bit.
        let keys = |results: &[IcpResult]| -> Vec<_> {
            results
                .iter()
                .map(|r| {
                    (
                        r.pose,
                        r.iterations,
                        r.converged,
                        r.inliers,
                        r.rmse.to_bits(),
                    )
                })
                .collect()
        };
        for count in 1..=starts.len() {
            let split = index.refine_each(&cloud, &starts[..count], 25, 0.05, true, CONVERGED);
            assert_eq!(
                keys(&split),
                keys(&each[..count]),
                "split between two cores, {count} starts"
            );
        }
        // With every worker busy, the caller takes the handed half back and
        // refines it itself: the same results.
        {
            let _one_at_a_time = threads::tests::HOLDING
                .lock()
                .unwrap_or_else(|p| p.into_inner());
            let release = threads::tests::hold_the_workers();
            let taken_back = index.refine_each(&cloud, &starts[..3], 25, 0.05, true, CONVERGED);
            drop(release);
            assert_eq!(
                keys(&taken_back),
                keys(&each[..3]),
                "the half taken back by the caller"
            );
        }
        // The near starts converge to the truth; the turned-over one fits worse.
        assert!(each[0].rmse < 1e-4 && each[1].rmse < 1e-4, "{each:?}");
        assert!(
            each[2].rmse > 10.0 * each[0].rmse || each[2].inliers < each[0].inliers,
            "{each:?}"
        );
    }

    #[test]
    fn nearest_matches_brute_force() {
        let model = bracket();
        let index = ModelIndex::new(model.points.clone(), model.normals.clone());
        for q in [[0.0f32, 0.0, 0.0], [0.1, 0.02, -0.03], [-0.2, 0.5, 0.1]] {
            let (i, sq) = index.nearest(&q);
            let brute = model
                .points
                .iter()
                .map(|p| (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f32>())
                .fold(f32::INFINITY, f32::min);
            assert!((sq - brute).abs() < 1e-9);
            assert_eq!(index.nearest_k(&q, 3)[0], i);
        }
    }

    #[test]
    fn the_grid_of_cells_finds_the_kd_trees_nearest_point_near_and_far() {
        let model = bracket();
        let index = ModelIndex::new(model.points.clone(), model.normals.clone());
        let mut state = 7u64;
        let mut uniform = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        };
        // Near the surface (what ICP asks), and out to well beyond the model.
        for reach in [0.002f32, 0.01, 0.05, 0.3] {
            for k in 0..2000 {
                let p = model.points[(k * 7) % model.points.len()];
                let q = [
                    p[0] + reach * uniform(),
                    p[1] + reach * uniform(),
                    p[2] + reach * uniform(),
                ];
                let (i, d) = index.nearest(&q);
                let (j, e) = index.nearest_in_tree(&q);
                assert_eq!(d, e, "same squared distance at {q:?}");
                assert!(i == j || model.points[i] == model.points[j], "{i} vs {j}");
                for max_distance in [0.001, 0.005, 0.02, 0.1] {
                    let within = index.nearest_within(&q, max_distance);
                    let expected = ((e as f64).sqrt() <= max_distance).then_some(e);
                    assert_eq!(
                        within.map(|w| w.1),
                        expected,
                        "within {max_distance} m of {q:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn a_batch_of_look_ups_answers_as_one_at_a_time() {
        let model = bracket();
        let index = ModelIndex::new(model.points.clone(), model.normals.clone());
        // Near the surface, off it, far beyond the grid and not finite.
        let mut queries: Vec<Point3> = model
            .points
            .iter()
            .step_by(3)
            .enumerate()
            .map(|(k, p)| {
                let reach = [0.0005f32, 0.004, 0.03, 0.4][k % 4];
                let turn = k as f32 * 0.7;
                [
                    p[0] + reach * turn.cos(),
                    p[1] + reach * turn.sin(),
                    p[2] - reach,
                ]
            })
            .collect();
        queries.extend([[f32::NAN, 0.0, 0.0], [1e30, 0.0, 0.0]]);
        for max_distance in [0.001, 0.01, 0.1, f64::INFINITY] {
            let one_at_a_time: Vec<_> = queries
                .iter()
                .map(|q| index.nearest_within(q, max_distance))
                .collect();
            assert_eq!(
                index.nearest_each_within(&queries, max_distance),
                one_at_a_time
            );
        }
        let empty = ModelIndex::new(Vec::new(), Vec::new());
        assert_eq!(
            empty.nearest_each_within(&queries[..2], 0.1),
            queries[..2]
                .iter()
                .map(|q| empty.nearest_within(q, 0.1))
                .collect::<Vec<_>>()
        );
    }
}
