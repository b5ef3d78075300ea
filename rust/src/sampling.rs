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

/// Lanes processed together (and the padding of the point arrays): one
/// AVX-512 register, two AVX or four SSE registers of f32. The result is the same
/// whatever the lane count: the largest distance, lowest index on ties.
const LANES: usize = 16;

/// Lowers each point's distance-to-chosen-set with its distance to `c`, and
/// returns the index of the largest result (lowest index on ties).
#[inline]
fn update_and_argmax(xs: &[f32], ys: &[f32], zs: &[f32], min_sq: &mut [f32], c: Point3) -> usize {
    #[cfg(target_arch = "x86_64")]
    let (best, best_at) = if std::arch::is_x86_feature_detected!("avx512f") {
        // SAFETY: AVX-512F is present (checked above); all slices hold whole lanes.
        unsafe { x86::update_lanes_avx512(xs, ys, zs, min_sq, c) }
    } else if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 is present (checked above); all slices hold whole lanes.
        unsafe { x86::update_lanes_avx2(xs, ys, zs, min_sq, c) }
    } else {
        // SAFETY: SSE2 is part of the x86-64 baseline; all slices hold whole lanes.
        unsafe { x86::update_lanes_sse2(xs, ys, zs, min_sq, c) }
    };
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
#[cfg_attr(all(target_arch = "x86_64", not(test)), allow(dead_code))]
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

/// The portable kernel's result in SSE2, AVX2 and AVX-512 registers
/// (AVX-512's 16 lanes take a pass over the points in half AVX2's
/// instructions): lane `l`
/// covers indices `≡ l (mod LANES)`, with the same operations in the same
/// order (no fused multiply-add), so the same bits.
#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::LANES;
    use crate::Point3;
    use std::arch::x86_64::*;

    #[target_feature(enable = "sse2")]
    pub(super) unsafe fn update_lanes_sse2(
        xs: &[f32],
        ys: &[f32],
        zs: &[f32],
        min_sq: &mut [f32],
        c: Point3,
    ) -> ([f32; LANES], [u32; LANES]) {
        const REGS: usize = LANES / 4;
        let (cx, cy, cz) = (_mm_set1_ps(c[0]), _mm_set1_ps(c[1]), _mm_set1_ps(c[2]));
        let mut best = [_mm_set1_ps(f32::NEG_INFINITY); REGS];
        let mut best_at = [_mm_setzero_si128(); REGS];
        let mut index: [__m128i; REGS] = std::array::from_fn(|h| {
            _mm_add_epi32(_mm_setr_epi32(0, 1, 2, 3), _mm_set1_epi32(4 * h as i32))
        });
        let step = _mm_set1_epi32(LANES as i32);
        let (px, py, pz, pd) = (xs.as_ptr(), ys.as_ptr(), zs.as_ptr(), min_sq.as_mut_ptr());
        let mut i = 0;
        while i < xs.len() {
            for h in 0..REGS {
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
        for h in 0..REGS {
            _mm_storeu_ps(values.as_mut_ptr().add(4 * h), best[h]);
            _mm_storeu_si128(at.as_mut_ptr().add(4 * h) as *mut __m128i, best_at[h]);
        }
        (values, at)
    }

    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn update_lanes_avx512(
        xs: &[f32],
        ys: &[f32],
        zs: &[f32],
        min_sq: &mut [f32],
        c: Point3,
    ) -> ([f32; LANES], [u32; LANES]) {
        const _: () = assert!(LANES == 16, "one AVX-512 register of f32");
        let (cx, cy, cz) = (
            _mm512_set1_ps(c[0]),
            _mm512_set1_ps(c[1]),
            _mm512_set1_ps(c[2]),
        );
        let (px, py, pz, pd) = (xs.as_ptr(), ys.as_ptr(), zs.as_ptr(), min_sq.as_mut_ptr());
        // The 16 points from `i` lowered, and the lanes' running largest
        // distance and its index `at` updated (the first index on ties).
        let lower = |i: usize, best: &mut __m512, best_at: &mut __m512i, at: __m512i| {
            let dx = _mm512_sub_ps(_mm512_loadu_ps(px.add(i)), cx);
            let dy = _mm512_sub_ps(_mm512_loadu_ps(py.add(i)), cy);
            let dz = _mm512_sub_ps(_mm512_loadu_ps(pz.add(i)), cz);
            let d = _mm512_add_ps(
                _mm512_add_ps(_mm512_mul_ps(dx, dx), _mm512_mul_ps(dy, dy)),
                _mm512_mul_ps(dz, dz),
            );
            let lowered = _mm512_min_ps(d, _mm512_loadu_ps(pd.add(i)));
            _mm512_storeu_ps(pd.add(i), lowered);
            let better = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(lowered, *best);
            *best = _mm512_mask_blend_ps(better, *best, lowered);
            *best_at = _mm512_mask_blend_epi32(better, *best_at, at);
        };
        // Two running maxima, over alternate groups of 16 points, so that
        // one group's comparison need not wait for the previous one's.
        let mut best = [_mm512_set1_ps(f32::NEG_INFINITY); 2];
        let mut best_at = [_mm512_setzero_si512(); 2];
        let mut index = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
        let (step, pair) = (_mm512_set1_epi32(LANES as i32), 2 * LANES);
        let mut i = 0;
        while i + pair <= xs.len() {
            let [b0, b1] = &mut best;
            let [a0, a1] = &mut best_at;
            lower(i, b0, a0, index);
            lower(i + LANES, b1, a1, _mm512_add_epi32(index, step));
            index = _mm512_add_epi32(index, _mm512_add_epi32(step, step));
            i += pair;
        }
        if i < xs.len() {
            let [b0, _] = &mut best;
            let [a0, _] = &mut best_at;
            lower(i, b0, a0, index);
        }
        // Per lane, the larger of the two, the lower index on ties: the
        // first largest, as one running maximum over all groups gives.
        let second = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(best[1], best[0])
            | (_mm512_cmp_ps_mask::<_CMP_EQ_OQ>(best[1], best[0])
                & _mm512_cmplt_epu32_mask(best_at[1], best_at[0]));
        let best = _mm512_mask_blend_ps(second, best[0], best[1]);
        let best_at = _mm512_mask_blend_epi32(second, best_at[0], best_at[1]);
        let mut values = [0.0f32; LANES];
        let mut at = [0u32; LANES];
        _mm512_storeu_ps(values.as_mut_ptr(), best);
        _mm512_storeu_si512(at.as_mut_ptr() as *mut __m512i, best_at);
        (values, at)
    }

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn update_lanes_avx2(
        xs: &[f32],
        ys: &[f32],
        zs: &[f32],
        min_sq: &mut [f32],
        c: Point3,
    ) -> ([f32; LANES], [u32; LANES]) {
        const REGS: usize = LANES / 8;
        let (cx, cy, cz) = (
            _mm256_set1_ps(c[0]),
            _mm256_set1_ps(c[1]),
            _mm256_set1_ps(c[2]),
        );
        let mut best = [_mm256_set1_ps(f32::NEG_INFINITY); REGS];
        let mut best_at = [_mm256_setzero_si256(); REGS];
        let first = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        let mut index: [__m256i; REGS] =
            std::array::from_fn(|h| _mm256_add_epi32(first, _mm256_set1_epi32(8 * h as i32)));
        let step = _mm256_set1_epi32(LANES as i32);
        let (px, py, pz, pd) = (xs.as_ptr(), ys.as_ptr(), zs.as_ptr(), min_sq.as_mut_ptr());
        let mut i = 0;
        while i < xs.len() {
            for h in 0..REGS {
                let k = i + 8 * h;
                let dx = _mm256_sub_ps(_mm256_loadu_ps(px.add(k)), cx);
                let dy = _mm256_sub_ps(_mm256_loadu_ps(py.add(k)), cy);
                let dz = _mm256_sub_ps(_mm256_loadu_ps(pz.add(k)), cz);
                let d = _mm256_add_ps(
                    _mm256_add_ps(_mm256_mul_ps(dx, dx), _mm256_mul_ps(dy, dy)),
                    _mm256_mul_ps(dz, dz),
                );
                let lowered = _mm256_min_ps(d, _mm256_loadu_ps(pd.add(k)));
                _mm256_storeu_ps(pd.add(k), lowered);
                let better = _mm256_cmp_ps::<_CMP_GT_OQ>(lowered, best[h]);
                best[h] = _mm256_blendv_ps(best[h], lowered, better);
                best_at[h] = _mm256_castps_si256(_mm256_blendv_ps(
                    _mm256_castsi256_ps(best_at[h]),
                    _mm256_castsi256_ps(index[h]),
                    better,
                ));
                index[h] = _mm256_add_epi32(index[h], step);
            }
            i += LANES;
        }
        let mut values = [0.0f32; LANES];
        let mut at = [0u32; LANES];
        for h in 0..REGS {
            _mm256_storeu_ps(values.as_mut_ptr().add(8 * h), best[h]);
            _mm256_storeu_si256(at.as_mut_ptr().add(8 * h) as *mut __m256i, best_at[h]);
        }
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
    fn vector_kernels_match_the_portable_kernel() {
        // Random points (an odd number of groups of 16), and a lattice whose
        // many equal distances tie within lanes and between them.
        let lattice: Vec<Point3> = (0..1024)
            .map(|i| [(i % 8) as f32, ((i / 8) % 8) as f32, (i / 64) as f32])
            .collect();
        for cloud in [random_cloud(1003, 4), lattice] {
            kernels_match_on(&cloud);
        }
    }

    #[cfg(target_arch = "x86_64")]
    fn kernels_match_on(cloud: &[Point3]) {
        let n = cloud.len().div_ceil(LANES) * LANES;
        let col = |k: usize| {
            let mut v: Vec<f32> = cloud.iter().map(|p| p[k]).collect();
            v.resize(n, 0.0);
            v
        };
        let (xs, ys, zs) = (col(0), col(1), col(2));
        let mut a = vec![f32::NEG_INFINITY; n];
        a[..cloud.len()].fill(f32::INFINITY);
        let (mut b, mut c, mut d) = (a.clone(), a.clone(), a.clone());
        for centre in [
            [0.5, 0.5, 0.5],
            [0.0, 1.0, 0.2],
            [0.9, 0.1, 0.4],
            [3.5, 3.5, 7.5],
        ] {
            let portable = update_lanes(&xs, &ys, &zs, &mut a, centre);
            let sse2 = unsafe { x86::update_lanes_sse2(&xs, &ys, &zs, &mut b, centre) };
            assert_eq!(portable, sse2);
            assert_eq!(a, b);
            if std::arch::is_x86_feature_detected!("avx2") {
                let avx2 = unsafe { x86::update_lanes_avx2(&xs, &ys, &zs, &mut c, centre) };
                assert_eq!(portable, avx2);
                assert_eq!(a, c);
            }
            if std::arch::is_x86_feature_detected!("avx512f") {
                let avx512 = unsafe { x86::update_lanes_avx512(&xs, &ys, &zs, &mut d, centre) };
                assert_eq!(portable, avx512);
                assert_eq!(a, d);
            }
        }
    }

    #[test]
    fn ties_go_to_the_lowest_index_whatever_the_lanes() {
        // Four points at the same distance from the centroid, in different lanes.
        let mut cloud = vec![[0.0f32; 3]; 40];
        for (i, p) in cloud.iter_mut().enumerate() {
            *p = [0.01 * (i % 3) as f32, 0.0, 0.0];
        }
        for i in [5, 17, 22, 39] {
            cloud[i] = [0.0, 0.0, 1.0];
        }
        assert_eq!(farthest_point_sample(&cloud, 1), vec![5]);
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
