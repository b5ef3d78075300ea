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
    let take = m.min(n);
    #[cfg(target_arch = "x86_64")]
    let mut chosen = if take >= blocked::MIN_PICKS && std::arch::is_x86_feature_detected!("avx512f")
    {
        // SAFETY: AVX-512F is present (checked above).
        unsafe { blocked::farthest_point_sample(points, take) }
    } else {
        every_point_each_pick(points, take)
    };
    #[cfg(not(target_arch = "x86_64"))]
    let mut chosen = every_point_each_pick(points, take);
    chosen.reserve(m - take);
    for k in take..m {
        chosen.push(chosen[k % take]);
    }
    chosen
}

/// The first `take` (1 to the number of `points`) of [`farthest_point_sample`]'s
/// picks, by a pass over every point for each pick.
fn every_point_each_pick(points: &[Point3], take: usize) -> Vec<u32> {
    let n = points.len();
    // Structure-of-arrays padded to whole lanes. Padding slots carry a
    // distance of −∞, so they are never the farthest point.
    let padded = n.div_ceil(LANES) * LANES;
    let mut xs = vec![0.0f32; padded];
    let mut ys = vec![0.0f32; padded];
    let mut zs = vec![0.0f32; padded];
    for (i, p) in points.iter().enumerate() {
        (xs[i], ys[i], zs[i]) = (p[0], p[1], p[2]);
    }
    let centroid = centroid(points);
    let mut min_sq = vec![f32::NEG_INFINITY; padded];
    min_sq[..n].fill(f32::INFINITY);

    // The first pick is the farthest point from the centroid: the same
    // update-and-argmax step, on a copy whose distances are all still ∞.
    let mut scratch = min_sq.clone();
    let mut chosen = Vec::with_capacity(take);
    let mut current = update_and_argmax(&xs, &ys, &zs, &mut scratch, centroid);
    chosen.push(current as u32);
    for _ in 1..take {
        let c = [xs[current], ys[current], zs[current]];
        current = update_and_argmax(&xs, &ys, &zs, &mut min_sq, c);
        chosen.push(current as u32);
    }
    chosen
}

/// The centroid of `points` as [`farthest_point_sample`] takes it: f32
/// sums in input order (the first pick is the point farthest from it).
fn centroid(points: &[Point3]) -> Point3 {
    let inv_n = 1.0 / points.len() as f32;
    std::array::from_fn(|a| points.iter().map(|p| p[a]).sum::<f32>() * inv_n)
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
            let lowered = lower_16([px, py, pz], pd, i, [cx, cy, cz]);
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

    /// The 16 points from `i` (`points`: their x, y and z rows) lowered
    /// with their squared distance to a pick (`c`: its x, y and z in every
    /// lane), stored back into `min_sq` and returned: the step both
    /// AVX-512 samplers take, the portable kernel's operations in order.
    #[target_feature(enable = "avx512f")]
    #[inline]
    pub(super) unsafe fn lower_16(
        points: [*const f32; 3],
        min_sq: *mut f32,
        i: usize,
        c: [__m512; 3],
    ) -> __m512 {
        let [dx, dy, dz] =
            std::array::from_fn(|a| _mm512_sub_ps(_mm512_loadu_ps(points[a].add(i)), c[a]));
        let d = _mm512_add_ps(
            _mm512_add_ps(_mm512_mul_ps(dx, dx), _mm512_mul_ps(dy, dy)),
            _mm512_mul_ps(dz, dz),
        );
        let lowered = _mm512_min_ps(d, _mm512_loadu_ps(min_sq.add(i)));
        _mm512_storeu_ps(min_sq.add(i), lowered);
        lowered
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

/// Farthest-point sampling over blocks of nearby points, with AVX-512: the
/// same picks as the passes over every point above, bit for bit. The
/// points are put in Morton order and cut into blocks of [`BLOCK`]. A pick
/// whose squared distance to a block's bounding box is, with room for
/// rounding, at least the largest distance-to-chosen-set in the block
/// lowers none of them, so the block is skipped: most picks lie near a
/// few blocks. Ties still go to the lowest input index.
#[cfg(target_arch = "x86_64")]
mod blocked {
    use super::x86::lower_16;
    use super::{centroid, LANES};
    use crate::index::{bounds, counting_sort};
    use crate::Point3;
    use std::arch::x86_64::*;

    /// Points of a block: four AVX-512 registers.
    const BLOCK: usize = 4 * LANES;

    /// Fewer picks take the passes over every point: ordering the points
    /// costs more than skipping blocks saves (`docs/tuning.md`).
    pub(super) const MIN_PICKS: usize = 256;

    /// A bounding box's squared distance to a pick, shrunk by this share:
    /// far more than the rounding of an f32 squared distance.
    const ROUNDING: f32 = 1e-5;

    /// The first `take` (1 to the number of `points`) of
    /// [`super::farthest_point_sample`]'s picks.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn farthest_point_sample(points: &[Point3], take: usize) -> Vec<u32> {
        let n = points.len();
        let blocks = n.div_ceil(BLOCK);
        let padded = blocks * BLOCK;
        // Structure of arrays in Morton order, the last block padded with
        // slots whose distance is −∞ (never the farthest), and each slot's
        // input index.
        let (mut xs, mut ys, mut zs) = (
            vec![0.0f32; padded],
            vec![0.0f32; padded],
            vec![0.0f32; padded],
        );
        let mut ids = vec![u32::MAX; padded];
        // The blocks' bounding boxes, axis by axis, padded to whole
        // registers with empty boxes (infinitely far from any pick).
        let boxed = blocks.div_ceil(LANES) * LANES;
        let mut lo = [(); 3].map(|_| vec![f32::INFINITY; boxed]);
        let mut hi = [(); 3].map(|_| vec![f32::NEG_INFINITY; boxed]);
        for (k, i) in morton_order(points).into_iter().enumerate() {
            let p = points[i as usize];
            (xs[k], ys[k], zs[k], ids[k]) = (p[0], p[1], p[2], i);
            for a in 0..3 {
                lo[a][k / BLOCK] = lo[a][k / BLOCK].min(p[a]);
                hi[a][k / BLOCK] = hi[a][k / BLOCK].max(p[a]);
            }
        }
        let slots = Slots {
            xs: &xs,
            ys: &ys,
            zs: &zs,
            ids: &ids,
        };
        let mut min_sq = vec![f32::NEG_INFINITY; padded];
        min_sq[..n].fill(f32::INFINITY);
        // Each block's largest distance (padding: −∞, never the farthest).
        let mut best = vec![f32::NEG_INFINITY; boxed];

        // The first pick is the farthest point from the centroid: every
        // block lowered on a copy whose distances are all still ∞.
        let mut scratch = min_sq.clone();
        let c = centroid(points);
        for (b, best) in best[..blocks].iter_mut().enumerate() {
            *best = lower_block(&slots, &mut scratch, b, c);
        }
        let mut chosen = Vec::with_capacity(take);
        chosen.push(farthest(&slots, &scratch, &best));
        best[..blocks].fill(f32::INFINITY);
        for _ in 1..take {
            let c = points[chosen[chosen.len() - 1] as usize];
            for group in 0..boxed / LANES {
                let mut near = near_blocks(&lo, &hi, &best, group * LANES, c);
                while near != 0 {
                    let b = group * LANES + near.trailing_zeros() as usize;
                    near &= near - 1;
                    best[b] = lower_block(&slots, &mut min_sq, b, c);
                }
            }
            chosen.push(farthest(&slots, &min_sq, &best));
        }
        chosen
    }

    /// The points' coordinates and input indices, slot by slot.
    struct Slots<'a> {
        xs: &'a [f32],
        ys: &'a [f32],
        zs: &'a [f32],
        ids: &'a [u32],
    }

    /// A bit for each of the [`LANES`] blocks from `first` whose box
    /// (`lo`..`hi`, by axis) a point within their largest distance `best`
    /// (squared metres) of `c` may lie in; a clear bit: every point of the
    /// block is surely farther, in f32 arithmetic, so none is lowered.
    #[target_feature(enable = "avx512f")]
    unsafe fn near_blocks(
        lo: &[Vec<f32>; 3],
        hi: &[Vec<f32>; 3],
        best: &[f32],
        first: usize,
        c: Point3,
    ) -> u16 {
        let zero = _mm512_setzero_ps();
        let mut squared = zero;
        for a in 0..3 {
            let v = _mm512_set1_ps(c[a]);
            let below = _mm512_sub_ps(_mm512_loadu_ps(lo[a].as_ptr().add(first)), v);
            let above = _mm512_sub_ps(v, _mm512_loadu_ps(hi[a].as_ptr().add(first)));
            // maxps returns its second operand when either is NaN: a NaN gap is 0.
            let gap = _mm512_max_ps(_mm512_max_ps(below, above), zero);
            squared = _mm512_add_ps(squared, _mm512_mul_ps(gap, gap));
        }
        let shrunk = _mm512_mul_ps(squared, _mm512_set1_ps(1.0 - ROUNDING));
        _mm512_cmp_ps_mask::<_CMP_LT_OQ>(shrunk, _mm512_loadu_ps(best.as_ptr().add(first)))
    }

    /// The input index of the point with the largest distance `min_sq`
    /// (the lowest index on ties), from the blocks' largest ones `best`:
    /// only the blocks holding the largest are read point by point.
    #[target_feature(enable = "avx512f")]
    unsafe fn farthest(slots: &Slots, min_sq: &[f32], best: &[f32]) -> u32 {
        let mut top = _mm512_set1_ps(f32::NEG_INFINITY);
        for i in (0..best.len()).step_by(LANES) {
            top = _mm512_max_ps(top, _mm512_loadu_ps(best.as_ptr().add(i)));
        }
        let top = _mm512_set1_ps(_mm512_reduce_max_ps(top));
        let mut at = _mm512_set1_epi32(-1);
        for group in (0..best.len()).step_by(LANES) {
            let mut holding =
                _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(_mm512_loadu_ps(best.as_ptr().add(group)), top);
            while holding != 0 {
                let b = group + holding.trailing_zeros() as usize;
                holding &= holding - 1;
                for i in (b * BLOCK..(b + 1) * BLOCK).step_by(LANES) {
                    let there = _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(
                        _mm512_loadu_ps(min_sq.as_ptr().add(i)),
                        top,
                    );
                    let ids = _mm512_loadu_si512(slots.ids.as_ptr().add(i) as *const __m512i);
                    at = _mm512_mask_min_epu32(at, there, at, ids);
                }
            }
        }
        _mm512_reduce_min_epu32(at)
    }

    /// Lowers the distances of block `b`'s points with their distance to
    /// `c`, as the passes over every point do (the same operations), and
    /// returns the largest.
    #[target_feature(enable = "avx512f")]
    unsafe fn lower_block(slots: &Slots, min_sq: &mut [f32], b: usize, c: Point3) -> f32 {
        let c = c.map(|v| _mm512_set1_ps(v));
        let points = [slots.xs.as_ptr(), slots.ys.as_ptr(), slots.zs.as_ptr()];
        let mut best = _mm512_set1_ps(f32::NEG_INFINITY);
        for i in (b * BLOCK..(b + 1) * BLOCK).step_by(LANES) {
            best = _mm512_max_ps(best, lower_16(points, min_sq.as_mut_ptr(), i, c));
        }
        _mm512_reduce_max_ps(best)
    }

    /// Bits of each coordinate in a Morton code: 32 cells an axis, about
    /// as many as a block of a few thousand points needs.
    const BITS: u32 = 5;

    /// Input indices of `points` in Morton order over their bounding box
    /// ([`BITS`] bits an axis; points with the same code in input order),
    /// sorted by two passes of [`counting_sort`].
    #[inline(always)]
    fn morton_order(points: &[Point3]) -> Vec<u32> {
        let (lo, hi) = bounds(points);
        let cells = ((1 << BITS) - 1) as f32;
        let scale: [f32; 3] = std::array::from_fn(|a| {
            if hi[a] > lo[a] {
                cells / (hi[a] - lo[a])
            } else {
                0.0
            }
        });
        // A NaN coordinate is cell 0 (max returns the other operand).
        let cell =
            |p: &Point3, a: usize| spread(((p[a] - lo[a]) * scale[a]).max(0.0).min(cells) as u32);
        let codes: Vec<usize> = points
            .iter()
            .map(|p| (cell(p, 0) | cell(p, 1) << 1 | cell(p, 2) << 2) as usize)
            .collect();
        // Least significant digit first: the second pass keeps the first's
        // order within each of its buckets.
        const DIGIT: u32 = (3 * BITS).div_ceil(2);
        let low: Vec<usize> = codes.iter().map(|c| c & ((1 << DIGIT) - 1)).collect();
        let (by_low, _) = counting_sort(&low, 1 << DIGIT);
        let high: Vec<usize> = by_low.iter().map(|&i| codes[i as usize] >> DIGIT).collect();
        let (by_high, _) = counting_sort(&high, 1 << DIGIT);
        by_high.into_iter().map(|k| by_low[k as usize]).collect()
    }

    /// The low [`BITS`] bits of `v`, two zero bits after each.
    #[inline(always)]
    fn spread(v: u32) -> u32 {
        const _: () = assert!(BITS <= 10, "the shifts below spread 10 bits");
        let mut x = v & ((1 << BITS) - 1);
        x = (x | (x << 16)) & 0x0300_00ff;
        x = (x | (x << 8)) & 0x0300_f00f;
        x = (x | (x << 4)) & 0x030c_30c3;
        (x | (x << 2)) & 0x0924_9249
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

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn blocks_give_the_picks_of_passes_over_every_point() {
        if !std::arch::is_x86_feature_detected!("avx512f") {
            return;
        }
        // Random points, a lattice full of equal distances, duplicates,
        // a flat patch, and points with NaN and infinite coordinates.
        let lattice: Vec<Point3> = (0..1024)
            .map(|i| [(i % 8) as f32, ((i / 8) % 8) as f32, (i / 64) as f32])
            .collect();
        let doubled: Vec<Point3> = random_cloud(300, 7)
            .into_iter()
            .flat_map(|p| [p, p])
            .collect();
        let flat: Vec<Point3> = random_cloud(700, 8)
            .into_iter()
            .map(|p| [p[0], p[1], 0.5])
            .collect();
        let mut odd = random_cloud(500, 9);
        odd[17] = [f32::NAN, 0.0, 0.0];
        odd[300] = [0.0, f32::INFINITY, 0.0];
        for cloud in [
            random_cloud(1003, 4),
            random_cloud(2048, 5),
            lattice,
            doubled,
            flat,
            odd,
        ] {
            for take in [1, 64, 512, cloud.len()] {
                let blocked = unsafe { blocked::farthest_point_sample(&cloud, take) };
                let every = every_point_each_pick(&cloud, take);
                assert_eq!(blocked, every, "{} points, {take} picks", cloud.len());
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
