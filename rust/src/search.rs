//! Viewpoint search: cosine top-K over a codebook's codes, and verification
//! of candidate poses by how well the observed keypoints land on the model.

use rayon::prelude::*;

use crate::index::{ModelIndex, Pose};
use crate::threads;
use crate::Point3;

/// The `k` codes most similar to `query` (dot product of unit codes = cosine),
/// best first, as `(view index, similarity)`. `codes` is row-major (V × dim).
pub fn top_k(codes: &[f32], dim: usize, query: &[f32], k: usize) -> Vec<(usize, f32)> {
    assert!(
        dim > 0 && codes.len().is_multiple_of(dim) && query.len() == dim,
        "codes must be V × dim"
    );
    let mut scored = similarities(codes, dim, query);
    let k = k.min(scored.len());
    if k == 0 {
        return Vec::new();
    }
    // Highest similarity first; ties broken by view index, so results are deterministic.
    let order = |a: &(usize, f32), b: &(usize, f32)| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0));
    scored.select_nth_unstable_by(k - 1, order);
    scored.truncate(k);
    scored.sort_by(order);
    scored
}

/// Codes whose similarities [`similarities`] sums side by side.
const CODES_AT_ONCE: usize = 8;

/// `(view index, similarity)` of each of the row-major `codes` (V × dim)
/// to `query`. Each code's products are summed in order, as
/// `Iterator::sum` would (from −0.0), so every similarity is the same bit
/// for bit; [`CODES_AT_ONCE`] codes are summed side by side, so that the
/// sums do not wait on one another's additions.
fn similarities(codes: &[f32], dim: usize, query: &[f32]) -> Vec<(usize, f32)> {
    let mut scored = Vec::with_capacity(codes.len() / dim);
    let mut blocks = codes.chunks_exact(dim * CODES_AT_ONCE);
    for block in blocks.by_ref() {
        let rows: [&[f32]; CODES_AT_ONCE] = std::array::from_fn(|j| &block[j * dim..][..dim]);
        let mut sums = [-0.0f32; CODES_AT_ONCE];
        for (d, &q) in query.iter().enumerate() {
            for (sum, row) in sums.iter_mut().zip(&rows) {
                *sum += row[d] * q;
            }
        }
        let first = scored.len();
        scored.extend(sums.iter().enumerate().map(|(j, &sum)| (first + j, sum)));
    }
    let first = scored.len();
    scored.extend(
        blocks
            .remainder()
            .chunks_exact(dim)
            .enumerate()
            .map(|(j, code)| (first + j, code.iter().zip(query).map(|(a, b)| a * b).sum())),
    );
    scored
}

/// Mean distance (metres) from the observed `keypoints` (camera frame) to the
/// model surface, with each candidate pose (model → camera): lower is better.
pub fn verify(index: &ModelIndex, keypoints: &[Point3], candidates: &[Pose]) -> Vec<f64> {
    candidates
        .iter()
        .map(|pose| {
            let to_model = pose.inverse();
            let total: f64 = keypoints
                .iter()
                .map(|p| {
                    let m = to_model.apply(p);
                    (index.nearest(&[m.x as f32, m.y as f32, m.z as f32]).1 as f64).sqrt()
                })
                .sum();
            total / keypoints.len().max(1) as f64
        })
        .collect()
}

/// Distance (metres) from each of `points` (camera frame) to the model
/// surface, for each pose (model → camera): row-major, poses × points.
/// `along_normal`: the distance to the nearest model point's tangent plane
/// instead (blind to how the surface happens to be sampled). A pose whose
/// distances sum past `stop_above` × N (metres; with a millionth's slack
/// for the caller's own summation) is not finished: the rest of its row
/// reads infinity, as its mean is above `stop_above` either way. Poses run
/// in parallel (offline work such as symmetry detection).
pub fn point_distances(
    index: &ModelIndex,
    points: &[Point3],
    poses: &[Pose],
    along_normal: bool,
    stop_above: Option<f64>,
) -> Vec<f64> {
    let mut out = vec![0.0; poses.len() * points.len()];
    if points.is_empty() {
        return out;
    }
    let stop = stop_above.map_or(f64::INFINITY, |s| s * points.len() as f64 * (1.0 + 1e-6));
    threads::install(|| {
        out.par_chunks_mut(points.len())
            .zip(poses.par_iter())
            .for_each(|(row, pose)| {
                let to_model = pose.inverse();
                let mut sum = 0.0;
                for (d, p) in row.iter_mut().zip(points) {
                    if sum > stop {
                        *d = f64::INFINITY;
                        continue;
                    }
                    let m = to_model.apply(p);
                    let m = [m.x as f32, m.y as f32, m.z as f32];
                    let (i, squared) = index.nearest(&m);
                    *d = if along_normal {
                        let (q, n) = (index.points()[i], index.normals()[i]);
                        (0..3)
                            .map(|k| ((m[k] - q[k]) * n[k]) as f64)
                            .sum::<f64>()
                            .abs()
                    } else {
                        (squared as f64).sqrt()
                    };
                    sum += *d;
                }
            })
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix3, Rotation3, Vector3};

    #[test]
    fn similarities_are_each_codes_sum_in_order() {
        let mut rng = crate::rng::SplitMix64::new(7);
        let mut uniform = || rng.next_f64() as f32 - 0.5;
        let dim = 64;
        for views in [0, 1, 7, 8, 9, 2100] {
            let mut codes: Vec<f32> = (0..views * dim).map(|_| uniform()).collect();
            let mut query: Vec<f32> = (0..dim).map(|_| uniform()).collect();
            if views > 3 {
                // A code of zeros against a query of negative values: every
                // product −0.0, so the sum's sign is its start's.
                codes[3 * dim..4 * dim].fill(0.0);
                query.iter_mut().for_each(|q| *q = -q.abs() - 0.1);
            }
            let one_at_a_time: Vec<u32> = codes
                .chunks_exact(dim)
                .map(|code| {
                    let sum: f32 = code.iter().zip(&query).map(|(a, b)| a * b).sum();
                    sum.to_bits()
                })
                .collect();
            let found = similarities(&codes, dim, &query);
            assert!(found.iter().enumerate().all(|(v, &(i, _))| i == v));
            let bits: Vec<u32> = found.iter().map(|&(_, s)| s.to_bits()).collect();
            assert_eq!(bits, one_at_a_time, "{views} views");
        }
    }

    #[test]
    fn point_distances_are_per_point_and_per_pose() {
        // A flat square of points (z = 0) with normals +z.
        let points: Vec<Point3> = (0..100)
            .map(|i| [(i % 10) as f32 * 0.01, (i / 10) as f32 * 0.01, 0.0])
            .collect();
        let normals = vec![[0.0f32, 0.0, 1.0]; points.len()];
        let index = ModelIndex::new(points.clone(), normals);
        let lifted = Pose {
            rotation: Matrix3::identity(),
            translation: Vector3::new(0.0, 0.0, -0.003), // model 3 mm below the points
        };
        let slid = Pose {
            rotation: Matrix3::identity(),
            translation: Vector3::new(0.005, 0.0, 0.0), // half a spacing along the plane
        };
        let probe: Vec<Point3> = points[..20].to_vec();
        let d = point_distances(&index, &probe, &[lifted, slid], false, None);
        assert_eq!(d.len(), 2 * probe.len());
        assert!(d[..20].iter().all(|v| (v - 0.003).abs() < 1e-6), "{d:?}");
        assert!(d[20..].iter().all(|v| (v - 0.005).abs() < 1e-6), "{d:?}");
        // Along the normal, sliding within the plane costs nothing.
        let n = point_distances(&index, &probe, &[lifted, slid], true, None);
        assert!(n[..20].iter().all(|v| (v - 0.003).abs() < 1e-6), "{n:?}");
        assert!(n[20..].iter().all(|v| v.abs() < 1e-6), "{n:?}");
        // A row whose mean is past the stop is cut short; one below it is whole.
        let cut = point_distances(&index, &probe, &[lifted, slid], false, Some(0.004));
        let kept = cut[..20].iter().zip(&d[..20]).all(|(a, b)| a == b);
        assert!(kept, "{cut:?}");
        assert!(cut[20..].iter().any(|v| v.is_infinite()), "{cut:?}");
        assert!(
            cut[20..]
                .iter()
                .all(|v| v.is_infinite() || (v - 0.005).abs() < 1e-6),
            "{cut:?}"
        );
    }

    #[test]
    fn top_k_matches_a_full_sort() {
        let dim = 4;
        let codes: Vec<f32> = (0..400)
            .map(|i| ((i * 37 % 101) as f32 / 50.0) - 1.0)
            .collect();
        let query = [0.5f32, -0.5, 0.5, 0.5];
        let mut all: Vec<(usize, f32)> = codes
            .chunks_exact(dim)
            .enumerate()
            .map(|(v, c)| (v, c.iter().zip(&query).map(|(a, b)| a * b).sum()))
            .collect();
        all.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
        assert_eq!(top_k(&codes, dim, &query, 16), all[..16].to_vec());
        assert_eq!(top_k(&codes, dim, &query, 1000).len(), 100);
    }

    #[test]
    fn the_true_pose_verifies_best() {
        let points: Vec<Point3> = (0..2000)
            .map(|i| {
                let t = i as f32 * 0.01;
                [
                    0.05 * t.cos(),
                    0.03 * (2.0 * t).sin(),
                    0.002 * i as f32 - 2.0,
                ]
            })
            .map(|p| [p[0], p[1], p[2] * 0.04])
            .collect();
        let normals = vec![[0.0, 0.0, 1.0]; points.len()];
        let index = ModelIndex::new(points.clone(), normals);
        let truth = Pose {
            rotation: Matrix3::identity(),
            translation: Vector3::new(0.0, 0.0, 0.5),
        };
        let keypoints: Vec<Point3> = points
            .iter()
            .step_by(61)
            .map(|p| {
                let v = truth.apply(p);
                [v.x as f32, v.y as f32, v.z as f32]
            })
            .collect();
        let wrong = Pose {
            rotation: *Rotation3::from_euler_angles(0.0, 0.0, 0.5).matrix(),
            ..truth
        };
        let scores = verify(&index, &keypoints, &[wrong, truth]);
        assert!(scores[1] < 1e-6 && scores[0] > 1e-3, "{scores:?}");
    }
}
