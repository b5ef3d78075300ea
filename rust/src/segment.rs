//! Which points of a "segmented" cloud are the object. A detector's mask
//! spills onto the background and depth edges throw flying pixels; both
//! drag the centroid and poison the map. Two robust steps, in the camera
//! frame (metres):
//!
//! 1. a radius outlier test: a point with far fewer neighbours than the
//!    cloud's surfaces typically have floats alone (flying pixels between a
//!    foreground and a background surface);
//! 2. Euclidean clustering at a radius tied to the point spacing (through a
//!    grid of cells, not a kd-tree: no allocation per point): surfaces
//!    separated by a depth jump (the
//!    object and the table or wall behind it) fall apart. The largest
//!    component is the object; other components close to it are kept too
//!    (an occluder in front can cut the object in two, self-occlusion can
//!    split it at a depth jump), unless they lie in its *shadow*: beside it
//!    in the image but behind it, the way a mask's spill onto the table or
//!    wall behind an object does;
//! 3. steep faces put back: a face seen nearly edge-on is sparse in space
//!    (its points lie 1/cos θ of the spacing apart down its slope), so steps
//!    1 and 2 cut it away as outliers and fragments, though in the image it
//!    is as dense as any face. Its depth is a smooth ramp that meets the
//!    object at its edge: a dropped outlier or fragment whose dropped image
//!    neighbours fit a plane in depth, and whose plane passes through an
//!    image neighbour on the object, rejoins it, face by face until none
//!    does. The plane is fitted in inverse depth, which is affine over the
//!    image for a flat face however steep (depth itself curves). Spill lies
//!    across a depth jump from the object's edge and flying pixels scatter
//!    in depth: neither passes. A whole component dropped in step 2 stays
//!    out, even where its ramp meets the edge (a touching neighbour, or the
//!    support plane, the mask spilled onto).
//!
//! Its cost is measured by `cargo bench --bench search -- segment`
//! (`docs/tuning.md`, "The Rust core's constants").

use crate::index::{bounds, counting_sort, sampled_spacings, Grid, ModelTree};
use crate::Point3;

/// No component (a point in nobody's shadow).
const NONE: usize = usize::MAX;

/// Tuning of [`segment`]; every distance is relative, so one setting
/// serves any range and object size. `Default` is where each default is
/// defined (the Python layer's `edgepose.SegmentSettings` reads them).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SegmentSettings {
    /// Clouds of fewer than twice this many points are kept whole; a point
    /// with fewer than a quarter of this many neighbours is an outlier.
    pub neighbours: usize,
    /// A point is an outlier when it has fewer than `1 / (1 + outlier_sigmas)`
    /// of the cloud's median number of neighbours within the cluster radius.
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
    /// A component that hides at least this many of the object's points
    /// (it lies in front of them, beside them in the image) ...
    pub occluder_points: usize,
    /// ... and has fewer points than this fraction of the object's is an
    /// occluder the mask spilled onto, and is dropped. A larger one may be
    /// the object's own part in front of another (kept; evidence in
    /// `docs/tuning.md`).
    pub occluder_fraction: f64,
    /// ... and lies this many object diameters or more in front of the
    /// points it hides (a steep face of the object split off by sparse
    /// sampling lies at their depth).
    pub occluder_margin: f64,
    /// Whether step 3 puts steep faces back (see the module's docs).
    pub steep_faces: bool,
    /// Step 3's image neighbourhood: points within this many spacings of a
    /// point in the image (by viewing direction, measured at the cloud's
    /// median depth).
    pub ramp_spacings: f64,
    /// A dropped point's depth plane is fitted to it and at least this many
    /// dropped image neighbours.
    pub ramp_neighbours: usize,
    /// The plane's rms depth residual must be within this many times the
    /// object's median one (its kept points' planes: the sensor's noise) ...
    pub ramp_noise: f64,
    /// ... or this many spacings, whichever is larger (quantised depth).
    pub ramp_min_noise_spacings: f64,
    /// An image neighbour lies on the plane (a link, to the object or along
    /// the face) within this many times that tolerance of it in depth.
    pub ramp_link: f64,
}

impl Default for SegmentSettings {
    fn default() -> Self {
        Self {
            neighbours: 8,
            outlier_sigmas: 7.0,
            cluster_spacings: 3.0,
            min_component_fraction: 0.01,
            max_component_offset: 0.8,
            max_shadowed_fraction: 0.5,
            shadow_spacings: 4.0,
            occluder_points: 3,
            occluder_fraction: 0.05,
            occluder_margin: 0.1,
            steep_faces: true,
            ramp_spacings: 4.0,
            ramp_neighbours: 5,
            ramp_noise: 3.0,
            ramp_min_noise_spacings: 0.75,
            ramp_link: 3.0,
        }
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
        return Segmentation {
            keep: vec![true; n],
            spacing: 0.0,
        };
    }
    let spacing = median_spacing(cloud).max(1e-6);
    let radius = (settings.cluster_spacings * spacing) as f32;

    // Pairs of points within `radius`, found through a grid of cells that
    // size (every neighbour lies in the 27 cells around a point). Pair
    // order does not matter: a component's root is its lowest index.
    let mut pairs: Vec<(u32, u32)> = Vec::with_capacity(32 * n);
    let mut counts = vec![0.0f64; n];
    CellGrid::new(cloud, radius).for_each_neighbourhood(radius, |i, near| {
        counts[i] += near.len() as f64;
        for &j in near {
            pairs.push((i as u32, j));
            counts[j as usize] += 1.0;
        }
    });

    // 1. Outliers: points with far fewer neighbours than is typical of the
    //    cloud's surfaces (flying pixels hang alone between two surfaces).
    let typical = median_of(&counts);
    let inlier: Vec<bool> = counts
        .iter()
        .map(|&c| c >= (typical / (1.0 + settings.outlier_sigmas)).max(k as f64 / 4.0))
        .collect();

    // 2. Components of the inliers' neighbour graph.
    let mut components = UnionFind::new(n);
    for &(i, j) in &pairs {
        if inlier[i as usize] && inlier[j as usize] {
            components.union(i as usize, j as usize);
        }
    }
    let root_of: Vec<usize> = (0..n).map(|i| components.find(i)).collect();
    let mut size = vec![0usize; n];
    let mut sum = vec![[0.0f64; 3]; n];
    for i in (0..n).filter(|&i| inlier[i]) {
        size[root_of[i]] += 1;
        for a in 0..3 {
            sum[root_of[i]][a] += cloud[i][a] as f64;
        }
    }
    // Components in the shadow of another (beside it in the image, behind
    // it) are background the mask picked up, whatever their size.
    let single = (0..n).filter(|&r| size[r] > 0).count() == 1;
    let shadower = if single {
        vec![NONE; n]
    } else {
        in_shadow(
            cloud,
            &root_of,
            &inlier,
            settings.shadow_spacings * spacing,
            radius as f64,
        )
    };
    let shadowed: Vec<bool> = shadower.iter().map(|&r| r != NONE).collect();
    let mut shadowed_count = vec![0usize; n];
    for i in (0..n).filter(|&i| shadowed[i]) {
        shadowed_count[root_of[i]] += 1;
    }
    // A shadowed component (nearly) wholly inside the rest's silhouette is
    // the object's own (a can's lid behind its rim); spill lies outside it,
    // or only partly inside where the silhouette is concave.
    let rays: Vec<[f64; 2]> = cloud
        .iter()
        .map(|p| [p[0] as f64 / p[2] as f64, p[1] as f64 / p[2] as f64])
        .collect();
    // Inlier points grouped by component (roots ascending), and each
    // group's hull corners in the image: the hull of the rest of the cloud
    // is the hull of the other groups' corners (a few dozen points each).
    let in_front = |i: usize| inlier[i] && cloud[i][2] > 0.0;
    let members = grouped_by(&root_of, |i| inlier[i]);
    let groups: Vec<&[usize]> = members
        .chunk_by(|&a, &b| root_of[a] == root_of[b])
        .collect();
    let corners = std::cell::OnceCell::new();
    let corners = || {
        corners.get_or_init(|| -> Vec<Vec<[f64; 2]>> {
            let front_rays = |group: &[usize]| {
                group
                    .iter()
                    .filter(|&&i| in_front(i))
                    .map(|&i| rays[i])
                    .collect()
            };
            groups
                .iter()
                .map(|group| convex_hull(front_rays(group)))
                .collect()
        })
    };
    // The hull of every group's corners is the hull of the others' for a
    // group with no corner among its vertices.
    let whole = std::cell::OnceCell::new();
    let whole = || whole.get_or_init(|| convex_hull(corners().concat()));
    let mut lit_root = vec![false; n];
    for (g, mine) in groups.iter().enumerate() {
        let root = root_of[mine[0]];
        lit_root[root] =
            (shadowed_count[root] as f64) < settings.max_shadowed_fraction * size[root] as f64 || {
                let outer = corners()[g].iter().any(|c| whole().contains(c));
                let others_hull;
                let hull = if outer {
                    let others: Vec<[f64; 2]> = corners()
                        .iter()
                        .enumerate()
                        .filter(|&(h, _)| h != g)
                        .flat_map(|(_, c)| c.iter().copied())
                        .collect();
                    others_hull = convex_hull(others);
                    &others_hull
                } else {
                    whole()
                };
                let inside = mine
                    .iter()
                    .filter(|&&i| inside_convex(hull, rays[i]))
                    .count();
                10 * inside >= 9 * mine.len()
            };
    }
    let lit = |root: usize| lit_root[root];
    // The object: the largest lit component (ties to the lowest root, so the
    // result is deterministic), with lit components of some size near it.
    let largest = (0..n)
        .filter(|&r| lit(r))
        .max_by(|&a, &b| size[a].cmp(&size[b]).then(b.cmp(&a)))
        .or_else(|| (0..n).max_by(|&a, &b| size[a].cmp(&size[b]).then(b.cmp(&a))))
        .expect("n > 0");
    let centroid = |root: usize| sum[root].map(|s| s / size[root] as f64);
    let anchor = centroid(largest);
    // Components in front of the object that hide some of it: an occluder's
    // surface the mask spilled onto.
    // Counted only for a component well in front of what it hides (its
    // centroid nearer by `occluder_margin` diameters than their mean depth):
    // a steep face of the object that sampling split off lies at its depth.
    let (mut hides, mut hidden_depth) = (vec![0usize; n], vec![0.0f64; n]);
    for i in (0..n).filter(|&i| root_of[i] == largest && shadower[i] != NONE) {
        hides[shadower[i]] += 1;
        hidden_depth[shadower[i]] += cloud[i][2] as f64;
    }
    for root in 0..n {
        if hides[root] > 0
            && hidden_depth[root] / hides[root] as f64 - centroid(root)[2]
                < settings.occluder_margin * diameter
        {
            hides[root] = 0;
        }
    }
    // The size floor: a component smaller than this is a fragment.
    let above_floor =
        |root: usize| size[root] as f64 >= settings.min_component_fraction * size[largest] as f64;
    let keep_root: Vec<bool> = (0..n)
        .map(|root| {
            root == largest
                || (lit(root)
                    && above_floor(root)
                    && distance(centroid(root), anchor) <= settings.max_component_offset * diameter
                    && (hides[root] < settings.occluder_points
                        || size[root] as f64 >= settings.occluder_fraction * size[largest] as f64))
        })
        .collect();
    let mut keep: Vec<bool> = (0..n).map(|i| inlier[i] && keep_root[root_of[i]]).collect();
    if settings.steep_faces {
        let object = |i: usize| inlier[i] && root_of[i] == largest;
        // Only what a steep face breaks into may rejoin: outliers and
        // fragments below the size floor. A whole component dropped for
        // lying in a shadow or in front of the object is a surface beside
        // it (a touching neighbour, the support plane seen steeply).
        let fragment = |i: usize| !inlier[i] || !above_floor(root_of[i]);
        rejoin_steep_faces(cloud, &mut keep, object, fragment, spacing, settings);
    }
    Segmentation { keep, spacing }
}

/// Step 3: puts the steep faces of the object that steps 1 and 2 dropped
/// back into `keep` (see the module's docs): those that meet a point for
/// which `object` holds (the largest component: other kept components do
/// not grow). Only dropped points for which `fragment` holds may rejoin.
/// `spacing`: the cloud's median point spacing, metres.
fn rejoin_steep_faces(
    cloud: &[Point3],
    keep: &mut [bool],
    object: impl Fn(usize) -> bool,
    fragment: impl Fn(usize) -> bool,
    spacing: f64,
    settings: &SegmentSettings,
) {
    // Image positions: viewing directions scaled to lateral metres at the
    // median depth (points at or behind the camera take no part).
    let front: Vec<usize> = (0..cloud.len()).filter(|&i| cloud[i][2] > 0.0).collect();
    if front.iter().all(|&i| keep[i]) || !front.iter().any(|&i| keep[i]) {
        return;
    }
    let depths: Vec<f64> = front.iter().map(|&i| cloud[i][2] as f64).collect();
    let z0 = median_of(&depths) as f32;
    let image: Vec<Point3> = front
        .iter()
        .map(|&i| {
            let p = cloud[i];
            [p[0] / p[2] * z0, p[1] / p[2] * z0, 0.0]
        })
        .collect();
    let depth = |a: usize| cloud[front[a]][2];
    let kept: Vec<bool> = front.iter().map(|&i| keep[i]).collect();
    let reach = (settings.ramp_spacings * spacing) as f32;
    let grid = CellGrid::new(&image, reach.max(1e-9));
    // Point `a`'s image neighbours (itself excluded) into `near`, and its
    // depth plane over it and those of the same status (kept or dropped),
    // with the plane's rms residual (metres); `None` for too few.
    let plane_of = |a: usize, near: &mut Vec<usize>| -> Option<(DepthPlane, f64)> {
        near.clear();
        grid.within(&image[a], reach, |b| {
            if b != a {
                near.push(b);
            }
        });
        let offset = |b: usize| {
            (
                image[b][0] - image[a][0],
                image[b][1] - image[a][1],
                depth(b),
            )
        };
        let same = std::iter::once(a).chain(near.iter().copied().filter(|&b| kept[b] == kept[a]));
        (same.clone().count() > settings.ramp_neighbours)
            .then(|| DepthPlane::fit(same.map(offset)))
            .flatten()
    };
    // The sensor's noise: the median rms of the kept points' planes (a
    // sample of at most 128 of them). Worked out when a dropped point first
    // has a plane: a cloud whose only dropped points are scattered flying
    // pixels needs none.
    let tolerance = std::cell::OnceCell::new();
    let tolerance = || {
        *tolerance.get_or_init(|| {
            let mut near = Vec::new();
            let kept_at: Vec<usize> = (0..front.len()).filter(|&a| kept[a]).collect();
            let noise: Vec<f64> = kept_at
                .iter()
                .step_by(kept_at.len().div_ceil(128).max(1))
                .filter_map(|&a| plane_of(a, &mut near).map(|(_, rms)| rms))
                .collect();
            (settings.ramp_noise * median_of(&noise))
                .max(settings.ramp_min_noise_spacings * spacing)
        })
    };
    // Each dropped point on a plane (a ramp) is linked to the image
    // neighbours on its plane; it rejoins when a chain of links leads to a
    // point of the object (the object's edge the face meets).
    let mut near = Vec::new();
    let mut rejoined = vec![false; front.len()];
    let mut linked_from: Vec<Vec<u32>> = vec![Vec::new(); front.len()];
    let mut queue = Vec::new();
    for a in (0..front.len()).filter(|&a| !kept[a] && fragment(front[a])) {
        let Some((plane, rms)) = plane_of(a, &mut near) else {
            continue;
        };
        if rms > tolerance() {
            continue;
        }
        let reach_link = settings.ramp_link * tolerance();
        for &b in &near {
            let on_plane = plane.depth_at(image[b][0] - image[a][0], image[b][1] - image[a][1]);
            if (depth(b) as f64 - on_plane).abs() <= reach_link {
                if object(front[b]) && !rejoined[a] {
                    rejoined[a] = true;
                    queue.push(a);
                } else if !kept[b] {
                    linked_from[b].push(a as u32);
                }
            }
        }
    }
    while let Some(b) = queue.pop() {
        keep[front[b]] = true;
        for &a in &linked_from[b] {
            if !rejoined[a as usize] {
                rejoined[a as usize] = true;
                queue.push(a as usize);
            }
        }
    }
}

/// A plane seen from the camera: inverse depth is affine over the image,
/// `1/z = a + b·u + c·v` (`u`, `v` lateral metres from the point it was
/// fitted around, at a common depth; exact for a flat surface however
/// steeply it is seen, where depth itself curves).
#[derive(Clone, Copy, Debug)]
struct DepthPlane {
    a: f64,
    b: f64,
    c: f64,
}

impl DepthPlane {
    /// The least-squares plane through `(u, v, z)` samples and its rms
    /// depth residual (metres); `None` when they do not span the image
    /// plane (a line).
    fn fit(samples: impl Iterator<Item = (f32, f32, f32)> + Clone) -> Option<(Self, f64)> {
        let mut normal = nalgebra::Matrix3::<f64>::zeros();
        let mut rhs = nalgebra::Vector3::<f64>::zeros();
        let mut count = 0.0;
        for (u, v, z) in samples.clone() {
            let row = nalgebra::Vector3::new(1.0, u as f64, v as f64);
            normal += row * row.transpose();
            rhs += row / z as f64;
            count += 1.0;
        }
        let solution = normal.cholesky()?.solve(&rhs);
        let plane = Self {
            a: solution[0],
            b: solution[1],
            c: solution[2],
        };
        let squares: f64 = samples
            .map(|(u, v, z)| (z as f64 - plane.depth_at(u, v)).powi(2))
            .sum();
        Some((plane, (squares / count).sqrt()))
    }

    /// Depth at `(u, v)`, metres (infinite where the plane does not cross
    /// the viewing ray in front of the camera).
    fn depth_at(&self, u: f32, v: f32) -> f64 {
        let inverse = self.a + self.b * u as f64 + self.c * v as f64;
        if inverse > 0.0 {
            1.0 / inverse
        } else {
            f64::INFINITY
        }
    }
}

/// For each inlier point in the shadow of another component (a point of
/// another component lies within `lateral` metres of it by viewing direction,
/// measured at the point's depth, and nearer the camera by more than `gap`
/// metres), the root of the first such component found; [`NONE`] otherwise.
fn in_shadow(
    cloud: &[Point3],
    root_of: &[usize],
    inlier: &[bool],
    lateral: f64,
    gap: f64,
) -> Vec<usize> {
    let mut shadowed = vec![NONE; cloud.len()];
    let front: Vec<usize> = (0..cloud.len())
        .filter(|&i| inlier[i] && cloud[i][2] > 0.0)
        .collect();
    if front.is_empty() {
        return shadowed;
    }
    let mut depths: Vec<f64> = front.iter().map(|&i| cloud[i][2] as f64).collect();
    let reach = (lateral / median_of(&depths)) as f32;
    depths.clear();
    // Directions (x/z, y/z) as points on the plane z = 1.
    let rays: Vec<Point3> = front
        .iter()
        .map(|&i| [cloud[i][0] / cloud[i][2], cloud[i][1] / cloud[i][2], 0.0])
        .collect();
    let roots: Vec<usize> = front.iter().map(|&i| root_of[i]).collect();
    CellGrid::new(&rays, reach.max(1e-9)).for_each_near(reach, &roots, |a, near| {
        for &b in near {
            let (i, j) = (front[a], front[b as usize]);
            let behind = (cloud[i][2] - cloud[j][2]) as f64;
            if behind > gap {
                if shadowed[i] == NONE {
                    shadowed[i] = root_of[j];
                }
            } else if -behind > gap && shadowed[j] == NONE {
                shadowed[j] = root_of[i];
            }
        }
    });
    shadowed
}

/// Median distance from a point to its nearest neighbour, over an evenly
/// spread sample of at most 256 points (enough for a median), metres.
///
/// Looked up in a grid of cubes about as large as a surface's spacing would
/// be if the points covered the cloud's two largest extents: a nearest
/// neighbour within a cube's side is exact, and the median is exact when
/// more than half the samples have one. Otherwise (a cloud along a line)
/// the kd-tree answers.
fn median_spacing(cloud: &[Point3]) -> f64 {
    let (lo, hi) = bounds(cloud);
    let mut extents: [f64; 3] = std::array::from_fn(|a| (hi[a] - lo[a]) as f64);
    extents.sort_by(|a, b| b.total_cmp(a));
    let guess = 1.5 * (extents[0] * extents[1] / cloud.len().max(1) as f64).sqrt();
    if guess > 0.0 {
        let grid = CellGrid::new(cloud, guess as f32);
        let step = cloud.len().div_ceil(256).max(1);
        let mut found: Vec<f64> = Vec::with_capacity(256);
        let mut samples = 0;
        for i in (0..cloud.len()).step_by(step) {
            samples += 1;
            if let Some(d2) = grid.nearest_squared_distance(i, &cloud[i]) {
                found.push((d2 as f64).sqrt());
            }
        }
        // `median_of`'s rank among all samples, the unfound ones last.
        let rank = ((samples - 1) as f64 * 0.5).round() as usize;
        if rank < found.len() {
            return *found.select_nth_unstable_by(rank, f64::total_cmp).1;
        }
    }
    median_of(&sampled_spacings(&ModelTree::new_from_slice(cloud), cloud))
}

/// Most cubes a [`CellGrid`] holds per point (a larger side beyond that):
/// its cubes are scanned once, so an empty cube costs almost nothing.
const CUBES_PER_POINT: f64 = 8.0;

/// Points binned into cubes of side `cell` (or a little more, see
/// [`CUBES_PER_POINT`]): every point within `cell` of another lies in the
/// 27 cubes around its cube (9 squares for `flat` points, all with z = 0).
/// Cubes are numbered z fastest, so the three cubes of a column along z
/// hold one contiguous run of points.
struct CellGrid {
    grid: Grid,
    /// Point indices sorted by cube.
    order: Vec<u32>,
    /// The points' coordinates in that order (contiguous per cube).
    xs: Vec<f32>,
    ys: Vec<f32>,
    zs: Vec<f32>,
    /// Per cube, where its points start in `order` (one more entry at the end).
    starts: Vec<u32>,
}

impl CellGrid {
    fn new(points: &[Point3], cell: f32) -> Self {
        let (lo, hi) = bounds(points);
        let max_cubes = (CUBES_PER_POINT * points.len() as f64).max(4096.0);
        // A margin of a hundredth of a cube: a point on the box's far faces
        // stays inside whatever the rounding.
        let grid = Grid::new(lo, hi, cell, 0.01 * cell as f64, max_cubes);
        let (order, starts) = grid.bin(points);
        let axis = |a: usize| order.iter().map(|&i| points[i as usize][a]).collect();
        Self {
            grid,
            xs: axis(0),
            ys: axis(1),
            zs: axis(2),
            order,
            starts,
        }
    }

    /// The squared distance from `p` (point `i` of the binned points) to
    /// its nearest other point, when that lies within a cube's side.
    fn nearest_squared_distance(&self, i: usize, p: &Point3) -> Option<f32> {
        let mut best = f32::INFINITY;
        self.scan_around(p, |k, d| {
            if d < best && self.order[k] as usize != i {
                best = d;
            }
        })?;
        let limit = self.grid.cell * self.grid.cell;
        (best <= limit).then_some(best)
    }

    /// Visits every binned point within `within` (no more than a cube's
    /// side) of `p`, `p` itself included when binned.
    fn within(&self, p: &Point3, within: f32, mut visit: impl FnMut(usize)) {
        let limit = within * within;
        self.scan_around(p, |k, d| {
            if d <= limit {
                visit(self.order[k] as usize);
            }
        });
    }

    /// `visit(k, squared distance to p)` for every binned point (its place
    /// `k` in cube order) in the 27 cubes around `p`'s; `None` when `p` lies
    /// outside the grid.
    fn scan_around(&self, p: &Point3, mut visit: impl FnMut(usize, f32)) -> Option<()> {
        let g = self.grid.coordinates(p)?;
        let dims = self.grid.dims;
        for x in (g[0] - 1).max(0)..=(g[0] + 1).min(dims[0] - 1) {
            for y in (g[1] - 1).max(0)..=(g[1] + 1).min(dims[1] - 1) {
                let first = self.grid.flat([x, y, (g[2] - 1).max(0)]);
                let last = self.grid.flat([x, y, (g[2] + 1).min(dims[2] - 1)]);
                for k in self.starts[first] as usize..self.starts[last + 1] as usize {
                    let d = (self.xs[k] - p[0]).powi(2)
                        + (self.ys[k] - p[1]).powi(2)
                        + (self.zs[k] - p[2]).powi(2);
                    visit(k, d);
                }
            }
        }
        Some(())
    }

    /// The runs of cubes (first and last cube, as [`Grid::flat`] indices)
    /// of `columns` of [`LATER_CUBES`] around cube `g` that lie in the grid.
    fn runs_of<'a>(
        &'a self,
        g: [i32; 3],
        columns: &'a [([i32; 2], i32, i32)],
    ) -> impl Iterator<Item = (usize, usize)> + 'a {
        let dims = self.grid.dims;
        columns.iter().filter_map(move |&([dx, dy], z0, z1)| {
            let (x, y) = (g[0] + dx, g[1] + dy);
            let (z0, z1) = ((g[2] + z0).max(0), (g[2] + z1).min(dims[2] - 1));
            (x >= 0 && x < dims[0] && y >= 0 && y < dims[1] && z0 <= z1)
                .then(|| (self.grid.flat([x, y, z0]), self.grid.flat([x, y, z1])))
        })
    }

    /// Visits every unordered pair of distinct points at most `within`
    /// apart (no more than a cube's side) once: `visit(i, near)` gets each
    /// point `i` with all its partners at once, those after it in its cube
    /// and the next one along z, then those in the other cubes that sort
    /// after its cube (in that order): the pairs
    /// [`for_each_near`](Self::for_each_near) visits when every label
    /// differs, point by point instead of run by run. Each cube's partner
    /// cubes are copied into one buffer, which a point scans eight partners
    /// at a time where AVX2 is present (a run is a few points; a buffer is
    /// dozens).
    fn for_each_neighbourhood(&self, within: f32, mut visit: impl FnMut(usize, &[u32])) {
        let limit = within * within;
        let (order, starts, dims) = (&self.order, &self.starts, self.grid.dims);
        let mut partners = Partners::default();
        let mut near: Vec<u32> = Vec::new();
        for c in 0..self.grid.count() {
            let (a, b) = (starts[c] as usize, starts[c + 1] as usize);
            if a == b {
                continue;
            }
            let g = self.grid.unflat(c);
            partners.clear();
            // The cube's own points and the next cube's along z: one run.
            let up = if g[2] + 1 < dims[2] { c + 1 } else { c };
            partners.extend(self, a, starts[up + 1] as usize);
            for (first, last) in self.runs_of(g, &LATER_CUBES[1..]) {
                partners.extend(self, starts[first] as usize, starts[last + 1] as usize);
            }
            partners.pad();
            near.resize(partners.len() + LANES, 0);
            for (x, &i) in order[a..b].iter().enumerate() {
                let p = [self.xs[a + x], self.ys[a + x], self.zs[a + x]];
                // Within the cube, only the points after this one.
                let found = partners.near(x + 1, p, limit, &mut near);
                if found > 0 {
                    visit(i as usize, &near[..found]);
                }
            }
        }
    }

    /// Visits every unordered pair of distinct points at most `within`
    /// apart (no more than a cube's side) whose `labels` (one per point)
    /// differ once, in batches: `visit(i, near)` gets point `i` and some of
    /// its partners `near`. Cube by cube in a fixed order: the pairs within
    /// a cube, then those with each run of neighbouring cubes that sort
    /// after it (so no pair is seen twice). Cubes whose points all share
    /// one label are not paired with each other: most of a cloud is one
    /// component, and its pairs are skipped wholesale.
    fn for_each_near(&self, within: f32, labels: &[usize], mut visit: impl FnMut(usize, &[u32])) {
        let limit = within * within;
        let (order, starts) = (&self.order, &self.starts);
        let dims = self.grid.dims;
        let count = self.grid.count();
        /// A cube without points.
        const EMPTY: usize = usize::MAX;
        /// A cube whose points carry different labels.
        const MIXED: usize = usize::MAX - 1;
        let cube_labels: Vec<usize> = (0..count)
            .map(|c| {
                let mine = &order[starts[c] as usize..starts[c + 1] as usize];
                match mine.first().map(|&i| labels[i as usize]) {
                    None => EMPTY,
                    Some(first) if mine.iter().all(|&i| labels[i as usize] == first) => first,
                    Some(_) => MIXED,
                }
            })
            .collect();
        let label_of = |c: usize| cube_labels[c];
        let differ = |i: u32, j: u32| labels[i as usize] != labels[j as usize];
        let mut runs: Vec<(usize, usize)> = Vec::with_capacity(LATER_CUBES.len());
        let mut near: Vec<u32> = Vec::new();
        for c in 0..count {
            let (a, b) = (starts[c] as usize, starts[c + 1] as usize);
            if a == b {
                continue;
            }
            let label = label_of(c);
            let pure = label != MIXED;
            let g = self.grid.unflat(c);
            runs.clear();
            // A mixed cube's own points pair among themselves and with the
            // next cube along z, which follows them: one run.
            let up = if g[2] + 1 < dims[2] { c + 1 } else { c };
            let own = (!pure).then_some((a, starts[up + 1] as usize));
            for (first, last) in self.runs_of(g, &LATER_CUBES[own.map_or(0, |_| 1)..]) {
                let (ra, rb) = (starts[first] as usize, starts[last + 1] as usize);
                // A pure cube is not paired with a run of cubes all of its label.
                if ra < rb
                    && !(pure
                        && (first..=last)
                            .all(|k| matches!(label_of(k), l if l == label || l == EMPTY)))
                {
                    runs.push((ra, rb));
                }
            }
            // Pairs within the cube and the next (none within a pure cube),
            // then with each run; the near ones gathered without a branch per
            // point (whether one is near is a coin toss).
            for (r, &(ra, rb)) in own.iter().chain(&runs).enumerate() {
                let (rx, ry, rz, ro) = (
                    &self.xs[ra..rb],
                    &self.ys[ra..rb],
                    &self.zs[ra..rb],
                    &order[ra..rb],
                );
                if near.len() < rb - ra {
                    near.resize(rb - ra, 0);
                }
                let mine = order[a..b]
                    .iter()
                    .zip(&self.xs[a..b])
                    .zip(&self.ys[a..b])
                    .zip(&self.zs[a..b]);
                for (x, (((&i, &px), &py), &pz)) in mine.enumerate() {
                    // Within the cube, only the points after this one.
                    let from = if r == 0 && own.is_some() { x + 1 } else { 0 };
                    let mut found = 0;
                    let run = rx[from..]
                        .iter()
                        .zip(&ry[from..])
                        .zip(&rz[from..])
                        .zip(&ro[from..]);
                    for (((&qx, &qy), &qz), &j) in run {
                        let d =
                            (qx - px) * (qx - px) + (qy - py) * (qy - py) + (qz - pz) * (qz - pz);
                        near[found] = j;
                        found += ((d <= limit) & differ(i, j)) as usize;
                    }
                    if found > 0 {
                        visit(i as usize, &near[..found]);
                    }
                }
            }
        }
    }
}

/// The neighbouring cubes that sort after a cube (lexicographically by
/// offset), as runs along z: (0, 0, +1), then the columns (0, +1),
/// (+1, −1), (+1, 0) and (+1, +1), each from z − 1 to z + 1.
const LATER_CUBES: [([i32; 2], i32, i32); 5] = [
    ([0, 0], 1, 1),
    ([0, 1], -1, 1),
    ([1, -1], -1, 1),
    ([1, 0], -1, 1),
    ([1, 1], -1, 1),
];

/// Points scanned together by [`Partners::near`] (and its padding).
const LANES: usize = 8;

/// The points of a cube's partner cubes, copied into one buffer
/// ([`CellGrid::for_each_neighbourhood`]): coordinates and point indices,
/// then [`LANES`] points at infinity, which are near nothing.
#[derive(Default)]
struct Partners {
    xs: Vec<f32>,
    ys: Vec<f32>,
    zs: Vec<f32>,
    index: Vec<u32>,
}

impl Partners {
    fn clear(&mut self) {
        for axis in [&mut self.xs, &mut self.ys, &mut self.zs] {
            axis.clear();
        }
        self.index.clear();
    }

    /// Appends the grid's points `from..to` (in cube order).
    fn extend(&mut self, grid: &CellGrid, from: usize, to: usize) {
        self.xs.extend_from_slice(&grid.xs[from..to]);
        self.ys.extend_from_slice(&grid.ys[from..to]);
        self.zs.extend_from_slice(&grid.zs[from..to]);
        self.index.extend_from_slice(&grid.order[from..to]);
    }

    /// Ends the buffer with the padding a scan may read past its last point.
    fn pad(&mut self) {
        for axis in [&mut self.xs, &mut self.ys, &mut self.zs] {
            axis.extend_from_slice(&[f32::INFINITY; LANES]);
        }
        self.index.extend_from_slice(&[0; LANES]);
    }

    /// Points held, padding aside.
    fn len(&self) -> usize {
        self.index.len() - LANES
    }

    /// Writes to the front of `near` (at least [`len`](Self::len) +
    /// [`LANES`] entries) the indices of the points from `start` on whose
    /// squared distance to `p` is at most `limit`, in order, and returns
    /// how many.
    fn near(&self, start: usize, p: Point3, limit: f32, near: &mut [u32]) -> usize {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: AVX2 is present (checked above).
            return unsafe { self.near_avx2(start, p, limit, near) };
        }
        self.near_one_at_a_time(start, p, limit, near)
    }

    /// [`near`](Self::near), one point at a time.
    fn near_one_at_a_time(&self, start: usize, p: Point3, limit: f32, near: &mut [u32]) -> usize {
        let mut found = 0;
        let end = self.len();
        let points = self.xs[start..end]
            .iter()
            .zip(&self.ys[start..end])
            .zip(&self.zs[start..end])
            .zip(&self.index[start..end]);
        for (((&qx, &qy), &qz), &j) in points {
            let d =
                (qx - p[0]) * (qx - p[0]) + (qy - p[1]) * (qy - p[1]) + (qz - p[2]) * (qz - p[2]);
            // Written whether near or not: no branch on a coin toss.
            near[found] = j;
            found += (d <= limit) as usize;
        }
        found
    }

    /// [`near`](Self::near) eight points at a time: the distances in the
    /// scalar loop's operation order (no fused multiply-add), the near
    /// points' indices packed to the front of each eight and stored at once.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn near_avx2(&self, start: usize, p: Point3, limit: f32, near: &mut [u32]) -> usize {
        use std::arch::x86_64::*;
        let end = self.len();
        // Every load of eight from k < end ends within the padding, every
        // store at `found` ≤ k − start within `near`.
        assert!(start <= end && near.len() >= end + LANES);
        let (px, py, pz) = (
            _mm256_set1_ps(p[0]),
            _mm256_set1_ps(p[1]),
            _mm256_set1_ps(p[2]),
        );
        let limit = _mm256_set1_ps(limit);
        let (mut k, mut found) = (start, 0);
        while k < end {
            // SAFETY: see the assertion above.
            unsafe {
                let dx = _mm256_sub_ps(_mm256_loadu_ps(self.xs.as_ptr().add(k)), px);
                let dy = _mm256_sub_ps(_mm256_loadu_ps(self.ys.as_ptr().add(k)), py);
                let dz = _mm256_sub_ps(_mm256_loadu_ps(self.zs.as_ptr().add(k)), pz);
                let d = _mm256_add_ps(
                    _mm256_add_ps(_mm256_mul_ps(dx, dx), _mm256_mul_ps(dy, dy)),
                    _mm256_mul_ps(dz, dz),
                );
                let within = _mm256_cmp_ps::<_CMP_LE_OQ>(d, limit);
                // Lanes past the last point hold infinity: never within.
                let mask = _mm256_movemask_ps(within) as usize;
                let lanes = _mm256_loadu_si256(PACKED_LANES[mask].as_ptr() as *const __m256i);
                let indices = _mm256_loadu_si256(self.index.as_ptr().add(k) as *const __m256i);
                _mm256_storeu_si256(
                    near.as_mut_ptr().add(found) as *mut __m256i,
                    _mm256_permutevar8x32_epi32(indices, lanes),
                );
                found += mask.count_ones() as usize;
            }
            k += LANES;
        }
        found
    }
}

/// For each 8-bit mask, the positions of its set bits in order (the rest
/// 0): the permutation that packs the chosen lanes of eight to the front.
#[cfg(target_arch = "x86_64")]
static PACKED_LANES: [[u32; 8]; 256] = {
    let mut table = [[0u32; 8]; 256];
    let mut mask = 0;
    while mask < 256 {
        let (mut lane, mut next) = (0, 0);
        while lane < 8 {
            if mask & (1 << lane) != 0 {
                table[mask][next] = lane as u32;
                next += 1;
            }
            lane += 1;
        }
        mask += 1;
    }
    table
};

/// The indices `i` for which `chosen(i)`, ordered by `label[i]` (labels
/// below `label.len()`), ascending within a label.
fn grouped_by(label: &[usize], chosen: impl Fn(usize) -> bool) -> Vec<usize> {
    let n = label.len();
    let keys: Vec<usize> = (0..n)
        .map(|i| if chosen(i) { label[i] } else { n })
        .collect();
    let (order, starts) = counting_sort(&keys, n);
    order[..starts[n] as usize]
        .iter()
        .map(|&i| i as usize)
        .collect()
}

/// Convex hull of 2-D points, counter-clockwise (Andrew's monotone chain).
/// Points strictly inside the octagon of the extreme points in eight
/// directions cannot be corners and are dropped before sorting (Akl and
/// Toussaint): most of a dense blob.
fn convex_hull(mut points: Vec<[f64; 2]>) -> Vec<[f64; 2]> {
    if points.len() > 32 {
        let directions: [[f64; 2]; 8] = [
            [1.0, 0.0],
            [1.0, 1.0],
            [0.0, 1.0],
            [-1.0, 1.0],
            [-1.0, 0.0],
            [-1.0, -1.0],
            [0.0, -1.0],
            [1.0, -1.0],
        ];
        let mut best = [f64::NEG_INFINITY; 8];
        let mut octagon = [[0.0f64; 2]; 8];
        for p in &points {
            for (k, d) in directions.iter().enumerate() {
                let reach = d[0] * p[0] + d[1] * p[1];
                if reach > best[k] {
                    best[k] = reach;
                    octagon[k] = *p;
                }
            }
        }
        let mut octagon = octagon.to_vec();
        octagon.dedup();
        if octagon.len() > 1 && octagon.first() == octagon.last() {
            octagon.pop();
        }
        if octagon.len() >= 3 {
            let strictly_inside = |p: &[f64; 2]| {
                (0..octagon.len()).all(|k| {
                    let (a, b) = (octagon[k], octagon[(k + 1) % octagon.len()]);
                    (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]) > 0.0
                })
            };
            points.retain(|p| !strictly_inside(p));
        }
    }
    points.sort_unstable_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    points.dedup();
    if points.len() < 3 {
        return points;
    }
    let cross = |o: [f64; 2], a: [f64; 2], b: [f64; 2]| {
        (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
    };
    let mut hull: Vec<[f64; 2]> = Vec::with_capacity(2 * points.len());
    for pass in 0..2 {
        let start = hull.len();
        let ordered: Box<dyn Iterator<Item = &[f64; 2]>> = if pass == 0 {
            Box::new(points.iter())
        } else {
            Box::new(points.iter().rev())
        };
        for &p in ordered {
            while hull.len() >= start + 2
                && cross(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0
            {
                hull.pop();
            }
            hull.push(p);
        }
        hull.pop();
    }
    hull
}

/// Whether `p` lies inside (or on) the counter-clockwise convex polygon `hull`.
fn inside_convex(hull: &[[f64; 2]], p: [f64; 2]) -> bool {
    hull.len() >= 3
        && (0..hull.len()).all(|k| {
            let (a, b) = (hull[k], hull[(k + 1) % hull.len()]);
            (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]) >= 0.0
        })
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
        Self {
            parent: (0..n).collect(),
        }
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
    fn plane(
        depth: f32,
        spacing: f32,
        (x0, x1): (f32, f32),
        (y0, y1): (f32, f32),
        hole: impl Fn(f32, f32) -> bool,
    ) -> Vec<Point3> {
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
    fn spill_onto_an_occluder_in_front_is_dropped_but_a_large_front_part_is_kept() {
        // A 14 × 10 cm object (diameter taken as 0.2 m) at 0.7 m; its right
        // edge is hidden by an occluder at 0.6 m, and the mask spilled onto a
        // strip of it beside the edge in the image (3 columns, 4 % of the
        // object's points). The same strip only 1.5 cm in front (less than
        // `occluder_margin`, 0.1 diameters) is kept: it may be a steep face
        // of the object that sparse sampling split off.
        let object = plane(0.7, 0.002, (0.0, 0.14), (0.0, 0.1), |_, _| false);
        for (columns, depth, dropped) in [(3, 0.6f32, true), (12, 0.6, false), (3, 0.685, false)] {
            let edge = 0.14 / 0.7 * depth; // the object's edge ray, at the strip's depth
            let width = columns as f32 * 0.002;
            let strip = plane(
                depth,
                0.002,
                (edge, edge + width - 1e-4),
                (0.0, 0.1 * depth / 0.7),
                |_, _| false,
            );
            let cloud: Vec<Point3> = object.iter().chain(&strip).copied().collect();
            let found = segment(&cloud, 0.2, &SegmentSettings::default());
            let kept_object = found.keep[..object.len()].iter().filter(|&&k| k).count();
            let kept_strip = found.keep[object.len()..].iter().filter(|&&k| k).count();
            assert!(
                kept_object as f64 > 0.95 * object.len() as f64,
                "{kept_object} of {}",
                object.len()
            );
            if dropped {
                assert_eq!(
                    kept_strip,
                    0,
                    "a thin occluder strip of {} points was kept",
                    strip.len()
                );
            } else {
                // 12 columns: 17 % of the object's size, as large as a part
                // of it in front of another; 1.5 cm: within the margin.
                assert_eq!(kept_strip, strip.len(), "{columns} columns at {depth} m");
            }
        }
    }

    #[test]
    fn a_background_ring_and_flying_pixels_are_dropped() {
        // A 10 cm square object at 0.6 m; the detector's mask spilled onto a
        // ring of the wall 5 cm behind it; flying pixels hang between them.
        let object = plane(0.6, 0.002, (-0.05, 0.05), (-0.05, 0.05), |_, _| false);
        let ring = plane(0.65, 0.002, (-0.06, 0.06), (-0.06, 0.06), |x, y| {
            x.abs() < 0.052 && y.abs() < 0.052
        });
        // Mixed pixels along the top edge: each at a random depth between the two surfaces.
        let mut rng = crate::rng::SplitMix64::new(7);
        let flying: Vec<Point3> = (0..50)
            .map(|i| {
                [
                    -0.05 + 0.002 * i as f32,
                    0.051,
                    0.6 + 0.05 * rng.next_f64() as f32,
                ]
            })
            .collect();
        let cloud: Vec<Point3> = object.iter().chain(&ring).chain(&flying).copied().collect();
        let keep = segment(&cloud, 0.14, &SegmentSettings::default()).keep;
        let kept_object = keep[..object.len()].iter().filter(|&&k| k).count();
        assert!(
            kept_object as f64 >= 0.99 * object.len() as f64,
            "{kept_object} of {} object points",
            object.len()
        );
        assert!(
            keep[object.len()..object.len() + ring.len()]
                .iter()
                .all(|&k| !k),
            "ring points kept"
        );
        let stray = flying
            .iter()
            .zip(&keep[object.len() + ring.len()..])
            .filter(|(p, &k)| k && p[2] > 0.61)
            .count();
        assert_eq!(stray, 0, "flying pixels more than 1 cm off the object kept");
    }

    /// A box's face at 0.6 m whose right side, seen `steepness` degrees
    /// from face-on, runs back to `far` metres, sampled evenly in the image
    /// through a mask that spills `wall_columns` columns onto a wall at
    /// 0.75 m beside it (none: no wall): (cloud, what each point is).
    fn box_with_a_steep_side(
        steepness: f64,
        far: f64,
        wall_columns: f64,
    ) -> (Vec<Point3>, Vec<Surface>) {
        let slope = steepness.to_radians().tan();
        // The side runs from the front's edge (u = 0, 0.6 m) to `far`.
        let side_end = (1.0 - 0.6 / far) / slope;
        let wall_end = side_end + wall_columns * 0.002 / 0.75;
        sampled_in_image(wall_end, |u| {
            if u < 0.0 {
                (0.6, Surface::Front)
            } else if u < side_end {
                (0.6 / (1.0 - u * slope), Surface::Side)
            } else {
                (0.75, Surface::Wall)
            }
        })
    }

    #[test]
    fn a_deep_steep_face_is_put_back_whole() {
        // A side 85–87° from face-on running 20–30 cm back: over a point's
        // image neighbours its depth curves, and a plane fitted to depth
        // itself left 59 % of it (85°, to 0.9 m) and 79–85 % (87°) out.
        for (steepness, far) in [(85.0, 0.9), (87.0, 0.8), (87.0, 0.9)] {
            let (cloud, what) = box_with_a_steep_side(steepness, far, 0.0);
            let [_, [front, side]] = kept_shares(&cloud, &what, [Surface::Front, Surface::Side]);
            assert!(front >= 0.99, "{steepness}° to {far} m: front {front}");
            assert!(side >= 0.9, "{steepness}° to {far} m: side {side}");
        }
    }

    #[test]
    fn a_flat_surface_seen_steeply_is_a_depth_plane() {
        // Depth over the image curves on a flat surface seen 85° from
        // face-on (its inverse is affine): the fit leaves no residual.
        let slope = 85f64.to_radians().tan();
        let samples: Vec<(f32, f32, f32)> = (0..9)
            .flat_map(|i| (0..9).map(move |j| (i as f32 * 0.002, j as f32 * 0.002)))
            .map(|(u, v)| (u, v, (0.6 / (1.0 - u as f64 / 0.6 * slope)) as f32))
            .collect();
        let (plane, rms) = DepthPlane::fit(samples.iter().copied()).expect("spans the image");
        assert!(rms < 1e-4, "rms {rms} m over depths to {}", samples[80].2);
        let far = samples[80];
        assert!((plane.depth_at(far.0, far.1) - far.2 as f64).abs() < 1e-4);
    }

    /// A box's face at 0.6 m and, right of its edge, a neighbour's face
    /// `behind` metres deeper at the edge, turned `steepness` degrees from
    /// face-on and going away, onto which the mask spilled `columns`
    /// columns: (cloud, what each point is).
    fn box_beside_a_neighbour(
        steepness: f64,
        behind: f64,
        columns: f64,
    ) -> (Vec<Point3>, Vec<Surface>) {
        let slope = steepness.to_radians().tan();
        sampled_in_image(columns * 0.002 / 0.6, |u| {
            if u < 0.0 {
                (0.6, Surface::Front)
            } else {
                ((0.6 + behind) / (1.0 - u * slope), Surface::Neighbour)
            }
        })
    }

    /// Points sampled evenly in the image (2 mm apart at 0.6 m; `u`, `v`:
    /// x/z and y/z) over u from -0.12 to `u_end` and v from -0.08 to 0.08,
    /// at the depth `surface_at(u)` gives (metres) with 1 mm noise.
    fn sampled_in_image(
        u_end: f64,
        surface_at: impl Fn(f64) -> (f64, Surface),
    ) -> (Vec<Point3>, Vec<Surface>) {
        let mut rng = crate::rng::SplitMix64::new(11);
        let (mut cloud, mut what) = (Vec::new(), Vec::new());
        let count = ((u_end + 0.12) * 0.16 / (0.002f64 / 0.6).powi(2)) as usize;
        for _ in 0..count {
            let u = -0.12 + (u_end + 0.12) * rng.next_f64();
            let v = -0.08 + 0.16 * rng.next_f64();
            let (z, surface) = surface_at(u);
            let z = z + 0.001 * (rng.next_f64() + rng.next_f64() + rng.next_f64() - 1.5) * 2.0;
            cloud.push([(u * z) as f32, (v * z) as f32, z as f32]);
            what.push(surface);
        }
        (cloud, what)
    }

    /// The share of each of `surfaces` that `segment` keeps of `cloud`
    /// (diameter 0.2 m), without and with step 3.
    fn kept_shares<const N: usize>(
        cloud: &[Point3],
        what: &[Surface],
        surfaces: [Surface; N],
    ) -> [[f64; N]; 2] {
        [false, true].map(|steep_faces| {
            let settings = SegmentSettings {
                steep_faces,
                ..SegmentSettings::default()
            };
            let keep = segment(cloud, 0.2, &settings).keep;
            surfaces.map(|surface| {
                let on: Vec<bool> = (0..cloud.len())
                    .filter(|&i| what[i] == surface)
                    .map(|i| keep[i])
                    .collect();
                on.iter().filter(|&&k| k).count() as f64 / on.len() as f64
            })
        })
    }

    #[derive(Clone, Copy, Debug, PartialEq)]
    enum Surface {
        Front,
        Side,
        Wall,
        Neighbour,
    }

    #[test]
    fn a_steep_face_is_put_back_and_the_wall_beside_it_is_not() {
        // Without step 3 most of a side seen 80° or more from face-on is
        // cut away; with it most of it is kept up to 80°, and much more of
        // it at 85°. The wall strip the mask spilled onto (some of which
        // steps 1 and 2 keep as a component) does not grow.
        for (steepness, least) in [(75.0, 0.7), (80.0, 0.6), (85.0, 0.3)] {
            let (cloud, what) = box_with_a_steep_side(steepness, 0.7, 4.0);
            let [[_, side_before, wall_before], [front, side, wall]] = kept_shares(
                &cloud,
                &what,
                [Surface::Front, Surface::Side, Surface::Wall],
            );
            assert!(front >= 0.99, "{steepness}°: front {front}");
            assert!(
                side >= least && side >= side_before + 0.2,
                "{steepness}°: side {side_before} -> {side}"
            );
            assert!(
                wall <= wall_before,
                "{steepness}°: wall {wall_before} -> {wall}"
            );
        }
    }

    #[test]
    fn spill_onto_a_neighbour_touching_the_edge_is_not_put_back() {
        // A neighbour's face 1 cm behind the box's edge, 60° from face-on:
        // its depth ramp meets the edge as a steep face of the box would.
        // Steps 1 and 2 drop (much of) it as a whole component in the box's
        // shadow; step 3 only puts back outliers and fragments below the
        // size floor, so most of it stays out (before that rule, all 4
        // columns and 95 % of 8 came back).
        for (columns, most) in [(4.0, 0.25), (8.0, 0.05)] {
            let (cloud, what) = box_beside_a_neighbour(60.0, 0.01, columns);
            let [[neighbour_before], [neighbour]] =
                kept_shares(&cloud, &what, [Surface::Neighbour]);
            assert!(
                neighbour <= neighbour_before + most,
                "{columns} columns: neighbour {neighbour_before} -> {neighbour}"
            );
        }
    }

    #[test]
    fn an_object_cut_in_two_by_an_occluder_keeps_both_parts() {
        let object = plane(0.6, 0.002, (-0.05, 0.05), (-0.05, 0.05), |x, _| {
            x.abs() < 0.01
        });
        let keep = segment(&object, 0.14, &SegmentSettings::default()).keep;
        assert!(keep.iter().all(|&k| k));
    }

    #[test]
    fn a_recessed_part_inside_the_silhouette_is_kept() {
        // A can seen from above: a 1.5 cm rim ring at 0.6 m around a lid 1 cm deeper.
        let rim = plane(0.6, 0.002, (-0.05, 0.05), (-0.05, 0.05), |x, y| {
            x.abs() < 0.035 && y.abs() < 0.035
        });
        let lid = plane(0.61, 0.002, (-0.034, 0.034), (-0.034, 0.034), |_, _| false);
        let cloud: Vec<Point3> = rim.iter().chain(&lid).copied().collect();
        let keep = segment(&cloud, 0.14, &SegmentSettings::default()).keep;
        assert!(
            keep.iter().all(|&k| k),
            "{} of {} kept",
            keep.iter().filter(|&&k| k).count(),
            keep.len()
        );
    }

    #[test]
    fn a_distant_blob_is_dropped() {
        let object = plane(0.6, 0.002, (-0.05, 0.05), (-0.05, 0.05), |_, _| false);
        let far = plane(0.6, 0.002, (0.3, 0.34), (0.0, 0.04), |_, _| false);
        let cloud: Vec<Point3> = object.iter().chain(&far).copied().collect();
        let keep = segment(&cloud, 0.14, &SegmentSettings::default()).keep;
        assert!(
            keep[..object.len()].iter().all(|&k| k) && keep[object.len()..].iter().all(|&k| !k)
        );
    }

    #[test]
    fn tiny_clouds_are_kept_whole() {
        let cloud = vec![[0.0f32, 0.0, 0.5]; 10];
        assert_eq!(
            segment(&cloud, 0.1, &SegmentSettings::default()).keep,
            vec![true; 10]
        );
    }

    /// Points on the faces of a 10 × 6 × 4 cm box at 0.6 m, at random.
    fn random_box_surface(count: usize, seed: u64) -> Vec<Point3> {
        let mut rng = crate::rng::SplitMix64::new(seed);
        let half = [0.05f32, 0.03, 0.02];
        (0..count)
            .map(|_| {
                let axis = (rng.next_f64() * 3.0) as usize % 3;
                let mut p: Point3 =
                    std::array::from_fn(|k| (rng.next_f64() as f32 * 2.0 - 1.0) * half[k]);
                p[axis] = if rng.next_f64() < 0.5 {
                    -half[axis]
                } else {
                    half[axis]
                };
                p[2] += 0.6;
                p
            })
            .collect()
    }

    #[test]
    fn the_grid_finds_every_pair_within_reach_once() {
        let cloud = random_box_surface(600, 3);
        let within = 0.006f32;
        let labels: Vec<usize> = (0..cloud.len())
            .map(|i| (cloud[i][0] > 0.01) as usize)
            .collect();
        let grid = CellGrid::new(&cloud, within);
        for labels in [None, Some(&labels[..])] {
            let mut found = Vec::new();
            let add = |i: usize, near: &[u32]| {
                found.extend(near.iter().map(|&j| (i.min(j as usize), i.max(j as usize))));
            };
            match labels {
                Some(labels) => grid.for_each_near(within, labels, add),
                None => grid.for_each_neighbourhood(within, add),
            }
            let mut expected = Vec::new();
            for i in 0..cloud.len() {
                for j in i + 1..cloud.len() {
                    let d: f32 = (0..3).map(|a| (cloud[i][a] - cloud[j][a]).powi(2)).sum();
                    if d <= within * within && labels.is_none_or(|l| l[i] != l[j]) {
                        expected.push((i, j));
                    }
                }
            }
            let count = found.len();
            found.sort_unstable();
            found.dedup();
            assert_eq!(found.len(), count, "a pair was visited twice");
            assert_eq!(found, expected);
        }
    }

    #[test]
    fn partners_near_a_point_are_the_same_eight_at_a_time_as_one_at_a_time() {
        let cloud = random_box_surface(61, 5);
        let grid = CellGrid::new(&cloud, 1.0);
        for (end, p) in [(61, cloud[0]), (16, cloud[7]), (7, cloud[3]), (0, cloud[1])] {
            let mut partners = Partners::default();
            partners.extend(&grid, 0, end);
            partners.pad();
            // A limit exactly at the middle point's squared distance: it is near.
            let middle = end / 2;
            let exact = (grid.xs[middle] - p[0]) * (grid.xs[middle] - p[0])
                + (grid.ys[middle] - p[1]) * (grid.ys[middle] - p[1])
                + (grid.zs[middle] - p[2]) * (grid.zs[middle] - p[2]);
            for start in [0, 1, 3, end].map(|s| s.min(end)) {
                for limit in [0.0, 1e-4, exact, 1.0] {
                    let (mut fast, mut slow) = (vec![0; end + LANES], vec![0; end + LANES]);
                    let count = partners.near(start, p, limit, &mut fast);
                    let expected = partners.near_one_at_a_time(start, p, limit, &mut slow);
                    assert_eq!(
                        fast[..count],
                        slow[..expected],
                        "from {start} within {limit}"
                    );
                    if limit == exact && start <= middle && middle < end {
                        assert!(fast[..count].contains(&grid.order[middle]));
                    }
                }
            }
        }
    }

    #[test]
    fn the_grid_median_spacing_is_the_kd_trees() {
        let line: Vec<Point3> = (0..300).map(|i| [0.001 * i as f32, 0.0, 0.5]).collect();
        let plane = plane(0.6, 0.002, (-0.05, 0.05), (-0.05, 0.05), |_, _| false);
        for cloud in [random_box_surface(2048, 5), plane, line] {
            let tree = median_of(&sampled_spacings(
                &ModelTree::new_from_slice(&cloud),
                &cloud,
            ));
            assert_eq!(median_spacing(&cloud), tree);
        }
    }

    #[test]
    fn the_hull_of_a_blob_holds_every_point_and_only_its_corners() {
        let mut rng = crate::rng::SplitMix64::new(11);
        let blob: Vec<[f64; 2]> = (0..500)
            .map(|_| {
                let (r, a) = (
                    rng.next_f64().sqrt(),
                    rng.next_f64() * std::f64::consts::TAU,
                );
                [r * a.cos(), 0.5 * r * a.sin()]
            })
            .collect();
        let hull = convex_hull(blob.clone());
        assert!(hull.len() >= 8 && hull.iter().all(|c| blob.contains(c)));
        assert!(blob.iter().all(|&p| inside_convex(&hull, p)));
        // Every corner is strictly convex (a left turn).
        for k in 0..hull.len() {
            let (o, a, b) = (
                hull[k],
                hull[(k + 1) % hull.len()],
                hull[(k + 2) % hull.len()],
            );
            assert!((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]) > 0.0);
        }
    }
}
