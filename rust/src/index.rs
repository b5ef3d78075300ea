//! The model's surface with exact nearest-point look-ups, and rigid poses:
//! shared by verification ([`crate::search`]), scoring ([`crate::scoring`])
//! and ICP ([`crate::refine`]). An estimate asks for ~30,000 nearest model
//! points, nearly all near the surface: a grid of cells answers those
//! (ICP of 1,024 points × 20 iterations 2.8× faster than through the
//! kd-tree alone on the YCB models, with the same poses bit for bit), the
//! kd-tree the rest.

use std::num::NonZero;
use std::sync::{Arc, OnceLock};

use kiddo::immutable::float::kdtree::ImmutableKdTree;
use kiddo::SquaredEuclidean;
use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use crate::pairs::{pair_poses, PairSettings, PairTable, VotedPose};
use crate::threads;
use crate::Point3;

/// The model's kd-tree: leaves of 8 points, not kiddo's default 32. ICP,
/// scoring and verification query it tens of thousands of times per
/// estimate for points near the surface, where small leaves are faster
/// (`docs/tuning.md`, "The Rust core's constants"). Nearest neighbours are
/// exact whatever the leaf size.
pub(crate) type ModelTree = ImmutableKdTree<f32, u32, 3, 8>;

/// The model's points and normals with a kd-tree and grids of cells over
/// the points (model frame, metres), built once per codebook load.
/// Immutable, so many threads may query it at once.
pub struct ModelIndex {
    /// The kd-tree and cells depend on the points alone, so indexes of the
    /// same points with other normals share them ([`ModelIndex::with_normals`]).
    tree: Arc<ModelTree>,
    cells: Arc<CellIndex>,
    points: Vec<Point3>,
    normals: Vec<Point3>,
    /// Built on the first [`ModelIndex::pair_poses`]: only doubtful views
    /// ask for it, so loading a codebook does not pay for it.
    pairs: OnceLock<PairTable>,
}

/// A rigid transform `p_cam = rotation · p_model + translation` (metres).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    pub rotation: Matrix3<f64>,
    pub translation: Vector3<f64>,
}

impl Pose {
    pub fn inverse(&self) -> Pose {
        let rt = self.rotation.transpose();
        Pose {
            rotation: rt,
            translation: -(rt * self.translation),
        }
    }

    pub fn apply(&self, p: &Point3) -> Vector3<f64> {
        self.rotation * Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64) + self.translation
    }
}

impl ModelIndex {
    pub fn new(points: Vec<Point3>, normals: Vec<Point3>) -> Self {
        assert_eq!(points.len(), normals.len(), "one normal per point");
        let tree = ModelTree::new_from_slice(&points);
        let cells = CellIndex::new(&points, mean_spacing(&tree, &points), &tree);
        Self {
            tree: Arc::new(tree),
            cells: Arc::new(cells),
            points,
            normals,
            pairs: OnceLock::new(),
        }
    }

    /// The index of these points with other `normals` (one per point), sharing
    /// this one's kd-tree and cells: a codebook build searches symmetries with
    /// the model's normals and stores them rounded, over the same points.
    pub fn with_normals(&self, normals: Vec<Point3>) -> Self {
        assert_eq!(self.points.len(), normals.len(), "one normal per point");
        Self {
            tree: Arc::clone(&self.tree),
            cells: Arc::clone(&self.cells),
            points: self.points.clone(),
            normals,
            pairs: OnceLock::new(),
        }
    }

    /// The model's point-pair table ([`crate::pairs`]), built on first use.
    pub fn pair_table(&self) -> &PairTable {
        self.pairs
            .get_or_init(|| PairTable::new(&self.points, &self.normals))
    }

    /// Pose hypotheses (model frame → camera) voted for by point pairs of
    /// the observed `cloud` (camera frame, metres), most votes first.
    pub fn pair_poses(&self, cloud: &[Point3], settings: &PairSettings) -> Vec<VotedPose> {
        pair_poses(self.pair_table(), cloud, settings)
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The model's points, model frame, metres.
    pub fn points(&self) -> &[Point3] {
        &self.points
    }

    /// The model's unit outward normals, one per point.
    pub fn normals(&self) -> &[Point3] {
        &self.normals
    }

    /// Index and squared distance of the model point nearest to `p` (model
    /// frame). Exact: through the grid of cells for points near the model
    /// (ICP, scoring and verification ask almost only for those), through the
    /// kd-tree for points farther out.
    pub fn nearest(&self, p: &[f32; 3]) -> (usize, f32) {
        match self.cells.nearest(p, f64::INFINITY, &self.points) {
            Lookup::Found(i, squared) => (i, squared),
            Lookup::Beyond | Lookup::Unknown => self.nearest_in_tree(p),
        }
    }

    /// [`nearest`](Self::nearest) when that point lies within `max_distance`
    /// metres of `p` (`√squared ≤ max_distance`, in f64), None otherwise. Fast
    /// for points far from the model too: ICP, scoring and alignment ignore
    /// or truncate pairs beyond a distance, so they need not be found.
    pub fn nearest_within(&self, p: &[f32; 3], max_distance: f64) -> Option<(usize, f32)> {
        let lookup = self.cells.nearest(p, max_distance, &self.points);
        self.within(p, lookup, max_distance)
    }

    /// The grid's `lookup` of `p` as [`nearest_within`](Self::nearest_within)
    /// answers it: the kd-tree where the grid cannot tell.
    fn within(&self, p: &[f32; 3], lookup: Lookup, max_distance: f64) -> Option<(usize, f32)> {
        let (i, squared) = match lookup {
            Lookup::Found(i, squared) => (i, squared),
            Lookup::Beyond => return None,
            Lookup::Unknown => self.nearest_in_tree(p),
        };
        ((squared as f64).sqrt() <= max_distance).then_some((i, squared))
    }

    /// [`nearest_within`](Self::nearest_within) of each of `queries`, in
    /// order: the same answers, with the look-ups' memory loads overlapped
    /// (ICP asks for a whole cloud at once).
    pub fn nearest_each_within(
        &self,
        queries: &[Point3],
        max_distance: f64,
    ) -> Vec<Option<(usize, f32)>> {
        let mut found = Vec::with_capacity(queries.len());
        self.cells
            .nearest_each(queries, max_distance, &self.points, |p, lookup| {
                found.push(self.within(p, lookup, max_distance));
            });
        found
    }

    /// [`nearest`](Self::nearest) through the kd-tree alone.
    pub fn nearest_in_tree(&self, p: &[f32; 3]) -> (usize, f32) {
        let nn = self.tree.nearest_one::<SquaredEuclidean>(p);
        (nn.item as usize, nn.distance)
    }

    /// Indices of the `k` nearest model points to `p`, nearest first.
    pub fn nearest_k(&self, p: &[f32; 3], k: usize) -> Vec<usize> {
        let Some(k) = NonZero::new(k) else {
            return Vec::new();
        };
        self.tree
            .nearest_n::<SquaredEuclidean>(p, k)
            .into_iter()
            .map(|nn| nn.item as usize)
            .collect()
    }
}

/// Cells of the coarse grid are this many mean point spacings wide: a point
/// off the candidate lists' band finds its nearest model point within the
/// 27 cells around it (the width: `docs/tuning.md`, "The Rust core's constants").
const CELL_SPACINGS: f32 = 4.0;

/// Cells farther than this many rings around a query's cell are not
/// searched; the kd-tree answers such a query (far from the surface).
const MAX_RING: i32 = 2;

/// The grid reaches this fraction of the model's bounding-box diagonal
/// beyond the box: ICP, scoring and alignment never look farther than 0.1
/// diameters, so [`ModelIndex::nearest_within`] answers them all here.
const MARGIN_DIAGONALS: f64 = 0.15;

/// Model-frame points (metres, f64) as the f32 queries of a [`ModelIndex`].
pub(crate) fn as_queries(points: &[Vector3<f64>]) -> Vec<Point3> {
    points
        .iter()
        .map(|m| [m.x as f32, m.y as f32, m.z as f32])
        .collect()
}

/// What the grid knows about a query's nearest model point.
enum Lookup {
    /// Its index and squared distance (exact).
    Found(usize, f32),
    /// It lies farther than the asked distance.
    Beyond,
    /// The grid cannot tell cheaply: ask the kd-tree.
    Unknown,
}

/// Mean distance from a model point to its nearest other point (metres; at
/// least 1 µm), over [`sampled_spacings`].
fn mean_spacing(tree: &ModelTree, points: &[Point3]) -> f32 {
    let nearest = sampled_spacings(tree, points);
    ((nearest.iter().sum::<f64>() / nearest.len().max(1) as f64) as f32).max(1e-6)
}

/// Distance (metres) from each of an evenly spread sample of at most 256 of
/// `points` to its nearest other point, through `tree` (built on `points`):
/// the point spacing of a model or of an observed cloud.
pub(crate) fn sampled_spacings(tree: &ModelTree, points: &[Point3]) -> Vec<f64> {
    let two = NonZero::new(2).expect("2 > 0");
    let step = points.len().div_ceil(256).max(1);
    points
        .iter()
        .step_by(step)
        .filter_map(|p| {
            tree.nearest_n::<SquaredEuclidean>(p, two)
                .get(1)
                .map(|nn| (nn.distance as f64).sqrt())
        })
        .collect()
}

/// The model's points binned into a uniform grid of cubes (reaching
/// [`MARGIN_DIAGONALS`] beyond their bounding box), for exact
/// nearest-neighbour queries: a query near the surface scans its cell's
/// [`CandidateLists`] entry; one farther out the list of its cell of this
/// grid; one farther still searches the cells in rings of growing size
/// around its cell until no point outside them can be nearer;
/// one farther than the caller's cut-off is turned away by the cell's
/// clearance. The same answer as the kd-tree (ties aside), 2–3× sooner.
struct CellIndex {
    grid: Grid,
    /// Every model point lies farther than this from any point outside the
    /// grid, metres.
    margin: f64,
    /// Per cell, a lower bound of the distance from any point in it to the
    /// model, metres (0 for cells holding model points).
    clearance: Vec<f32>,
    /// Per cell, the model point nearest to its centre: a first guess that
    /// bounds the search (within half a cell diagonal of the true distance
    /// plus the centre's).
    anchor: Vec<u32>,
    /// Cell `c`'s points are `points[starts[c]..starts[c + 1]]`.
    starts: Vec<u32>,
    /// The model's points sorted by cell, with their model index.
    points: Vec<(Point3, u32)>,
    /// A finer grid over the model's bounding box whose cells near the
    /// surface list every model point that can be nearest to a point in
    /// them: one short scan answers most of ICP's queries.
    lists: CandidateLists,
    /// The same lists for this grid's own cells, out to [`FAR_BAND_CELLS`]:
    /// they answer the queries beyond the finer grid's band (a wrong
    /// candidate's keypoints, a far start of ICP) with one scan instead of
    /// the rings of cells.
    far: CandidateLists,
}

/// Cells of the coarse grid whose centre lies within this many cell sides
/// of the model get a candidate list.
const FAR_BAND_CELLS: f64 = 3.0;

/// Cells of [`CandidateLists`] are this many mean point spacings wide: short
/// lists, few cells (`docs/tuning.md`, "The Rust core's constants").
const LIST_SPACINGS: f32 = 1.0;

/// Cells of [`CandidateLists`] whose centre lies within this many cell sides
/// of the model get a list (the others hold none): far enough that few
/// look-ups search the coarse grid's rings (`docs/tuning.md`).
const LIST_BAND_CELLS: f64 = 4.0;

/// Most cells of the model's grids, whatever the requested side (a degenerate model).
const MAX_MODEL_CELLS: f64 = 1e6;

/// The smallest box holding the finite points of `points`, metres (both
/// corners at the origin when there are none).
pub(crate) fn bounds(points: &[Point3]) -> ([f32; 3], [f32; 3]) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in points.iter().filter(|p| p.iter().all(|v| v.is_finite())) {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    if lo[0] > hi[0] {
        return ([0.0; 3], [0.0; 3]);
    }
    (lo, hi)
}

/// The indices `0..keys.len()` sorted by key, stably (a counting sort), and
/// per bucket where its run starts in that order (`buckets + 1` entries:
/// bucket `k` holds `order[starts[k]..starts[k + 1]]`). Keys of `buckets`
/// or more come last, in no bucket.
pub(crate) fn counting_sort(keys: &[usize], buckets: usize) -> (Vec<u32>, Vec<u32>) {
    let mut starts = vec![0u32; buckets + 2];
    for &k in keys {
        starts[k.min(buckets) + 1] += 1;
    }
    let mut total = 0;
    for start in starts.iter_mut() {
        total += *start;
        *start = total;
    }
    let mut next = starts.clone();
    let mut order = vec![0u32; keys.len()];
    for (i, &k) in keys.iter().enumerate() {
        let k = k.min(buckets);
        order[next[k] as usize] = i as u32;
        next[k] += 1;
    }
    starts.truncate(buckets + 1);
    (order, starts)
}

/// A uniform grid of cubes over the box `[lo − margin, hi + margin]`
/// (metres): which cell holds a point, and where a cell's centre lies. At
/// most ~`max_cells` cells: the side grows when the requested one would give more.
#[derive(Clone, Copy)]
pub(crate) struct Grid {
    /// Corner of cell (0, 0, 0), metres.
    pub(crate) origin: [f32; 3],
    /// Cell side, metres.
    pub(crate) cell: f32,
    pub(crate) dims: [i32; 3],
}

impl Grid {
    pub(crate) fn new(lo: [f32; 3], hi: [f32; 3], cell: f32, margin: f64, max_cells: f64) -> Self {
        let volume: f64 = (0..3)
            .map(|a| (hi[a] - lo[a]) as f64 + 2.0 * margin + cell as f64)
            .product();
        let mut cell = cell.max((volume / max_cells).cbrt() as f32).max(1e-6);
        let origin = lo.map(|v| v - margin as f32);
        let cells_along = |cell: f32, a: usize| {
            ((hi[a] - origin[a]) as f64 + margin).div_euclid(cell as f64) + 1.0
        };
        // The volume bounds the count for a cube-like box only: a flat or
        // thin one (a degenerate cloud) needs larger cells to stay within it.
        while (0..3).map(|a| cells_along(cell, a)).product::<f64>() > 2.0 * max_cells
            && cell.is_finite()
        {
            cell *= 1.25;
        }
        let dims = std::array::from_fn(|a| cells_along(cell, a).max(1.0) as i32);
        Self { origin, cell, dims }
    }

    pub(crate) fn count(&self) -> usize {
        self.dims.iter().map(|&d| d as usize).product()
    }

    /// The indices of `points` sorted by cell and per cell where its run
    /// starts (see [`counting_sort`]). Points outside the grid (or not
    /// finite) come last, in no cell.
    pub(crate) fn bin(&self, points: &[Point3]) -> (Vec<u32>, Vec<u32>) {
        let count = self.count();
        let cell_of: Vec<usize> = points
            .iter()
            .map(|p| self.coordinates(p).map_or(count, |g| self.flat(g)))
            .collect();
        counting_sort(&cell_of, count)
    }

    /// The cell holding `p`, or None outside the grid.
    pub(crate) fn coordinates(&self, p: &[f32; 3]) -> Option<[i32; 3]> {
        let mut g = [0i32; 3];
        for (a, ga) in g.iter_mut().enumerate() {
            let v = (p[a] - self.origin[a]) / self.cell;
            // `v as i32` rounds towards zero: the floor for v ≥ 0.
            if !(v >= 0.0 && v < self.dims[a] as f32) {
                return None;
            }
            *ga = (v as i32).min(self.dims[a] - 1);
        }
        Some(g)
    }

    pub(crate) fn flat(&self, g: [i32; 3]) -> usize {
        ((g[0] * self.dims[1] + g[1]) * self.dims[2] + g[2]) as usize
    }

    /// The centre of cell `c` (a [`flat`](Self::flat) index), metres.
    fn centre(&self, c: usize) -> [f32; 3] {
        let g = self.unflat(c);
        std::array::from_fn(|a| self.origin[a] + (g[a] as f32 + 0.5) * self.cell)
    }

    /// The coordinates of cell `c` (a [`flat`](Self::flat) index).
    pub(crate) fn unflat(&self, c: usize) -> [i32; 3] {
        let d = self.dims;
        [
            c as i32 / (d[1] * d[2]),
            (c as i32 / d[2]) % d[1],
            c as i32 % d[2],
        ]
    }
}

/// Per cell of a grid around the model, the model points that
/// can be nearest to some point in the cell: those within `r + 2h` of its
/// centre, where `r` is the distance from the centre to its nearest model
/// point and `h` half the cell's diagonal (a point `q` of the cell has a
/// model point within `r + h`, so its nearest lies within `r + 2h` of the
/// centre). Cells farther than the band asked for from the model hold none,
/// and so does every cell of a model of more than 65,536 points (lists of
/// 16-bit indices).
struct CandidateLists {
    grid: Grid,
    /// Cell `c`'s list is `items[starts[c]..starts[c + 1]]` (empty: none).
    starts: Vec<u32>,
    items: Vec<u16>,
}

impl CandidateLists {
    /// Lists for the cells of `grid` (over the model's `points`, indexed by
    /// `tree`) whose centre lies within `band_cells` cell sides of the model.
    fn new(points: &[Point3], grid: Grid, band_cells: f64, tree: &ModelTree) -> Self {
        let (cell, dims, count) = (grid.cell, grid.dims, grid.count());
        let half_diagonal = 0.5 * 3f64.sqrt() * cell as f64;
        let band = band_cells * cell as f64;
        // Cells whose centre lies within `band` of some model point: its
        // centre is within `band + h` of that point's cell's centre, so their
        // offset (in cells) is at most that long, with slack for rounding
        // (the rest need no look-up).
        let mut near = vec![false; count];
        let limit = (band + half_diagonal) / cell as f64 + 0.01;
        let reach = limit.ceil() as i32;
        let offsets: Vec<[i32; 3]> = (-reach..=reach)
            .flat_map(|x| {
                (-reach..=reach).flat_map(move |y| (-reach..=reach).map(move |z| [x, y, z]))
            })
            .filter(|o| ((o[0] * o[0] + o[1] * o[1] + o[2] * o[2]) as f64) <= limit * limit)
            .collect();
        let short = points.len() <= 1 << 16; // indices fit 16 bits
        for p in points.iter().filter(|_| short) {
            let g = grid
                .coordinates(p)
                .expect("model points lie inside the grid");
            for o in &offsets {
                let at: [i32; 3] = std::array::from_fn(|a| g[a] + o[a]);
                if (0..3).all(|a| at[a] >= 0 && at[a] < dims[a]) {
                    near[grid.flat(at)] = true;
                }
            }
        }
        let lists: Vec<Vec<u16>> = threads::install(|| {
            (0..count)
                .into_par_iter()
                .map(|c| {
                    if !near[c] {
                        return Vec::new();
                    }
                    let centre = grid.centre(c);
                    let r = (tree.nearest_one::<SquaredEuclidean>(&centre).distance as f64).sqrt();
                    if r > band {
                        return Vec::new();
                    }
                    // Slack for rounding: a few more points, never one fewer.
                    let reach = (r + 2.0 * half_diagonal) * (1.0 + 1e-5) + 1e-6 * cell as f64;
                    let mut found =
                        tree.within_unsorted::<SquaredEuclidean>(&centre, (reach * reach) as f32);
                    if found.len() > RIVALS {
                        found.select_nth_unstable_by(RIVALS, |a, b| {
                            a.distance.total_cmp(&b.distance)
                        });
                    }
                    let rivals: Vec<u32> = found.iter().take(RIVALS).map(|nn| nn.item).collect();
                    let cell_box = CellBox::around(centre, cell, reach);
                    let mut items: Vec<u16> = found
                        .iter()
                        .filter(|nn| {
                            let j = nn.item;
                            rivals.iter().all(|&i| {
                                i == j
                                    || cell_box.can_beat(&points[j as usize], &points[i as usize])
                            })
                        })
                        .map(|nn| nn.item as u16) // `short`: every index fits
                        .collect();
                    items.sort_unstable();
                    items
                })
                .collect()
        });
        let mut starts = Vec::with_capacity(count + 1);
        starts.push(0u32);
        let mut items = Vec::with_capacity(lists.iter().map(Vec::len).sum());
        for list in lists {
            items.extend(list);
            starts.push(items.len() as u32);
        }
        Self {
            grid,
            starts,
            items,
        }
    }

    /// The list of `p`'s cell: empty outside the box or far from the model.
    fn of(&self, p: &[f32; 3]) -> &[u16] {
        let (a, b) = self.span_of(p);
        &self.items[a as usize..b as usize]
    }

    /// Where `p`'s list lies in `items` (empty outside the box).
    fn span_of(&self, p: &[f32; 3]) -> (u32, u32) {
        match self.grid.coordinates(p) {
            Some(g) => {
                let c = self.grid.flat(g);
                (self.starts[c], self.starts[c + 1])
            }
            None => (0, 0),
        }
    }

    /// The list of cell `c` (a [`Grid::flat`] index).
    fn at(&self, c: usize) -> &[u16] {
        &self.items[self.starts[c] as usize..self.starts[c + 1] as usize]
    }
}

/// A candidate list's point is tested against this many of the points
/// nearest to its cell's centre (see [`CellBox::can_beat`]).
const RIVALS: usize = 8;

/// A cell of [`CandidateLists`] grown a little for rounding, and the slack
/// of its tests (squared metres): what decides whether a model point can be
/// nearest to some point in the cell.
struct CellBox {
    lo: [f64; 3],
    hi: [f64; 3],
    slack: f64,
}

impl CellBox {
    /// The cell of side `cell` around `centre` (metres), whose lists reach
    /// `reach` metres from the centre.
    fn around(centre: [f32; 3], cell: f32, reach: f64) -> Self {
        let half = 0.5 * cell as f64 * (1.0 + 1e-4) + 1e-9;
        Self {
            lo: centre.map(|v| v as f64 - half),
            hi: centre.map(|v| v as f64 + half),
            // Far above the rounding of f32 squared distances up to `reach`.
            slack: 1e-5 * (reach + 3f64.sqrt() * half).powi(2),
        }
    }

    /// Whether model point `j` can be at least as near as point `i` to some
    /// point `q` of the box: `|q − j|² − |q − i|²` is linear in `q`, so its
    /// least value over the box lies at a corner. A point that cannot beat
    /// some other point is nearest to no point of the cell and leaves its
    /// list (ties and rounding kept in by the slack).
    fn can_beat(&self, j: &Point3, i: &Point3) -> bool {
        let mut least = 0.0;
        for a in 0..3 {
            let (ja, ia) = (j[a] as f64, i[a] as f64);
            let towards = ia - ja;
            let q = if towards >= 0.0 {
                self.lo[a]
            } else {
                self.hi[a]
            };
            least += 2.0 * q * towards + ja * ja - ia * ia;
        }
        least <= self.slack
    }
}

impl CellIndex {
    fn new(points: &[Point3], spacing: f32, tree: &ModelTree) -> Self {
        let cell = CELL_SPACINGS * spacing;
        let (lo, hi) = bounds(points);
        let diagonal = (0..3)
            .map(|a| ((hi[a] - lo[a]) as f64).powi(2))
            .sum::<f64>()
            .sqrt();
        let margin = MARGIN_DIAGONALS * diagonal;
        let grid = Grid::new(lo, hi, cell, margin, MAX_MODEL_CELLS);
        let count = grid.count();
        let (order, starts) = grid.bin(points);
        debug_assert_eq!(
            starts[count] as usize,
            points.len(),
            "model points lie inside the grid"
        );
        let sorted: Vec<([f32; 3], u32)> = order.iter().map(|&i| (points[i as usize], i)).collect();
        // From the cell's centre, minus half its diagonal (and some slack
        // for rounding), to the nearest model point.
        let half_diagonal = 0.5 * 3f64.sqrt() * grid.cell as f64;
        let (clearance, anchor) = threads::install(|| {
            (0..count)
                .into_par_iter()
                .map(|c| {
                    if points.is_empty() {
                        return (0.0, 0);
                    }
                    let nn = tree.nearest_one::<SquaredEuclidean>(&grid.centre(c));
                    if starts[c + 1] > starts[c] {
                        return (0.0, nn.item);
                    }
                    let nearest = (nn.distance as f64).sqrt();
                    let clearance =
                        (nearest - half_diagonal) * (1.0 - 1e-5) - 1e-6 * grid.cell as f64;
                    (clearance.max(0.0) as f32, nn.item)
                })
                .unzip()
        });
        Self {
            grid,
            margin: margin * (1.0 - 1e-6) - 1e-9,
            clearance,
            anchor,
            starts,
            points: sorted,
            far: CandidateLists::new(points, grid, FAR_BAND_CELLS, tree),
            lists: CandidateLists::new(
                points,
                Grid::new(lo, hi, LIST_SPACINGS * spacing, 0.0, MAX_MODEL_CELLS),
                LIST_BAND_CELLS,
                tree,
            ),
        }
    }

    /// The nearest of the `model`'s points to `p` and its squared distance,
    /// from `p`'s candidate list, or when it lies within [`MAX_RING`] rings of cells; [`Lookup::Beyond`] when every model
    /// point is surely farther than `max_distance` metres. Ties go to the
    /// lower model index.
    fn nearest(&self, p: &[f32; 3], max_distance: f64, model: &[Point3]) -> Lookup {
        if model.is_empty() {
            return Lookup::Unknown;
        }
        // A fine list answers first: its cells lie near the surface, where
        // the clearance below turns nothing away (a point it would turn
        // away is as far from its nearest point, which the caller drops).
        let fine = self.lists.of(p);
        if !fine.is_empty() {
            return nearest_in_list(p, fine, model);
        }
        self.nearest_off_lists(p, max_distance, model)
    }

    /// [`nearest`](Self::nearest) of each of `queries`, in order, handed to
    /// `answer(query, lookup)`. Most queries lie near the surface, where a
    /// look-up is two dependent memory loads (the cell's list, its items)
    /// that mostly miss the cache: where each query's list lies is read
    /// first for all of them, in a loop with no other work, so those loads
    /// overlap instead of waiting one after the other.
    fn nearest_each(
        &self,
        queries: &[Point3],
        max_distance: f64,
        model: &[Point3],
        mut answer: impl FnMut(&Point3, Lookup),
    ) {
        if model.is_empty() {
            return queries.iter().for_each(|p| answer(p, Lookup::Unknown));
        }
        let lists = &self.lists;
        let spans: Vec<(u32, u32)> = queries.iter().map(|p| lists.span_of(p)).collect();
        for (i, (p, &(a, b))) in queries.iter().zip(&spans).enumerate() {
            if let Some(&(ahead, _)) = spans.get(i + PREFETCH_AHEAD) {
                prefetch(&lists.items, ahead as usize);
            }
            let lookup = if a < b {
                nearest_in_list(p, &lists.items[a as usize..b as usize], model)
            } else {
                self.nearest_off_lists(p, max_distance, model)
            };
            answer(p, lookup);
        }
    }

    /// [`nearest`](Self::nearest) of a query whose cell holds no fine list.
    fn nearest_off_lists(&self, p: &[f32; 3], max_distance: f64, model: &[Point3]) -> Lookup {
        let grid = &self.grid;
        let Some(g) = grid.coordinates(p) else {
            return if max_distance < self.margin {
                Lookup::Beyond
            } else {
                Lookup::Unknown
            };
        };
        let c = grid.flat(g);
        if self.clearance[c] as f64 > max_distance {
            return Lookup::Beyond;
        }
        let far = self.far.at(c);
        if !far.is_empty() {
            return nearest_in_list(p, far, model);
        }
        // Distances from `p` to its cell's lower and upper walls, per axis:
        // a cell `k` cells away along an axis is at least `(k − 1)` cells
        // plus that wall away, and is skipped when farther than the nearest
        // point so far (or than `max_distance`: such a point is not wanted).
        let lower: [f32; 3] =
            std::array::from_fn(|a| p[a] - (grid.origin[a] + g[a] as f32 * grid.cell));
        let upper: [f32; 3] = std::array::from_fn(|a| grid.cell - lower[a]);
        let gap = |a: usize, k: i32| match k {
            0 => 0.0,
            k if k < 0 => lower[a] + (-k - 1) as f32 * grid.cell,
            k => upper[a] + (k - 1) as f32 * grid.cell,
        };
        let wanted = (max_distance * max_distance).min(f32::MAX as f64) as f32;
        let anchor = self.anchor[c];
        let mut best = (squared(p, &model[anchor as usize]), anchor);
        for ring in 0..=MAX_RING {
            let lo: [i32; 3] = std::array::from_fn(|a| (g[a] - ring).max(0));
            let hi: [i32; 3] = std::array::from_fn(|a| (g[a] + ring).min(grid.dims[a] - 1));
            for x in lo[0]..=hi[0] {
                let gx = gap(0, x - g[0]).powi(2);
                for y in lo[1]..=hi[1] {
                    let gxy = gx + gap(1, y - g[1]).powi(2);
                    if gxy > best.0.min(wanted) {
                        continue;
                    }
                    let inner_xy = (x - g[0]).abs() < ring && (y - g[1]).abs() < ring;
                    let mut z = lo[2];
                    while z <= hi[2] {
                        if inner_xy && (z - g[2]).abs() < ring {
                            z = g[2] + ring; // skip the rings already searched
                            continue;
                        }
                        if gxy + gap(2, z - g[2]).powi(2) <= best.0.min(wanted) {
                            let c = grid.flat([x, y, z]);
                            let (a, b) = (self.starts[c] as usize, self.starts[c + 1] as usize);
                            for &(q, item) in &self.points[a..b] {
                                let d = squared(p, &q);
                                if d < best.0 || (d == best.0 && item < best.1) {
                                    best = (d, item);
                                }
                            }
                        }
                        z += 1;
                    }
                }
            }
            // Any point not yet seen lies beyond the searched cube's walls
            // (or beyond the grid, which holds every model point).
            let mut clearance = f32::INFINITY;
            for (a, &ga) in g.iter().enumerate() {
                if ga - ring > 0 {
                    clearance = clearance.min(gap(a, -ring - 1));
                }
                if ga + ring < grid.dims[a] - 1 {
                    clearance = clearance.min(gap(a, ring + 1));
                }
            }
            if best.0 <= clearance * clearance {
                // The nearest point, unless a cell was skipped for lying
                // beyond `max_distance`: then so does the nearest point, and
                // this one is farther still (the caller checks).
                return Lookup::Found(best.1 as usize, best.0);
            }
            if clearance as f64 > max_distance {
                return Lookup::Beyond; // nothing unseen is near enough, nor the nearest seen
            }
        }
        Lookup::Unknown
    }
}

/// Queries ahead whose candidate list is asked for from memory while the
/// current one is answered: a list is a cache miss, and its query's answer
/// needs it before anything else.
const PREFETCH_AHEAD: usize = 8;

/// Asks the CPU to bring `items[at]` into its first-level cache (a hint:
/// nothing outside the slice is touched, nothing is read yet).
#[inline(always)]
fn prefetch<T>(items: &[T], at: usize) {
    #[cfg(target_arch = "x86_64")]
    if let Some(item) = items.get(at) {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        // SAFETY: SSE is part of x86_64; a prefetch of a valid address
        // changes no memory and cannot fault.
        unsafe { _mm_prefetch::<_MM_HINT_T0>((item as *const T).cast::<i8>()) };
    }
}

/// The nearest to `p` of the `model`'s points listed (ascending indices,
/// not empty) and its squared distance; ties go to the lower index.
fn nearest_in_list(p: &[f32; 3], list: &[u16], model: &[Point3]) -> Lookup {
    let mut best = (f32::INFINITY, u16::MAX);
    for &item in list {
        let d = squared(p, &model[item as usize]);
        if d < best.0 {
            best = (d, item); // ascending items: ties keep the lower
        }
    }
    Lookup::Found(best.1 as usize, best.0)
}

/// Squared distance, summed in kiddo's order (x, y, z): the same f32 value.
fn squared(a: &[f32; 3], b: &[f32; 3]) -> f32 {
    let mut d = 0.0f32;
    for k in 0..3 {
        d += (a[k] - b[k]) * (a[k] - b[k]);
    }
    d
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_point_that_cannot_beat_a_rival_is_nearest_to_no_point_of_the_cell() {
        let mut state = 11u64;
        let mut uniform = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let cell = 0.004f32;
        let cell_box = CellBox::around([0.0; 3], cell, 0.01);
        let (mut kept, mut dropped) = (0, 0);
        for _ in 0..2000 {
            let mut point = || {
                [
                    0.02 * uniform() - 0.01,
                    0.02 * uniform() - 0.01,
                    0.02 * uniform() - 0.01,
                ]
            };
            let (j, i) = (point(), point());
            // Some point of the cell (its corners and a lattice) nearer to j than to i?
            let mut beats = false;
            for a in 0..=4 {
                for b in 0..=4 {
                    for c in 0..=4 {
                        let q = [a, b, c].map(|k| (k as f32 / 4.0 - 0.5) * cell);
                        beats |= squared(&q, &j) <= squared(&q, &i);
                    }
                }
            }
            if beats {
                assert!(
                    cell_box.can_beat(&j, &i),
                    "{j:?} beats {i:?} somewhere in the cell"
                );
                kept += 1;
            } else if !cell_box.can_beat(&j, &i) {
                dropped += 1;
            }
        }
        assert!(
            kept > 100 && dropped > 100,
            "kept {kept}, dropped {dropped}"
        );
    }

    #[test]
    fn a_flat_or_thin_box_stays_within_the_cell_budget() {
        // Found by fuzzing: points 7 cm × 16 mm across but ~0 thick, with a
        // requested cell of ~0, asked for ~10^14 cells (an abort on allocation).
        let budget = 4096.0;
        for (hi, cell) in [
            ([0.07, 0.016, 1e-30], 1e-30),
            ([1.0, 1e-30, 1e-30], 1e-30),
            ([1e5, 1e5, 0.0], 1e-6),
            ([1.0, 1.0, 1.0], 1e-3),
        ] {
            let grid = Grid::new([0.0; 3], hi, cell, 0.0, budget);
            assert!(grid.dims.iter().all(|&d| d >= 1), "{hi:?}: {:?}", grid.dims);
            assert!(
                grid.count() as f64 <= 2.0 * budget,
                "{hi:?}: {:?}",
                grid.dims
            );
        }
        // Not finite: one cell, every point outside.
        let grid = Grid::new([0.0; 3], [f32::INFINITY, 1.0, 1.0], 0.01, 0.0, budget);
        assert!(grid.count() <= 2 * budget as usize);
    }
}
