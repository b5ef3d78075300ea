//! Farthest-point sampling: picks `m` points that cover a cloud evenly,
//! whatever the sensor's density pattern, so maps of a model and of an
//! observed cloud are comparable.

use crate::Point3;

/// Indices of `m` points chosen by farthest-point sampling.
///
/// Starts from the point farthest from the centroid (independent of input
/// order), then repeatedly takes the point farthest from all chosen so far;
/// ties go to the lowest index. When the cloud has fewer than `m` points,
/// all are chosen and the list is padded by cycling through them, so the
/// result always has exactly `m` entries. An empty cloud gives an empty list.
pub fn farthest_point_sample(points: &[Point3], m: usize) -> Vec<u32> {
    let n = points.len();
    if n == 0 || m == 0 {
        return Vec::new();
    }
    // Structure-of-arrays padded to whole lanes. Padding slots carry a
    // distance of −∞, so they are never the farthest point.
    let padded = n.div_ceil(LANES) * LANES;
    let mut xs = vec![0.0f32; padded];
    let mut ys = vec![0.0f32; padded];
    let mut zs = vec![0.0f32; padded];
    for (i, p) in points.iter().enumerate() {
        (xs[i], ys[i], zs[i]) = (p[0], p[1], p[2]);
    }
    let inv_n = 1.0 / n as f32;
    let centroid = [
        xs[..n].iter().sum::<f32>() * inv_n,
        ys[..n].iter().sum::<f32>() * inv_n,
        zs[..n].iter().sum::<f32>() * inv_n,
    ];
    let mut min_sq = vec![f32::NEG_INFINITY; padded];
    min_sq[..n].fill(f32::INFINITY);

    // The first pick is the farthest point from the centroid: the same
    // update-and-argmax step, on a copy whose distances are all still ∞.
    let mut scratch = min_sq.clone();
    let take = m.min(n);
    let mut chosen = Vec::with_capacity(m);
    let mut current = update_and_argmax(&xs, &ys, &zs, &mut scratch, centroid);
    chosen.push(current as u32);
    for _ in 1..take {
        let c = [xs[current], ys[current], zs[current]];
        current = update_and_argmax(&xs, &ys, &zs, &mut min_sq, c);
        chosen.push(current as u32);
    }
    for k in take..m {
        chosen.push(chosen[k % take]);
    }
    chosen
}

/// Lanes processed together; written so the compiler keeps them in vector
/// registers (two SSE or one AVX register of f32).
const LANES: usize = 8;

/// Lowers each point's distance-to-chosen-set with its distance to `c`, and
/// returns the index of the largest result (lowest index on ties).
#[inline]
fn update_and_argmax(xs: &[f32], ys: &[f32], zs: &[f32], min_sq: &mut [f32], c: Point3) -> usize {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: SSE2 is part of the x86-64 baseline; all slices hold whole lanes.
    let (best, best_at) = unsafe { sse2::update_lanes(xs, ys, zs, min_sq, c) };
    #[cfg(not(target_arch = "x86_64"))]
    let (best, best_at) = update_lanes(xs, ys, zs, min_sq, c);

    let mut winner = 0;
    for l in 1..LANES {
        if best[l] > best[winner] || (best[l] == best[winner] && best_at[l] < best_at[winner]) {
            winner = l;
        }
    }
    best_at[winner] as usize
}

/// Portable kernel: per lane, the largest lowered distance and where it is.
#[cfg_attr(target_arch = "x86_64", allow(dead_code))]
fn update_lanes(
    xs: &[f32],
    ys: &[f32],
    zs: &[f32],
    min_sq: &mut [f32],
    c: Point3,
) -> ([f32; LANES], [u32; LANES]) {
    let mut best = [f32::NEG_INFINITY; LANES];
    let mut best_at = [0u32; LANES];
    for i in 0..xs.len() {
        let l = i % LANES;
        let (dx, dy, dz) = (xs[i] - c[0], ys[i] - c[1], zs[i] - c[2]);
        let d = dx * dx + dy * dy + dz * dz;
        let lowered = if d < min_sq[i] { d } else { min_sq[i] };
        min_sq[i] = lowered;
        if lowered > best[l] {
            best[l] = lowered;
            best_at[l] = i as u32;
        }
    }
    (best, best_at)
}

#[cfg(target_arch = "x86_64")]
mod sse2 {
    use super::LANES;
    use crate::Point3;
    use std::arch::x86_64::*;

    /// Same result as `update_lanes`, two 4-wide registers per step. Lane `l`
    /// covers indices `≡ l (mod 8)`, exactly as the portable kernel.
    #[target_feature(enable = "sse2")]
    pub(super) unsafe fn update_lanes(
        xs: &[f32],
        ys: &[f32],
        zs: &[f32],
        min_sq: &mut [f32],
        c: Point3,
    ) -> ([f32; LANES], [u32; LANES]) {
        let (cx, cy, cz) = (_mm_set1_ps(c[0]), _mm_set1_ps(c[1]), _mm_set1_ps(c[2]));
        let mut best = [_mm_set1_ps(f32::NEG_INFINITY); 2];
        let mut best_at = [_mm_setzero_si128(); 2];
        let mut index = [_mm_setr_epi32(0, 1, 2, 3), _mm_setr_epi32(4, 5, 6, 7)];
        let step = _mm_set1_epi32(LANES as i32);
        let (px, py, pz, pd) = (xs.as_ptr(), ys.as_ptr(), zs.as_ptr(), min_sq.as_mut_ptr());
        let mut i = 0;
        while i < xs.len() {
            for h in 0..2 {
                let k = i + 4 * h;
                let dx = _mm_sub_ps(_mm_loadu_ps(px.add(k)), cx);
                let dy = _mm_sub_ps(_mm_loadu_ps(py.add(k)), cy);
                let dz = _mm_sub_ps(_mm_loadu_ps(pz.add(k)), cz);
                let d = _mm_add_ps(
                    _mm_add_ps(_mm_mul_ps(dx, dx), _mm_mul_ps(dy, dy)),
                    _mm_mul_ps(dz, dz),
                );
                // minps(d, old) returns old when d is not smaller: `if d < old {d} else {old}`.
                let lowered = _mm_min_ps(d, _mm_loadu_ps(pd.add(k)));
                _mm_storeu_ps(pd.add(k), lowered);
                let better = _mm_cmpgt_ps(lowered, best[h]);
                best[h] = _mm_or_ps(_mm_and_ps(better, lowered), _mm_andnot_ps(better, best[h]));
                let better_i = _mm_castps_si128(better);
                best_at[h] = _mm_or_si128(
                    _mm_and_si128(better_i, index[h]),
                    _mm_andnot_si128(better_i, best_at[h]),
                );
                index[h] = _mm_add_epi32(index[h], step);
            }
            i += LANES;
        }
        let mut values = [0.0f32; LANES];
        let mut at = [0u32; LANES];
        _mm_storeu_ps(values.as_mut_ptr(), best[0]);
        _mm_storeu_ps(values.as_mut_ptr().add(4), best[1]);
        _mm_storeu_si128(at.as_mut_ptr() as *mut __m128i, best_at[0]);
        _mm_storeu_si128(at.as_mut_ptr().add(4) as *mut __m128i, best_at[1]);
        (values, at)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    fn random_cloud(n: usize, seed: u64) -> Vec<Point3> {
        let mut rng = SplitMix64::new(seed);
        (0..n)
            .map(|_| {
                [
                    rng.next_f64() as f32,
                    rng.next_f64() as f32,
                    rng.next_f64() as f32,
                ]
            })
            .collect()
    }

    #[test]
    fn picks_distinct_points_that_spread_out() {
        let cloud = random_cloud(2000, 1);
        let idx = farthest_point_sample(&cloud, 64);
        let mut sorted = idx.clone();
        sorted.sort();
        sorted.dedup();
        assert_eq!(sorted.len(), 64, "FPS must not repeat points when n >= m");
        // Every cloud point lies near a chosen point: coverage radius of 64
        // points in a unit cube is well under 0.35.
        let chosen: Vec<Point3> = idx.iter().map(|&i| cloud[i as usize]).collect();
        let worst = cloud
            .iter()
            .map(|p| {
                chosen
                    .iter()
                    .map(|c| (0..3).map(|k| (p[k] - c[k]).powi(2)).sum::<f32>())
                    .fold(f32::INFINITY, f32::min)
            })
            .fold(0.0f32, f32::max)
            .sqrt();
        assert!(worst < 0.35, "coverage radius {worst}");
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn vector_kernel_matches_portable_kernel() {
        let cloud = random_cloud(1003, 4);
        let n = cloud.len().div_ceil(LANES) * LANES;
        let col = |k: usize| {
            let mut v: Vec<f32> = cloud.iter().map(|p| p[k]).collect();
            v.resize(n, 0.0);
            v
        };
        let (xs, ys, zs) = (col(0), col(1), col(2));
        let mut a = vec![f32::NEG_INFINITY; n];
        a[..cloud.len()].fill(f32::INFINITY);
        let mut b = a.clone();
        for c in [[0.5, 0.5, 0.5], [0.0, 1.0, 0.2], [0.9, 0.1, 0.4]] {
            let portable = update_lanes(&xs, &ys, &zs, &mut a, c);
            let vector = unsafe { sse2::update_lanes(&xs, &ys, &zs, &mut b, c) };
            assert_eq!(portable, vector);
            assert_eq!(a, b);
        }
    }

    #[test]
    fn starts_at_the_point_farthest_from_the_centroid() {
        let cloud = vec![
            [0.0, 0.0, 0.0],
            [0.1, 0.0, 0.0],
            [5.0, 0.0, 0.0],
            [0.0, 0.2, 0.0],
        ];
        let idx = farthest_point_sample(&cloud, 2);
        assert_eq!(idx, vec![2, 3]); // (0, 0.2, 0) is 5.004 from (5, 0, 0)
    }

    #[test]
    fn pads_small_clouds_by_cycling_and_handles_empty() {
        let cloud = random_cloud(3, 2);
        let idx = farthest_point_sample(&cloud, 7);
        assert_eq!(idx.len(), 7);
        assert_eq!(&idx[3..6], &idx[0..3]);
        assert_eq!(idx[6], idx[0]);
        assert!(farthest_point_sample(&[], 5).is_empty());
    }
}
