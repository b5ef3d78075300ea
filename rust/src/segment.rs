//! Which points of a "segmented" cloud are the object. A detector's mask
//! spills onto the background and depth edges throw flying pixels; both
//! drag the centroid and poison the map. Two robust steps, in the camera
//! frame (metres):
//!
//! 1. a statistical outlier test: a point whose mean distance to its `k`
//!    nearest neighbours is far above the cloud's typical one floats alone
//!    (flying pixels between a foreground and a background surface);
//! 2. Euclidean clustering over the k-nearest-neighbour graph at a radius
//!    tied to the point spacing: surfaces separated by a depth jump (the
//!    object and the table or wall behind it) fall apart. The largest
//!    component is the object; other components close to it are kept too
//!    (an occluder in front can cut the object in two, self-occlusion can
//!    split it at a depth jump), unless they lie in its *shadow*: beside it
//!    in the image but behind it, the way a mask's spill onto the table or
//!    wall behind an object does.

use std::num::NonZero;

use kiddo::{ImmutableKdTree, SquaredEuclidean};

use crate::Point3;

/// Tuning of [`segment`]; every distance is relative, so one setting
/// serves any range and object size.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SegmentSettings {
    /// Neighbours per point for the outlier test and the clustering graph.
    pub neighbours: usize,
    /// A point is an outlier when its mean neighbour distance exceeds the
    /// median one by this many (robust, MAD-based) standard deviations.
    pub outlier_sigmas: f64,
    /// Points closer than this many times the cloud's median point spacing
    /// belong to the same surface.
    pub cluster_spacings: f64,
    /// Another component is kept when it has at least this fraction of the
    /// largest one's points ...
    pub min_component_fraction: f64,
    /// ... its centroid lies within this many object diameters of the
    /// largest component's centroid ...
    pub max_component_offset: f64,
    /// ... and less than this fraction of its points are in the largest
    /// component's shadow: within `shadow_spacings` point spacings of it in
    /// the image (by viewing direction) and behind it. A thin spill ring is
    /// all shadow; a part cut off by an occluder lies across a gap; a part
    /// split off by self-occlusion is mostly away from the edge that hides it.
    pub max_shadowed_fraction: f64,
    /// See `max_shadowed_fraction`.
    pub shadow_spacings: f64,
}

impl Default for SegmentSettings {
    fn default() -> Self {
        Self { neighbours: 8, outlier_sigmas: 3.0, cluster_spacings: 3.0, min_component_fraction: 0.02, max_component_offset: 0.6, max_shadowed_fraction: 0.5, shadow_spacings: 4.0 }
    }
}

/// What [`segment`] found.
#[derive(Clone, Debug, PartialEq)]
pub struct Segmentation {
    /// One flag per cloud point: whether it belongs to the object.
    pub keep: Vec<bool>,
    /// Median distance from a point to its nearest neighbour, metres (0 for tiny clouds).
    pub spacing: f64,
}

/// Which points of `cloud` (camera frame, metres) belong to the object,
/// `diameter` metres across. Fewer than `2 · (neighbours + 1)` points are
/// all kept (too few to judge).
pub fn segment(cloud: &[Point3], diameter: f64, settings: &SegmentSettings) -> Segmentation {
    let n = cloud.len();
    let k = settings.neighbours.max(1);
    if n < 2 * (k + 1) {
        return Segmentation { keep: vec![true; n], spacing: 0.0 };
    }
    let tree: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(cloud);
    let wanted = NonZero::new(k + 1).expect("k + 1 > 0");
    // Each point's k nearest others (the first hit is the point itself).
    let neighbours: Vec<Vec<(usize, f32)>> = cloud
        .iter()
        .map(|p| {
            tree.nearest_n::<SquaredEuclidean>(p, wanted)
                .into_iter()
                .skip(1)
                .map(|nn| (nn.item as usize, nn.distance.sqrt()))
                .collect()
        })
        .collect();

    // 1. Statistical outliers, with median and MAD so the outliers
    //    themselves do not widen the band.
    let mean_distance: Vec<f64> = neighbours
        .iter()
        .map(|nn| nn.iter().map(|&(_, d)| d as f64).sum::<f64>() / nn.len().max(1) as f64)
        .collect();
    let median = median_of(&mean_distance);
    let mad = median_of(&mean_distance.iter().map(|d| (d - median).abs()).collect::<Vec<_>>());
    let limit = median + settings.outlier_sigmas * 1.4826 * mad.max(0.25 * median);
    let inlier: Vec<bool> = mean_distance.iter().map(|&d| d <= limit).collect();

    // 2. Components of the inliers' neighbour graph, edges up to `radius`.
    let spacing = median_of(&neighbours.iter().filter_map(|nn| nn.first().map(|&(_, d)| d as f64)).collect::<Vec<_>>());
    let radius = (settings.cluster_spacings * spacing) as f32;
    let mut components = UnionFind::new(n);
    for (i, nn) in neighbours.iter().enumerate() {
        if !inlier[i] {
            continue;
        }
        for &(j, d) in nn {
            if d <= radius && inlier[j] {
                components.union(i, j);
            }
        }
    }
    let mut size = vec![0usize; n];
    let mut sum = vec![[0.0f64; 3]; n];
    for i in (0..n).filter(|&i| inlier[i]) {
        let root = components.find(i);
        size[root] += 1;
        for a in 0..3 {
            sum[root][a] += cloud[i][a] as f64;
        }
    }
    // Components in the shadow of another (beside it in the image, behind
    // it) are background the mask picked up, whatever their size.
    let root_of: Vec<usize> = (0..n).map(|i| components.find(i)).collect();
    let shadowed = in_shadow(cloud, &root_of, &inlier, settings.shadow_spacings * spacing, radius as f64);
    let mut shadowed_count = vec![0usize; n];
    for i in (0..n).filter(|&i| shadowed[i]) {
        shadowed_count[root_of[i]] += 1;
    }
    let lit = |root: usize| size[root] > 0 && (shadowed_count[root] as f64) < settings.max_shadowed_fraction * size[root] as f64;
    // The object: the largest lit component (ties to the lowest root, so the
    // result is deterministic), with lit components of some size near it.
    let largest = (0..n)
        .filter(|&r| lit(r))
        .max_by(|&a, &b| size[a].cmp(&size[b]).then(b.cmp(&a)))
        .or_else(|| (0..n).max_by(|&a, &b| size[a].cmp(&size[b]).then(b.cmp(&a))))
        .expect("n > 0");
    let centroid = |root: usize| sum[root].map(|s| s / size[root] as f64);
    let anchor = centroid(largest);
    let keep_root: Vec<bool> = (0..n)
        .map(|root| {
            root == largest
                || (lit(root)
                    && size[root] as f64 >= settings.min_component_fraction * size[largest] as f64
                    && distance(centroid(root), anchor) <= settings.max_component_offset * diameter)
        })
        .collect();
    Segmentation { keep: (0..n).map(|i| inlier[i] && keep_root[root_of[i]]).collect(), spacing }
}

/// Which inlier points lie in the shadow of another component: a point of
/// another component lies within `lateral` metres of it by viewing direction
/// (measured at the point's depth) and nearer the camera by more than `gap` metres.
fn in_shadow(cloud: &[Point3], root_of: &[usize], inlier: &[bool], lateral: f64, gap: f64) -> Vec<bool> {
    let direction = |p: &Point3| [p[0] / p[2], p[1] / p[2]];
    let front: Vec<usize> = (0..cloud.len()).filter(|&i| inlier[i] && cloud[i][2] > 0.0).collect();
    let mut shadowed = vec![false; cloud.len()];
    if front.is_empty() {
        return shadowed;
    }
    let rays: Vec<[f32; 2]> = front.iter().map(|&i| direction(&cloud[i])).collect();
    let tree: ImmutableKdTree<f32, 2> = ImmutableKdTree::new_from_slice(&rays);
    for &i in &front {
        let p = &cloud[i];
        let reach = (lateral / p[2] as f64).powi(2) as f32;
        shadowed[i] = tree.within_unsorted::<SquaredEuclidean>(&direction(p), reach).into_iter().any(|nn| {
            let j = front[nn.item as usize];
            root_of[j] != root_of[i] && (p[2] - cloud[j][2]) as f64 > gap
        });
    }
    shadowed
}

fn median_of(values: &[f64]) -> f64 {
    quantile(values, 0.5)
}

/// The value at fraction `q` (0–1) of the sorted `values` (nearest rank; 0 when empty).
fn quantile(values: &[f64], q: f64) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    let mut v = values.to_vec();
    let at = ((q * (v.len() - 1) as f64).round() as usize).min(v.len() - 1);
    *v.select_nth_unstable_by(at, f64::total_cmp).1
}

fn distance(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Disjoint sets with path halving and union by index (deterministic roots).
struct UnionFind {
    parent: Vec<usize>,
}

impl UnionFind {
    fn new(n: usize) -> Self {
        Self { parent: (0..n).collect() }
    }

    fn find(&mut self, mut i: usize) -> usize {
        while self.parent[i] != i {
            self.parent[i] = self.parent[self.parent[i]];
            i = self.parent[i];
        }
        i
    }

    fn union(&mut self, a: usize, b: usize) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra != rb {
            let (lo, hi) = if ra < rb { (ra, rb) } else { (rb, ra) };
            self.parent[hi] = lo;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A grid of points on the plane z = `depth`, `spacing` apart, over
    /// [x0, x1) × [y0, y1), skipping points for which `hole` is true.
    fn plane(depth: f32, spacing: f32, (x0, x1): (f32, f32), (y0, y1): (f32, f32), hole: impl Fn(f32, f32) -> bool) -> Vec<Point3> {
        let mut points = Vec::new();
        let mut y = y0;
        while y < y1 {
            let mut x = x0;
            while x < x1 {
                if !hole(x, y) {
                    points.push([x, y, depth]);
                }
                x += spacing;
            }
            y += spacing;
        }
        points
    }

    #[test]
    fn a_background_ring_and_flying_pixels_are_dropped() {
        // A 10 cm square object at 0.6 m; the detector's mask spilled onto a
        // ring of the wall 5 cm behind it; flying pixels hang between them.
        let object = plane(0.6, 0.002, (-0.05, 0.05), (-0.05, 0.05), |_, _| false);
        let ring = plane(0.65, 0.002, (-0.06, 0.06), (-0.06, 0.06), |x, y| x.abs() < 0.052 && y.abs() < 0.052);
        // Mixed pixels along the top edge: each at a random depth between the two surfaces.
        let mut rng = crate::rng::SplitMix64::new(7);
        let flying: Vec<Point3> = (0..50).map(|i| [-0.05 + 0.002 * i as f32, 0.051, 0.6 + 0.05 * rng.next_f64() as f32]).collect();
        let cloud: Vec<Point3> = object.iter().chain(&ring).chain(&flying).copied().collect();
        let keep = segment(&cloud, 0.14, &SegmentSettings::default()).keep;
        let kept_object = keep[..object.len()].iter().filter(|&&k| k).count();
        assert!(kept_object as f64 >= 0.99 * object.len() as f64, "{kept_object} of {} object points", object.len());
        assert!(keep[object.len()..object.len() + ring.len()].iter().all(|&k| !k), "ring points kept");
        let stray = flying.iter().zip(&keep[object.len() + ring.len()..]).filter(|(p, &k)| k && p[2] > 0.61).count();
        assert_eq!(stray, 0, "flying pixels more than 1 cm off the object kept");
    }

    #[test]
    fn an_object_cut_in_two_by_an_occluder_keeps_both_parts() {
        let object = plane(0.6, 0.002, (-0.05, 0.05), (-0.05, 0.05), |x, _| x.abs() < 0.01);
        let keep = segment(&object, 0.14, &SegmentSettings::default()).keep;
        assert!(keep.iter().all(|&k| k));
    }

    #[test]
    fn a_distant_blob_is_dropped() {
        let object = plane(0.6, 0.002, (-0.05, 0.05), (-0.05, 0.05), |_, _| false);
        let far = plane(0.6, 0.002, (0.3, 0.34), (0.0, 0.04), |_, _| false);
        let cloud: Vec<Point3> = object.iter().chain(&far).copied().collect();
        let keep = segment(&cloud, 0.14, &SegmentSettings::default()).keep;
        assert!(keep[..object.len()].iter().all(|&k| k) && keep[object.len()..].iter().all(|&k| !k));
    }

    #[test]
    fn tiny_clouds_are_kept_whole() {
        let cloud = vec![[0.0f32, 0.0, 0.5]; 10];
        assert_eq!(segment(&cloud, 0.1, &SegmentSettings::default()).keep, vec![true; 10]);
    }
}
