//! Neighbour groups of a map, the encoder's local regions: for each of a
//! map's first `centres` points (maps are in farthest-point order, so these
//! are an even subset) the indices of its `k` nearest map points, itself
//! included; and the features the encoder's layers read from them
//! ([`MapFeatures`]). Computed here rather than inside the ONNX graph, which
//! did both slowly: a top-k over all pairwise distances and dozens of small
//! operations (`export/README.md` has the figures).

use rayon::prelude::*;

use crate::threads;
use crate::Point3;

/// Indices (`centres × k`, row-major) of the `k` nearest points of `map` to
/// each of its first `centres` points, nearest first; equal distances are
/// ordered by index, so the result is deterministic.
pub fn map_neighbours(map: &[Point3], centres: usize, k: usize) -> Vec<u32> {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 is present (checked above).
        return unsafe { map_neighbours_avx2(map, centres, k) };
    }
    neighbours_in(map, centres, k)
}

/// [`map_neighbours`] compiled for AVX2: its loops vectorise 8 lanes wide
/// rather than SSE2's 4; the same operations, so the same groups.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn map_neighbours_avx2(map: &[Point3], centres: usize, k: usize) -> Vec<u32> {
    neighbours_in(map, centres, k)
}

#[inline(always)]
fn neighbours_in(map: &[Point3], centres: usize, k: usize) -> Vec<u32> {
    assert!(
        centres <= map.len() && k <= map.len(),
        "a map of {} points has no {centres} centres with {k} neighbours",
        map.len()
    );
    let mut out = Vec::with_capacity(centres * k);
    if k == 0 {
        return out;
    }
    // Coordinates as separate rows, so the distance loop vectorises.
    let xs: Vec<f32> = map.iter().map(|p| p[0]).collect();
    let ys: Vec<f32> = map.iter().map(|p| p[1]).collect();
    let zs: Vec<f32> = map.iter().map(|p| p[2]).collect();
    let mut distances = vec![0.0f32; map.len()];
    // (distance, index) packed as one sortable key: distances are ≥ 0, whose
    // bits order as they do; NaN is ranked last.
    let key = |d: f32, j: usize| {
        (if d.is_nan() { u32::MAX } else { d.to_bits() } as u64) << 32 | j as u64
    };
    let mut candidates: Vec<u64> = vec![0; map.len()];
    // Split the map into at least k blocks: any k of their minima are k
    // distinct distances, so the largest block minimum bounds the k-th
    // smallest distance from above.
    let block = map.len() / k;
    for c in &map[..centres] {
        // Two passes that each vectorise: the distances, then each block's
        // minimum in lanes (a running minimum of one value does not).
        for (((d, x), y), z) in distances.iter_mut().zip(&xs).zip(&ys).zip(&zs) {
            *d = (x - c[0]) * (x - c[0]) + (y - c[1]) * (y - c[1]) + (z - c[2]) * (z - c[2]);
        }
        let bound =
            distances
                .chunks(block)
                .map(block_minimum)
                .fold(
                    f32::NEG_INFINITY,
                    |bound, least| if least > bound { least } else { bound },
                );
        // Keep the points within the bound: a bit per point, 32 at a time
        // (the compares vectorise), then visit the set bits.
        let mut kept = 0;
        for (row, ds) in distances.chunks(32).enumerate() {
            let mut bits = ds
                .iter()
                .enumerate()
                .fold(0u32, |bits, (l, d)| bits | (((*d <= bound) as u32) << l));
            while bits != 0 {
                let j = row * 32 + bits.trailing_zeros() as usize;
                bits &= bits - 1;
                candidates[kept] = key(distances[j], j);
                kept += 1;
            }
        }
        if kept < k {
            // Only NaN coordinates get here: rank every point (NaN last).
            for (j, d) in distances.iter().enumerate() {
                candidates[j] = key(*d, j);
            }
            kept = distances.len();
        }
        let chosen = &mut candidates[..kept];
        if chosen.len() > k {
            chosen.select_nth_unstable(k - 1);
        }
        let chosen = &mut chosen[..k];
        chosen.sort_unstable();
        out.extend(chosen.iter().map(|&c| c as u32));
    }
    out
}

/// The least of `values` that are not NaN (infinity when none are).
fn block_minimum(values: &[f32]) -> f32 {
    const LANES: usize = 8;
    let mut lanes = [f32::INFINITY; LANES];
    let rows = values.chunks_exact(LANES);
    let rest = rows.remainder();
    for row in rows {
        for (least, &v) in lanes.iter_mut().zip(row) {
            *least = if v < *least { v } else { *least };
        }
    }
    for &v in rest {
        lanes[0] = if v < lanes[0] { v } else { lanes[0] };
    }
    lanes
        .into_iter()
        .fold(f32::INFINITY, |a, b| if b < a { b } else { a })
}

/// The encoder's inputs for maps (`export/network.py`, `map_features`):
/// what its layers see of each neighbour group, unchanged by a turn of the
/// map about the optical axis. Row-major, map-major; f32 operations in the
/// graph's order, so the codes are the same bit for bit as when the graph
/// computed them.
pub struct MapFeatures {
    /// `maps × centres × k × 6`: each neighbour's offset from its centre in
    /// the centre's radial frame (x along the centre's polar direction),
    /// its distance, then the centre's radius and depth; all × 4.
    pub edges: Vec<f32>,
    /// `maps × centres × 2`: each centre's radius from the optical axis and depth.
    pub own: Vec<f32>,
    /// `maps × centres × harmonics`: cos(mφ) of each centre's polar angle φ, m = 1, 2, ….
    pub cos: Vec<f32>,
    /// `maps × centres × harmonics`: sin(mφ).
    pub sin: Vec<f32>,
}

/// Neighbour offsets in the encoder's units: ×4 puts them near 0.4, as the
/// layers were trained.
const EDGE_SCALE: f32 = 4.0;
const EDGE_FEATURES: usize = 6;

/// [`MapFeatures`] of every map in `points` (maps of `m` points each,
/// flattened map-major), in parallel over maps.
pub fn features_of_maps(
    points: &[Point3],
    m: usize,
    centres: usize,
    k: usize,
    harmonics: usize,
) -> MapFeatures {
    assert!(
        m > 0 && points.len().is_multiple_of(m) && centres <= m && (1..=m).contains(&k),
        "points must hold whole maps of {m} points, each with {centres} centres of {k} neighbours"
    );
    let maps = points.len() / m;
    let sizes = [
        centres * k * EDGE_FEATURES,
        centres * 2,
        centres * harmonics,
    ];
    let mut out = MapFeatures {
        edges: vec![0.0; maps * sizes[0]],
        own: vec![0.0; maps * sizes[1]],
        cos: vec![0.0; maps * sizes[2]],
        sin: vec![0.0; maps * sizes[2]],
    };
    if maps == 0 || centres == 0 {
        return out;
    }
    let parts = points
        .chunks(m)
        .zip(out.edges.chunks_mut(sizes[0]))
        .zip(out.own.chunks_mut(sizes[1]))
        .zip(
            out.cos
                .chunks_mut(sizes[2])
                .zip(out.sin.chunks_mut(sizes[2])),
        )
        .map(|(((map, edges), own), (cos, sin))| OneMap {
            map,
            edges,
            own,
            cos,
            sin,
        });
    if maps == 1 {
        // One map (a query): waking the thread pool would cost more than the work.
        parts.for_each(|one| one.fill(centres, k, harmonics));
    } else {
        let parts: Vec<OneMap> = parts.collect();
        threads::install(|| {
            parts
                .into_par_iter()
                .for_each(|one| one.fill(centres, k, harmonics))
        });
    }
    out
}

/// One map and its rows of [`MapFeatures`].
struct OneMap<'a> {
    map: &'a [Point3],
    edges: &'a mut [f32],
    own: &'a mut [f32],
    cos: &'a mut [f32],
    sin: &'a mut [f32],
}

impl OneMap<'_> {
    fn fill(self, centres: usize, k: usize, harmonics: usize) {
        let groups = map_neighbours(self.map, centres, k);
        for (c, group) in groups.chunks_exact(k).enumerate() {
            let [x, y, z] = self.map[c];
            let r = (x * x + y * y + 1e-8).sqrt();
            let (cos_phi, sin_phi) = (x / r, y / r);
            self.own[2 * c] = r;
            self.own[2 * c + 1] = z;
            let rows = self.edges[c * k * EDGE_FEATURES..].chunks_exact_mut(EDGE_FEATURES);
            for (&j, edge) in group.iter().zip(rows) {
                let p = self.map[j as usize];
                let d = [p[0] - x, p[1] - y, p[2] - z];
                edge[0] = (cos_phi * d[0] + sin_phi * d[1]) * EDGE_SCALE;
                edge[1] = (-sin_phi * d[0] + cos_phi * d[1]) * EDGE_SCALE;
                edge[2] = d[2] * EDGE_SCALE;
                edge[3] = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2] + 1e-12).sqrt() * EDGE_SCALE;
                edge[4] = r * EDGE_SCALE;
                edge[5] = z * EDGE_SCALE;
            }
            // cos(mφ), sin(mφ) by the angle-addition recurrence, as in training.
            let row = c * harmonics..(c + 1) * harmonics;
            let (mut cos_m, mut sin_m) = (cos_phi, sin_phi);
            for (cos, sin) in self.cos[row.clone()].iter_mut().zip(&mut self.sin[row]) {
                (*cos, *sin) = (cos_m, sin_m);
                (cos_m, sin_m) = (
                    cos_m * cos_phi - sin_m * sin_phi,
                    sin_m * cos_phi + cos_m * sin_phi,
                );
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    fn random_map(n: usize, rng: &mut SplitMix64) -> Vec<Point3> {
        (0..n)
            .map(|_| [0; 3].map(|_: i32| rng.next_f64() as f32 - 0.5))
            .collect()
    }

    #[test]
    fn matches_a_full_sort() {
        let mut rng = SplitMix64::new(3);
        // Map sizes divisible by k and not (the block bound must hold for both).
        for (n, centres, k) in [(200, 20, 8), (100, 30, 16), (37, 10, 5)] {
            let map = random_map(n, &mut rng);
            let groups = map_neighbours(&map, centres, k);
            for (c, group) in groups.chunks_exact(k).enumerate() {
                let mut all: Vec<(f32, u32)> = map
                    .iter()
                    .enumerate()
                    .map(|(j, p)| ((0..3).map(|a| (p[a] - map[c][a]).powi(2)).sum(), j as u32))
                    .collect();
                all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                let expected: Vec<u32> = all[..k].iter().map(|&(_, j)| j).collect();
                assert_eq!(group, expected.as_slice(), "{n} points, k = {k}");
                assert_eq!(group[0], c as u32, "a centre is its own nearest point");
            }
        }
    }

    #[test]
    fn the_avx2_build_gives_the_portable_groups() {
        let mut rng = SplitMix64::new(11);
        for n in [64, 300, 512] {
            let map = random_map(n, &mut rng);
            assert_eq!(
                map_neighbours(&map, 32, 16),
                neighbours_in(&map, 32, 16),
                "{n} points"
            );
        }
    }

    #[test]
    fn duplicate_points_are_ordered_by_index() {
        let map: Vec<Point3> = vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.5, 0.0, 0.0],
        ];
        assert_eq!(map_neighbours(&map, 2, 3), vec![0, 2, 4, 1, 3, 4]);
    }

    #[test]
    fn nan_points_still_give_k_neighbours() {
        let mut map: Vec<Point3> = (0..40).map(|i| [i as f32, 0.0, 0.0]).collect();
        map[3] = [f32::NAN, 0.0, 0.0];
        let groups = map_neighbours(&map, 4, 8);
        assert_eq!(groups.len(), 32);
        assert_eq!(&groups[..4], &[0, 1, 2, 4]);
        // A NaN with its sign bit set ranks last too.
        map[3] = [-f32::NAN, 0.0, 0.0];
        assert_eq!(&map_neighbours(&map, 4, 8)[..4], &[0, 1, 2, 4]);
    }

    #[test]
    fn many_maps_equal_one_at_a_time() {
        let mut rng = SplitMix64::new(5);
        let maps: Vec<Point3> = random_map(64 * 7, &mut rng);
        let all = features_of_maps(&maps, 64, 16, 4, 3);
        for (i, map) in maps.chunks(64).enumerate() {
            let one = features_of_maps(map, 64, 16, 4, 3);
            assert_eq!(one.edges, all.edges[i * 16 * 4 * 6..(i + 1) * 16 * 4 * 6]);
            assert_eq!(one.own, all.own[i * 32..(i + 1) * 32]);
            assert_eq!(one.cos, all.cos[i * 48..(i + 1) * 48]);
            assert_eq!(one.sin, all.sin[i * 48..(i + 1) * 48]);
        }
    }

    #[test]
    fn features_are_offsets_in_the_centres_radial_frame() {
        // A centre on the y axis (φ = 90°) and a neighbour 0.1 further out along it.
        let map: Vec<Point3> = vec![[0.0, 0.5, 0.2], [0.0, 0.6, 0.2], [3.0, 3.0, 3.0]];
        let f = features_of_maps(&map, 3, 1, 2, 3);
        let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-6);
        assert!(close(&f.own, &[0.5, 0.2]));
        assert!(
            close(&f.edges[..6], &[0.0, 0.0, 0.0, 4e-6, 2.0, 0.8]),
            "{:?}",
            &f.edges[..6]
        );
        assert!(
            close(&f.edges[6..], &[0.4, 0.0, 0.0, 0.4, 2.0, 0.8]),
            "{:?}",
            &f.edges[6..]
        );
        // cos/sin of 90°, 180°, 270°.
        assert!(close(&f.cos, &[0.0, -1.0, 0.0]) && close(&f.sin, &[1.0, 0.0, -1.0]));
    }
}
