//! Point-pair features (Drost et al., CVPR 2010): pose hypotheses voted for
//! by pairs of oriented surface points. Each pair's feature (distance, and
//! the angles between the normals and the line joining the points) is
//! local, so a hidden part of the object removes votes without moving the
//! right pose's peak, unlike a view code computed from the whole visible
//! map. [`PairTable`] is built once per model; [`pair_poses`] votes with an
//! observed cloud and returns the strongest distinct poses (model frame →
//! camera, metres), which the caller verifies like any other candidate.

use std::num::NonZero;
use std::sync::LazyLock;

use kiddo::immutable::float::kdtree::ImmutableKdTree;
use kiddo::SquaredEuclidean;
use nalgebra::{Matrix3, Rotation3, SymmetricEigen, Unit, Vector3};
use rayon::prelude::*;

use crate::index::Pose;
use crate::sampling::farthest_point_sample;
use crate::threads;
use crate::Point3;

/// The model's points that take part (its first farthest-point samples:
/// evenly spread, ~0.05 diameters apart on a compact object, as Drost's
/// sampling), and so the size of the vote accumulator per reference point.
pub const MODEL_POINTS: usize = 384;
/// Distance bins per diameter (Drost: 0.05 d steps).
pub const DISTANCE_BINS: usize = 20;
/// Bins of each of the three feature angles over 0–180°: 12° steps, coarse
/// because the normals of a noisy depth cloud are several degrees off.
pub const FEATURE_ANGLE_BINS: usize = 15;
/// Bins of the rotation about the reference normal, over 360° (12°).
pub const ROTATION_BINS: usize = 30;
/// Cosines of the inner edges of the feature-angle bins, k·180°/bins for
/// k = 1..bins−1 (an angle past edge k has a cosine below it).
static ANGLE_EDGES: LazyLock<[f64; FEATURE_ANGLE_BINS - 1]> = LazyLock::new(|| {
    std::array::from_fn(|k| {
        ((k + 1) as f64 * std::f64::consts::PI / FEATURE_ANGLE_BINS as f64).cos()
    })
});
/// Distinct quantised features.
const FEATURE_KEYS: usize =
    DISTANCE_BINS * FEATURE_ANGLE_BINS * FEATURE_ANGLE_BINS * FEATURE_ANGLE_BINS;
/// A feature bin holds at most this many model pairs (evenly thinned): the
/// pairs of one plane or one cylinder share a handful of bins and carry
/// little information about where the object is, but they would take most
/// of the voting time and drown out the pairs across edges.
pub const MAX_PAIRS_PER_BIN: usize = 48;

/// Tuning of [`pair_poses`].
#[derive(Clone, Debug)]
pub struct PairSettings {
    /// Observed points (farthest-point samples of the cloud) that vote.
    pub scene_points: usize,
    /// Of those, every n-th is a reference point.
    pub reference_stride: usize,
    /// Neighbours that fit an observed point's normal.
    pub normal_neighbours: usize,
    /// Poses kept per reference point (its accumulator's best cells).
    pub peaks_per_reference: usize,
    /// Poses closer than this in rotation (degrees) and ...
    pub cluster_deg: f64,
    /// ... this in translation (× diameter) join one cluster.
    pub cluster_distance: f64,
    /// Clusters returned, most votes first.
    pub poses: usize,
}

impl Default for PairSettings {
    fn default() -> Self {
        Self {
            scene_points: 160,
            reference_stride: 2,
            normal_neighbours: 12,
            peaks_per_reference: 2,
            cluster_deg: 15.0,
            cluster_distance: 0.1,
            poses: 8,
        }
    }
}

/// A pose hypothesis and the votes behind it.
#[derive(Clone, Debug)]
pub struct VotedPose {
    pub pose: Pose,
    pub votes: f64,
}

/// The model's pairs, hashed by their quantised feature (model frame).
pub struct PairTable {
    points: Vec<Vector3<f64>>,
    /// Rotation taking each point's normal onto +x.
    to_x: Vec<Rotation3<f64>>,
    distance_step: f64,
    /// Feature key `k`'s pairs are `entries[starts[k]..starts[k + 1]]`.
    starts: Vec<u32>,
    /// (reference model point, its pair's turn bin about the normal).
    entries: Vec<(u16, u16)>,
}

impl PairTable {
    /// Pairs of the first [`MODEL_POINTS`] of `points` (with `normals`,
    /// unit, outward): built on the first second search, not at onboarding.
    pub fn new(points: &[Point3], normals: &[Point3]) -> Self {
        let m = points.len().min(MODEL_POINTS);
        let pts: Vec<Vector3<f64>> = points[..m].iter().map(vector).collect();
        let nrm: Vec<Vector3<f64>> = normals[..m].iter().map(|n| unit_or_z(vector(n))).collect();
        let to_x: Vec<Rotation3<f64>> = nrm.iter().map(rotation_to_x).collect();
        let diameter = pts
            .iter()
            .flat_map(|p| pts.iter().map(move |q| (p - q).norm()))
            .fold(0.0, f64::max);
        let distance_step = (diameter / DISTANCE_BINS as f64).max(1e-9);
        let mut keyed: Vec<(u32, u16, u16)> = threads::install(|| {
            (0..m)
                .into_par_iter()
                .flat_map_iter(|i| {
                    let (pts, nrm, to_x) = (&pts, &nrm, &to_x);
                    (0..m).filter(move |&j| j != i).filter_map(move |j| {
                        feature_key(&pts[i], &nrm[i], &pts[j], &nrm[j], distance_step).map(|key| {
                            let turn = turn_bin_about_x(&to_x[i], &pts[i], &pts[j]);
                            (key, i as u16, turn)
                        })
                    })
                })
                .collect()
        });
        keyed.sort_by_key(|e| e.0); // stable: (i, j) order within a key, as collected
        let mut starts = vec![0u32; FEATURE_KEYS + 1];
        let mut entries = Vec::new();
        for run in keyed.chunk_by(|a, b| a.0 == b.0) {
            let step = run.len().div_ceil(MAX_PAIRS_PER_BIN);
            entries.extend(run.iter().step_by(step).map(|e| (e.1, e.2)));
            starts[run[0].0 as usize + 1] = entries.len() as u32;
        }
        // Empty bins start where the previous one ended.
        for k in 1..starts.len() {
            starts[k] = starts[k].max(starts[k - 1]);
        }
        Self {
            points: pts,
            to_x,
            distance_step,
            starts,
            entries,
        }
    }

    /// Model pairs stored (after thinning).
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}

/// The strongest distinct poses (model frame → camera) of the model in
/// `cloud` (camera frame, metres; the camera at the origin orients the
/// normals), most votes first. Empty when the cloud has too few points.
pub fn pair_poses(table: &PairTable, cloud: &[Point3], settings: &PairSettings) -> Vec<VotedPose> {
    if cloud.len() < 8 || table.is_empty() {
        return Vec::new();
    }
    let picks = farthest_point_sample(cloud, settings.scene_points.min(cloud.len()));
    let (scene, normals) = oriented_points(cloud, &picks, settings.normal_neighbours);
    // A reference's cell gets a vote at most once per model pair of each of
    // its scene pairs (at most MAX_PAIRS_PER_BIN a pair's bin).
    let voted = if (scene.len() - 1) * MAX_PAIRS_PER_BIN <= u16::MAX as usize {
        vote::<u16>(table, &scene, &normals, settings)
    } else {
        vote::<u32>(table, &scene, &normals, settings)
    };
    cluster(voted, settings, table.distance_step * DISTANCE_BINS as f64)
}

/// A count of votes in the accumulator: `u16` when no cell can pass 65,535
/// (half the memory of `u32`, so a reference point's accumulator stays in
/// the core's first-level cache).
trait Votes: Copy + Ord + Default + Send + std::ops::AddAssign + Into<f64> {
    const ONE: Self;
}

impl Votes for u16 {
    const ONE: Self = 1;
}

impl Votes for u32 {
    const ONE: Self = 1;
}

/// Each reference point's best poses: its pairs with the other `scene`
/// points (with `normals`) vote in the `table` for a model point and a
/// turn about its normal, counted in `V`.
fn vote<V: Votes>(
    table: &PairTable,
    scene: &[Vector3<f64>],
    normals: &[Vector3<f64>],
    settings: &PairSettings,
) -> Vec<VotedPose> {
    let m = table.points.len();
    let max_distance = table.distance_step * DISTANCE_BINS as f64;
    let references: Vec<usize> = (0..scene.len())
        .step_by(settings.reference_stride.max(1))
        .collect();
    // Reference points vote on their own: in parallel (each pool thread
    // with an accumulator of its own), in order.
    let accumulator = || {
        (
            vec![V::default(); m * ROTATION_BINS],
            Vec::with_capacity(scene.len()),
        )
    };
    let votes_of = |(accumulator, runs): &mut (Vec<V>, Vec<(u32, u32, usize)>), r: &usize| {
        let r = *r;
        accumulator.fill(V::default());
        let to_x = rotation_to_x(&normals[r]);
        // Where each scene pair's model pairs lie in the table,
        // all read before any votes: the table's cache misses
        // overlap instead of waiting one after another.
        runs.clear();
        for i in 0..scene.len() {
            if i == r || (scene[i] - scene[r]).norm() > max_distance {
                continue;
            }
            let Some(key) = feature_key(
                &scene[r],
                &normals[r],
                &scene[i],
                &normals[i],
                table.distance_step,
            ) else {
                continue;
            };
            let (first, end) = (table.starts[key as usize], table.starts[key as usize + 1]);
            let scene_turn = turn_bin_about_x(&to_x, &scene[r], &scene[i]) as usize;
            runs.push((first, end, scene_turn));
        }
        for &(first, end, scene_turn) in runs.iter() {
            for &(model_ref, model_turn) in &table.entries[first as usize..end as usize] {
                // The turn taking the model pair onto the scene pair, in bins.
                let mut bin = scene_turn + ROTATION_BINS - model_turn as usize;
                if bin >= ROTATION_BINS {
                    bin -= ROTATION_BINS;
                }
                accumulator[model_ref as usize * ROTATION_BINS + bin] += V::ONE;
            }
        }
        best_cells(accumulator, settings.peaks_per_reference)
            .into_iter()
            .map(|(cell, votes)| {
                let (model_ref, bin) = (cell / ROTATION_BINS, cell % ROTATION_BINS);
                let turn = bin as f64 * std::f64::consts::TAU / ROTATION_BINS as f64;
                // s = to_x_sᵀ · Rx(turn) · to_x_m · (m − m_ref) + s_ref
                let rotation = to_x.inverse()
                    * Rotation3::from_axis_angle(&Vector3::x_axis(), turn)
                    * table.to_x[model_ref];
                let translation = scene[r] - rotation * table.points[model_ref];
                VotedPose {
                    pose: Pose {
                        rotation: *rotation.matrix(),
                        translation,
                    },
                    votes: votes.into(),
                }
            })
            .collect::<Vec<_>>()
    };
    if threads::on_this_thread() {
        let mut state = accumulator();
        references
            .iter()
            .flat_map(|r| votes_of(&mut state, r))
            .collect()
    } else {
        threads::install(|| {
            references
                .par_iter()
                .map_init(accumulator, votes_of)
                .flatten()
                .collect()
        })
    }
}

/// The accumulator's `count` best cells with at least one vote, (cell,
/// votes), best first (the lowest cell on ties). A pass for the maximum
/// and a search for its place per cell, both in vector lanes (AVX2 where
/// present: 8 lanes of u32 maxima, 16 of u16), unlike a running top-k.
fn best_cells<V: Votes>(accumulator: &mut [V], count: usize) -> Vec<(usize, V)> {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 is present (checked above).
        return unsafe { best_cells_avx2(accumulator, count) };
    }
    best_cells_in(accumulator, count)
}

/// [`best_cells`] compiled for AVX2; the same comparisons, so the same cells.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn best_cells_avx2<V: Votes>(accumulator: &mut [V], count: usize) -> Vec<(usize, V)> {
    best_cells_in(accumulator, count)
}

#[inline(always)]
fn best_cells_in<V: Votes>(accumulator: &mut [V], count: usize) -> Vec<(usize, V)> {
    let mut best = Vec::with_capacity(count);
    for _ in 0..count {
        let votes = accumulator.iter().copied().max().unwrap_or_default();
        if votes == V::default() {
            break;
        }
        let cell = first_of(accumulator, votes);
        best.push((cell, votes));
        accumulator[cell] = V::default();
    }
    best
}

/// The first place of `value` in `cells`, which holds it: a block of cells
/// is tested at once, without a branch per cell, before the cell is sought.
#[inline(always)]
fn first_of<V: Votes>(cells: &[V], value: V) -> usize {
    const BLOCK: usize = 32;
    let mut start = 0;
    for block in cells.chunks_exact(BLOCK) {
        if block.iter().fold(false, |hit, &v| hit | (v == value)) {
            break;
        }
        start += BLOCK;
    }
    start
        + cells[start..]
            .iter()
            .position(|&v| v == value)
            .expect("the value is in the cells")
}

/// Poses grouped greedily, most votes first: a pose within
/// `cluster_deg` and `cluster_distance` × `diameter` of a cluster's first
/// (strongest) pose adds its votes there. The `poses` clusters with the
/// most votes, each as its strongest pose.
fn cluster(mut voted: Vec<VotedPose>, settings: &PairSettings, diameter: f64) -> Vec<VotedPose> {
    voted.sort_by(|a, b| b.votes.total_cmp(&a.votes));
    let cos_max = settings.cluster_deg.to_radians().cos();
    let max_shift = settings.cluster_distance * diameter;
    // (strongest pose, votes, vote-weighted sum of translations)
    let mut clusters: Vec<(VotedPose, f64, Vector3<f64>)> = Vec::new();
    for v in voted {
        // The translations first: most clusters are elsewhere.
        let near = clusters.iter_mut().find(|(c, _, _)| {
            (c.pose.translation - v.pose.translation).norm() <= max_shift
                && ((c.pose.rotation.transpose() * v.pose.rotation).trace() - 1.0) / 2.0 >= cos_max
        });
        match near {
            Some((_, votes, sum)) => {
                *votes += v.votes;
                *sum += v.pose.translation * v.votes;
            }
            None => {
                let sum = v.pose.translation * v.votes;
                clusters.push((v.clone(), v.votes, sum));
            }
        }
    }
    clusters.sort_by(|a, b| b.1.total_cmp(&a.1));
    clusters.truncate(settings.poses);
    // A reference point lies up to half a model sample away from the model
    // point it voted for: the members' mean translation is nearer the truth.
    clusters
        .into_iter()
        .map(|(strongest, votes, sum)| VotedPose {
            pose: Pose {
                rotation: strongest.pose.rotation,
                translation: sum / votes,
            },
            votes,
        })
        .collect()
}

/// The picked points of `cloud` with unit normals fitted to their
/// `neighbours` nearest points (least-variance direction), turned to face
/// the camera at the origin.
fn oriented_points(
    cloud: &[Point3],
    picks: &[u32],
    neighbours: usize,
) -> (Vec<Vector3<f64>>, Vec<Vector3<f64>>) {
    let tree: ImmutableKdTree<f32, u32, 3, 32> = ImmutableKdTree::new_from_slice(cloud);
    let k = NonZero::new(neighbours.clamp(3, cloud.len())).expect("at least 3");
    picks
        .iter()
        .map(|&i| {
            let p = vector(&cloud[i as usize]);
            let near: Vec<Vector3<f64>> = tree
                .nearest_n::<SquaredEuclidean>(&cloud[i as usize], k)
                .iter()
                .map(|nn| vector(&cloud[nn.item as usize]))
                .collect();
            let mean = near.iter().sum::<Vector3<f64>>() / near.len() as f64;
            let scatter = near
                .iter()
                .map(|q| (q - mean) * (q - mean).transpose())
                .sum::<Matrix3<f64>>();
            let eigen = SymmetricEigen::new(scatter);
            let least = eigen.eigenvalues.imin();
            let mut n = unit_or_z(eigen.eigenvectors.column(least).into_owned());
            if n.dot(&p) > 0.0 {
                n = -n;
            }
            (p, n)
        })
        .unzip()
}

/// The quantised feature of the pair (p, q) with unit normals: distance and
/// the angles (n_p, d), (n_q, d), (n_p, n_q); None past [`DISTANCE_BINS`]
/// steps or for coincident points.
fn feature_key(
    p: &Vector3<f64>,
    n_p: &Vector3<f64>,
    q: &Vector3<f64>,
    n_q: &Vector3<f64>,
    distance_step: f64,
) -> Option<u32> {
    let d = q - p;
    let distance = d.norm();
    if !distance.is_finite() || distance <= 0.0 {
        return None; // coincident points, or NaN coordinates
    }
    let bin = (distance / distance_step) as usize;
    if bin >= DISTANCE_BINS {
        return None;
    }
    let dir = d / distance;
    // The angle's bin from its cosine: how many bin edges it lies past.
    let a = |cos: f64| ANGLE_EDGES.iter().filter(|&&edge| cos < edge).count() as u32;
    let n = FEATURE_ANGLE_BINS as u32;
    Some(((bin as u32 * n + a(n_p.dot(&dir))) * n + a(n_q.dot(&dir))) * n + a(n_p.dot(n_q)))
}

/// The bin (of [`ROTATION_BINS`] over 360°, centred on multiples of the
/// bin width) of an angle in radians.
#[cfg(test)]
fn turn_bin(angle: f64) -> u16 {
    let width = std::f64::consts::TAU / ROTATION_BINS as f64;
    ((angle / width).round() as i64).rem_euclid(ROTATION_BINS as i64) as u16
}

/// The bin edges of the half turn from +y to −y through +z: cosines and
/// sines of (k + ½) bin widths, k = 0..[`ROTATION_BINS`] / 2.
static TURN_EDGES: LazyLock<[[f64; ROTATION_BINS / 2]; 2]> = LazyLock::new(|| {
    let edge = |k: usize| (k as f64 + 0.5) * std::f64::consts::TAU / ROTATION_BINS as f64;
    [
        std::array::from_fn(|k| edge(k).cos()),
        std::array::from_fn(|k| edge(k).sin()),
    ]
});

/// The turn bin of `q` about the x axis once `p` is moved to the origin and
/// its normal onto +x by `to_x`: `turn_bin(angle_about_x(to_x, p, q))`,
/// from the bin edges the direction lies past instead of an arctangent
/// (the same bin but within ~1e-15 rad of an edge).
fn turn_bin_about_x(to_x: &Rotation3<f64>, p: &Vector3<f64>, q: &Vector3<f64>) -> u16 {
    let v = to_x * (q - p);
    turn_bin_of(v.y, v.z)
}

/// The bin of the direction (y, z) in the y–z plane, angles from +y
/// towards +z; −0 and +0 as `f64::atan2` takes them.
fn turn_bin_of(y: f64, z: f64) -> u16 {
    if y == 0.0 && z == 0.0 {
        // atan2(±0, +0) = ±0, atan2(±0, −0) = ±π.
        return if y.is_sign_negative() {
            (ROTATION_BINS / 2) as u16
        } else {
            0
        };
    }
    // Edges at or before the direction on its half turn (z's side; z = ±0
    // with y < 0 is the half turn itself, as atan2's ±π).
    let (across, [cos, sin]) = (z.abs(), &*TURN_EDGES);
    let mut past = 0;
    for k in 0..ROTATION_BINS / 2 {
        past += usize::from(cos[k] * across >= sin[k] * y);
    }
    if z >= 0.0 || past == 0 {
        past as u16
    } else {
        (ROTATION_BINS - past) as u16
    }
}

/// Angle (radians, −π..π) of `q` about the x axis once `p` is moved to the
/// origin and its normal onto +x by `to_x`.
#[cfg(test)]
fn angle_about_x(to_x: &Rotation3<f64>, p: &Vector3<f64>, q: &Vector3<f64>) -> f64 {
    let v = to_x * (q - p);
    v.z.atan2(v.y)
}

/// The rotation taking unit `n` onto +x (a half turn about z for −x).
fn rotation_to_x(n: &Vector3<f64>) -> Rotation3<f64> {
    Rotation3::rotation_between(n, &Vector3::x()).unwrap_or_else(|| {
        Rotation3::from_axis_angle(&Unit::new_normalize(Vector3::z()), std::f64::consts::PI)
    })
}

fn vector(p: &Point3) -> Vector3<f64> {
    Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64)
}

/// `v` normalised, or +z for a zero or non-finite vector.
fn unit_or_z(v: Vector3<f64>) -> Vector3<f64> {
    let norm = v.norm();
    if norm.is_finite() && norm > 1e-12 {
        v / norm
    } else {
        Vector3::z()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::refine::tests::{bracket, pose};
    use crate::rng::SplitMix64;

    /// The model's points that face a camera at the origin once posed by
    /// `truth` (a depth camera's view), and of those the ones with camera
    /// x below `keep_below_x` (the rest hidden by an occluder's edge).
    fn view(truth: &Pose, keep_below_x: f64) -> Vec<Point3> {
        let model = bracket();
        model
            .points
            .iter()
            .zip(&model.normals)
            .filter_map(|(p, n)| {
                let q = truth.apply(p);
                let normal = truth.rotation * vector(n);
                (normal.dot(&q) < 0.0 && q.x < keep_below_x)
                    .then_some([q.x as f32, q.y as f32, q.z as f32])
            })
            .collect()
    }

    fn errors(found: &Pose, truth: &Pose) -> (f64, f64) {
        let angle = Rotation3::from_matrix(&(found.rotation * truth.rotation.transpose())).angle();
        (
            angle.to_degrees(),
            (found.translation - truth.translation).norm(),
        )
    }

    fn table() -> PairTable {
        let model = bracket();
        PairTable::new(&model.points, &model.normals)
    }

    #[test]
    fn the_strongest_pose_is_the_true_one_on_a_whole_view() {
        let truth = pose(
            Vector3::new(0.3, -1.0, 0.5),
            2.0,
            Vector3::new(0.02, -0.01, 0.6),
        );
        let found = pair_poses(
            &table(),
            &view(&truth, f64::INFINITY),
            &PairSettings::default(),
        );
        let (deg, metres) = errors(&found[0].pose, &truth);
        // One bin of the turn is 12°, the model is sampled ~1 cm apart: ICP takes it from there.
        assert!(deg < 10.0 && metres < 0.012, "{deg}° {metres} m");
        assert!(found.windows(2).all(|w| w[0].votes >= w[1].votes));
    }

    #[test]
    fn half_the_object_hidden_still_votes_for_the_true_pose() {
        let truth = pose(
            Vector3::new(-0.7, 0.2, 1.0),
            1.1,
            Vector3::new(0.0, 0.03, 0.7),
        );
        let cloud = view(&truth, truth.translation.x);
        assert!(cloud.len() > 200);
        let found = pair_poses(&table(), &cloud, &PairSettings::default());
        let (deg, metres) = errors(&found[0].pose, &truth);
        assert!(deg < 10.0 && metres < 0.012, "{deg}° {metres} m");
    }

    #[test]
    fn the_best_cells_are_the_largest_lowest_first() {
        let mut rng = SplitMix64::new(3);
        for (len, top) in [(11_520, 40), (100, 3), (33, 1), (31, 5), (0, 1)] {
            let cells: Vec<u32> = (0..len)
                .map(|_| (rng.next_u64() % (top + 1)) as u32)
                .collect();
            for count in [0, 1, 2, 5] {
                // Sorted by votes (descending), then cell: the first `count` with votes.
                let mut expected: Vec<(usize, u32)> = cells
                    .iter()
                    .copied()
                    .enumerate()
                    .filter(|c| c.1 > 0)
                    .collect();
                expected.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
                expected.truncate(count);
                let mut accumulator = cells.clone();
                assert_eq!(
                    best_cells(&mut accumulator, count),
                    expected,
                    "{len} {count}"
                );
                let mut accumulator = cells.clone();
                assert_eq!(best_cells_in(&mut accumulator, count), expected);
                let mut narrow: Vec<u16> = cells.iter().map(|&v| v as u16).collect();
                let expected_narrow: Vec<(usize, u16)> =
                    expected.iter().map(|&(c, v)| (c, v as u16)).collect();
                assert_eq!(best_cells(&mut narrow, count), expected_narrow);
            }
        }
    }

    #[test]
    fn turn_bins_from_the_edges_are_the_arctangents_bins() {
        let mut rng = SplitMix64::new(11);
        let mut directions: Vec<(f64, f64)> = (0..100_000)
            .map(|_| {
                let angle = (rng.next_u64() as f64 / u64::MAX as f64 - 0.5) * std::f64::consts::TAU;
                let length = 1e-3 + rng.next_u64() as f64 / u64::MAX as f64;
                (length * angle.cos(), length * angle.sin())
            })
            .collect();
        // The axes and signed zeros, as atan2 takes them.
        for y in [0.0, -0.0, 1.0, -1.0] {
            for z in [0.0, -0.0, 1.0, -1.0] {
                directions.push((y, z));
            }
        }
        // Just either side of every bin edge.
        for k in 0..ROTATION_BINS {
            let edge = (k as f64 + 0.5) * std::f64::consts::TAU / ROTATION_BINS as f64;
            for off in [-1e-9, 1e-9] {
                directions.push(((edge + off).cos(), (edge + off).sin()));
            }
        }
        for (y, z) in directions {
            assert_eq!(turn_bin_of(y, z), turn_bin(z.atan2(y)), "({y}, {z})");
        }
    }

    #[test]
    fn narrow_and_wide_vote_counts_vote_alike() {
        let truth = pose(
            Vector3::new(0.2, 1.0, -0.4),
            0.9,
            Vector3::new(0.0, 0.0, 0.6),
        );
        let cloud = view(&truth, f64::INFINITY);
        let settings = PairSettings::default();
        let picks = farthest_point_sample(&cloud, settings.scene_points.min(cloud.len()));
        let (scene, normals) = oriented_points(&cloud, &picks, settings.normal_neighbours);
        let (narrow, wide) = (
            vote::<u16>(&table(), &scene, &normals, &settings),
            vote::<u32>(&table(), &scene, &normals, &settings),
        );
        assert!(!narrow.is_empty());
        assert_eq!(narrow.len(), wide.len());
        for (a, b) in narrow.iter().zip(&wide) {
            assert_eq!(
                (a.pose.rotation, a.pose.translation, a.votes),
                (b.pose.rotation, b.pose.translation, b.votes)
            );
        }
    }

    #[test]
    fn too_few_points_give_no_pose() {
        let cloud = vec![[0.0, 0.0, 0.5f32]; 5];
        assert!(pair_poses(&table(), &cloud, &PairSettings::default()).is_empty());
        let empty = PairTable::new(&[], &[]);
        assert!(empty.is_empty());
        let truth = pose(Vector3::x(), 0.5, Vector3::new(0.0, 0.0, 0.6));
        assert!(pair_poses(
            &empty,
            &view(&truth, f64::INFINITY),
            &PairSettings::default()
        )
        .is_empty());
    }

    #[test]
    fn a_pose_from_a_pair_maps_the_model_pair_onto_the_scene_pair() {
        // The frame construction alone: a model pair moved by a known pose
        // must give that pose back from the reference point and the turn.
        let truth = pose(
            Vector3::new(1.0, 2.0, -0.5),
            0.8,
            Vector3::new(0.1, 0.0, 0.5),
        );
        let (p, n) = (Vector3::new(0.01, 0.02, 0.03), Vector3::new(0.0, 0.6, 0.8));
        let q = Vector3::new(-0.02, 0.04, 0.0);
        let (sp, sn) = (truth.rotation * p + truth.translation, truth.rotation * n);
        let sq = truth.rotation * q + truth.translation;
        let (mx, sx) = (rotation_to_x(&n), rotation_to_x(&sn));
        let turn = angle_about_x(&sx, &sp, &sq) - angle_about_x(&mx, &p, &q);
        let rotation = sx.inverse() * Rotation3::from_axis_angle(&Vector3::x_axis(), turn) * mx;
        let translation = sp - rotation * p;
        let (deg, metres) = errors(
            &Pose {
                rotation: *rotation.matrix(),
                translation,
            },
            &truth,
        );
        assert!(deg < 1e-6 && metres < 1e-9, "{deg}° {metres} m");
    }
}
