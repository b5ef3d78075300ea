//! Neighbour groups of a map, the encoder's local regions: for each of a
//! map's first `centres` points (maps are in farthest-point order, so these
//! are an even subset) the indices of its `k` nearest map points, itself
//! included. Computed here rather than inside the ONNX graph, where a top-k
//! over all pairwise distances cost a third of the encoder's time.

use rayon::prelude::*;

use crate::threads;
use crate::Point3;

/// Indices (`centres × k`, row-major) of the `k` nearest points of `map` to
/// each of its first `centres` points, nearest first; equal distances are
/// ordered by index, so the result is deterministic.
pub fn map_neighbours(map: &[Point3], centres: usize, k: usize) -> Vec<u32> {
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
    let mut candidates: Vec<(f32, u32)> = vec![(0.0, 0); map.len()];
    // Split the map into at least k blocks: any k of their minima are k
    // distinct distances, so the largest block minimum bounds the k-th
    // smallest distance from above.
    let block = map.len() / k;
    for c in &map[..centres] {
        let mut bound = f32::NEG_INFINITY;
        for (((d, x), y), z) in distances
            .chunks_mut(block)
            .zip(xs.chunks(block))
            .zip(ys.chunks(block))
            .zip(zs.chunks(block))
        {
            let mut least = f32::INFINITY;
            for (((d, x), y), z) in d.iter_mut().zip(x).zip(y).zip(z) {
                *d = (x - c[0]) * (x - c[0]) + (y - c[1]) * (y - c[1]) + (z - c[2]) * (z - c[2]);
                least = if *d < least { *d } else { least };
            }
            bound = if least > bound { least } else { bound };
        }
        // Keep the points within the bound, without branches: write every
        // point, advance only past the kept ones.
        let mut kept = 0;
        for (j, d) in distances.iter().enumerate() {
            candidates[kept] = (*d, j as u32);
            kept += (*d <= bound) as usize;
        }
        if kept < k {
            // Only NaN coordinates get here: rank every point (NaN last).
            for (j, d) in distances.iter().enumerate() {
                candidates[j] = (*d, j as u32);
            }
            kept = distances.len();
        }
        let chosen = &mut candidates[..kept];
        let order = |a: &(f32, u32), b: &(f32, u32)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
        if chosen.len() > k {
            chosen.select_nth_unstable_by(k - 1, order);
        }
        let chosen = &mut chosen[..k];
        chosen.sort_unstable_by(order);
        out.extend(chosen.iter().map(|&(_, j)| j));
    }
    out
}

/// [`map_neighbours`] of every map in `points` (maps of `m` points each,
/// flattened map-major), in parallel over maps: `maps × centres × k` indices.
pub fn neighbours_of_maps(points: &[Point3], m: usize, centres: usize, k: usize) -> Vec<u32> {
    assert!(
        m > 0 && points.len().is_multiple_of(m),
        "points must hold whole maps of {m} points"
    );
    if points.len() == m {
        // One map (a query): waking the thread pool would cost more than the work.
        return map_neighbours(points, centres, k);
    }
    let per_map: Vec<Vec<u32>> = threads::install(|| {
        points
            .par_chunks(m)
            .map(|map| map_neighbours(map, centres, k))
            .collect()
    });
    per_map.concat()
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
    }

    #[test]
    fn many_maps_equal_one_at_a_time() {
        let mut rng = SplitMix64::new(5);
        let maps: Vec<Point3> = random_map(64 * 7, &mut rng);
        let all = neighbours_of_maps(&maps, 64, 16, 4);
        let one_by_one: Vec<u32> = maps
            .chunks(64)
            .flat_map(|m| map_neighbours(m, 16, 4))
            .collect();
        assert_eq!(all, one_by_one);
    }
}
