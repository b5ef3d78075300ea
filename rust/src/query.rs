//! Stage 1 of `estimate`: an observed cloud (camera frame, metres) made
//! ready for the codebook, in two steps (after [`back_project`] when the
//! cloud comes from a depth image and a mask):
//!
//! 1. [`clean_cloud`]: the valid rows (finite, within `max_coordinate`),
//!    at most `max_points` of them (a seeded draw), without the points
//!    farther than a diameter from the median (segmentation leaks), and
//!    checked to span a plausible extent for the object;
//! 2. [`prepare_query`]: the points [`segment`] keeps as the object, turned
//!    so the ray through their centroid is the optical axis, and resampled
//!    to a map ([`normalize_to_map`]) whose first points, back in the camera
//!    frame, are the query's keypoints.
//!
//! Both run in one call each, without the GIL, for `estimate` and for the
//! threads of `estimate_many`.

use std::collections::HashSet;
use std::fmt;

use nalgebra::{Matrix3, Vector3};

use crate::maps::normalize_to_map;
use crate::rng::SplitMix64;
use crate::segment::{segment, SegmentSettings};
use crate::views::{ray_alignment, Rotation};
use crate::Point3;

/// Pinhole intrinsics, pixels: focal lengths and principal point (OpenCV:
/// pixel (row v, column u) has its centre at (u, v)).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pinhole {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

/// Camera-frame points (metres) of the pixels of a `width`-wide row-major
/// depth image whose `mask` flag is set and whose depth is measured (`depth
/// / depth_scale` finite and positive, metres) and whose point is finite,
/// in row-major order.
pub fn back_project<T: Copy + Into<f64>>(
    depth: &[T],
    mask: &[bool],
    width: usize,
    camera: &Pinhole,
    depth_scale: f64,
) -> Vec<[f64; 3]> {
    let Some(area) = flags_box(mask, width) else {
        return Vec::new();
    };
    let flags: usize = (area.top..area.bottom)
        .map(|v| {
            let row = &mask[v * width + area.left..v * width + area.right];
            row.iter().map(|m| *m as usize).sum::<usize>()
        })
        .sum();
    let mut points = Vec::with_capacity(flags);
    let lens = BoxLens::new(camera, width, &area, depth_scale);
    each_masked_pixel(depth, mask, &area, width, |_, u, row, d| {
        points.extend(lens.point(u, row, d));
    });
    points
}

/// `visit(pixel, u, row, depth)` for each flagged pixel of `area`: its
/// row-major index into `depth`, its column and row in the box, its depth.
fn each_masked_pixel<T: Copy>(
    depth: &[T],
    mask: &[bool],
    area: &MaskBox,
    width: usize,
    mut visit: impl FnMut(usize, usize, usize, T),
) {
    for v in area.top..area.bottom {
        let start = v * width + area.left;
        let span = start..v * width + area.right;
        for (u, (d, _)) in depth[span.clone()]
            .iter()
            .zip(&mask[span])
            .enumerate()
            .filter(|(_, (_, m))| **m)
        {
            visit(start + u, u, v - area.top, *d);
        }
    }
}

/// Back-projection of the pixels of a box of a `width`-wide image whose
/// top-left pixel is (`left`, `top`): the principal point shifted by that
/// corner, as the box cut out would have it.
struct BoxLens {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    width: usize,
    top: usize,
    left: usize,
    depth_scale: f64,
    /// `1 / fx`, `1 / fy`, `1 / depth_scale`: [`measured_within`](Self::measured_within)'s
    /// multiplications, where divisions would cost most of a pixel's time.
    reciprocals: [f64; 3],
}

impl BoxLens {
    fn new(camera: &Pinhole, width: usize, area: &MaskBox, depth_scale: f64) -> Self {
        Self {
            reciprocals: [1.0 / camera.fx, 1.0 / camera.fy, 1.0 / depth_scale],
            fx: camera.fx,
            fy: camera.fy,
            cx: camera.cx - area.left as f64,
            cy: camera.cy - area.top as f64,
            width,
            top: area.top,
            left: area.left,
            depth_scale,
        }
    }

    /// The point of the box's pixel (`u`, `row`) measured at `depth`; None
    /// without a measurement (`depth / depth_scale` not finite and
    /// positive) or when the point is not finite.
    fn point<T: Into<f64>>(&self, u: usize, row: usize, depth: T) -> Option<[f64; 3]> {
        let z = depth.into() / self.depth_scale;
        if !(z.is_finite() && z > 0.0) {
            return None;
        }
        let x = (u as f64 - self.cx) * z / self.fx;
        let y = (row as f64 - self.cy) * z / self.fy;
        // Absurd intrinsics or scale (fx of 1e-200) overflow: no point, as without depth.
        (x.is_finite() && y.is_finite()).then_some([x, y, z])
    }

    /// Whether the box's pixel (`u`, `row`) has a [`point`](Self::point)
    /// (None: no measurement) within `limit` of the camera on every axis:
    /// the same answer as `point(...).map(|p| within(&p, limit))`. Reciprocals
    /// stand for the divisions; the divisions decide only where the products
    /// land within a billionth of a bound, far more than their rounding.
    fn measured_within<T: Copy + Into<f64>>(
        &self,
        u: usize,
        row: usize,
        depth: T,
        limit: f64,
    ) -> Option<bool> {
        let d: f64 = depth.into();
        if d.is_nan() || d <= 0.0 {
            return None; // so is z = d / depth_scale: no measurement
        }
        let [fx, fy, scale] = self.reciprocals;
        let z = d * scale;
        let x = (u as f64 - self.cx) * z * fx;
        let y = (row as f64 - self.cy) * z * fy;
        if z >= 1e-300 && x.abs().max(y.abs()).max(z) < limit * (1.0 - 1e-9) {
            return Some(true);
        }
        self.point(u, row, depth).map(|p| within(&p, limit))
    }

    /// [`point`](Self::point) of `pixel`, a row-major index into the image.
    fn point_of_pixel<T: Into<f64>>(&self, pixel: usize, depth: T) -> Option<[f64; 3]> {
        let (u, row) = (
            pixel % self.width - self.left,
            pixel / self.width - self.top,
        );
        self.point(u, row, depth)
    }
}

/// The bounding box of a mask's set flags: rows `top..bottom`, columns `left..right`.
struct MaskBox {
    top: usize,
    bottom: usize,
    left: usize,
    right: usize,
}

/// The [`MaskBox`] of a `width`-wide row-major `mask`, or None when no flag is set.
fn flags_box(mask: &[bool], width: usize) -> Option<MaskBox> {
    if width == 0 {
        return None;
    }
    let mut found: Option<MaskBox> = None;
    for (v, flags) in mask.chunks_exact(width).enumerate() {
        // Without an early exit the test runs as vector operations: most rows have no flag.
        if flags.iter().fold(0u8, |any, m| any | *m as u8) == 0 {
            continue;
        }
        let first = flags.iter().position(|m| *m).unwrap_or(0);
        let last = flags.iter().rposition(|m| *m).unwrap_or(first);
        found = Some(match found {
            None => MaskBox {
                top: v,
                bottom: v + 1,
                left: first,
                right: last + 1,
            },
            Some(b) => MaskBox {
                bottom: v + 1,
                left: b.left.min(first),
                right: b.right.max(last + 1),
                ..b
            },
        });
    }
    found
}

/// Limits of [`clean_cloud`] (the Python layer's `edgepose.cloud` constants).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CleanSettings {
    /// At most this many points are kept (a seeded draw of the valid rows).
    pub max_points: usize,
    /// Seed of that draw: the same cloud always gives the same points.
    pub seed: u64,
    /// Fewer valid points than this cannot give a pose.
    pub min_points: usize,
    /// A coordinate larger than this (metres) marks its row as garbage.
    pub max_coordinate: f64,
    /// A cloud spanning more object diameters than this is not the object alone.
    pub max_extent_diameters: f64,
    /// A cloud spanning fewer object diameters than this holds no shape.
    pub min_extent_diameters: f64,
}

/// Why a cloud cannot give a pose; the message names the likely cause.
#[derive(Clone, Debug, PartialEq)]
pub enum CloudProblem {
    TooFewPoints {
        valid: usize,
        total: usize,
        needed: usize,
        max_coordinate: f64,
    },
    TooWide {
        extent: f64,
        diameter: f64,
    },
    TooSmall {
        extent: f64,
        diameter: f64,
    },
    /// The centroid is the camera centre: no ray to align.
    AtCameraCentre,
}

impl fmt::Display for CloudProblem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::TooFewPoints {
                valid,
                total,
                needed,
                max_coordinate,
            } => write!(
                f,
                "cloud has {valid} valid points of {total} (rows with NaN, inf or coordinates beyond \
                 {max_coordinate} m are dropped); at least {needed} are needed"
            ),
            Self::TooWide { extent, diameter } => write!(
                f,
                "cloud spans {extent:.3} m but the object is {diameter:.3} m across: \
                 is the cloud in millimetres, or not segmented?"
            ),
            Self::TooSmall { extent, diameter } => write!(
                f,
                "cloud spans only {extent:.3} m but the object is {diameter:.3} m across: \
                 do its points coincide, or is it in other units than metres?"
            ),
            Self::AtCameraCentre => write!(
                f,
                "cloud is centred on the camera centre (0, 0, 0): no viewing ray to align"
            ),
        }
    }
}

impl std::error::Error for CloudProblem {}

/// The points of a cloud of `total` rows (`row(i)`: row `i`, metres, camera
/// frame) that `estimate` matches against an object `diameter` metres
/// across; see the module's step 1. The rows are read twice and never
/// copied whole: memory stays bounded by `max_points`, whatever the cloud's size.
pub fn clean_cloud(
    total: usize,
    row: impl Fn(usize) -> [f64; 3],
    diameter: f64,
    settings: &CleanSettings,
) -> Result<Vec<Point3>, CloudProblem> {
    let limit = settings.max_coordinate;
    let valid = (0..total).filter(|&i| within(&row(i), limit)).count();
    check_count(valid, total, settings)?;
    let ranks = draw(valid, settings.max_points, settings.seed);
    let mut wanted = ranks.iter().peekable();
    let mut points: Vec<[f64; 3]> = Vec::with_capacity(ranks.len());
    let mut rank = 0;
    for i in 0..total {
        let p = row(i);
        if within(&p, limit) {
            if wanted.next_if_eq(&&rank).is_some() {
                points.push(p);
            }
            rank += 1;
        }
    }
    kept_near_median(points, diameter, settings)
}

/// [`clean_cloud`] of the cloud [`back_project`] makes of `mask` in
/// `depth`: the same points, each pixel's computed once and only the drawn
/// ones kept (a tracked frame keeps a thousand of tens of thousands).
pub fn clean_depth_cloud<T: Copy + Into<f64>>(
    depth: &[T],
    mask: &[bool],
    width: usize,
    camera: &Pinhole,
    depth_scale: f64,
    diameter: f64,
    settings: &CleanSettings,
) -> Result<Vec<Point3>, CloudProblem> {
    let Some(area) = flags_box(mask, width) else {
        return clean_cloud(0, |_| [0.0; 3], diameter, settings);
    };
    let lens = BoxLens::new(camera, width, &area, depth_scale);
    let limit = settings.max_coordinate;
    let (mut total, mut valid) = (0, Vec::new());
    each_masked_pixel(depth, mask, &area, width, |pixel, u, row, d| {
        if let Some(within) = lens.measured_within(u, row, d, limit) {
            total += 1;
            if within {
                valid.push(pixel);
            }
        }
    });
    check_count(valid.len(), total, settings)?;
    let points = draw(valid.len(), settings.max_points, settings.seed)
        .into_iter()
        .filter_map(|rank| lens.point_of_pixel(valid[rank], depth[valid[rank]]))
        .collect();
    kept_near_median(points, diameter, settings)
}

/// Whether every coordinate of `p` is within `limit` (false for NaN).
fn within(p: &[f64; 3], limit: f64) -> bool {
    p.iter().all(|c| c.abs() <= limit)
}

fn check_count(valid: usize, total: usize, settings: &CleanSettings) -> Result<(), CloudProblem> {
    if valid < settings.min_points {
        return Err(CloudProblem::TooFewPoints {
            valid,
            total,
            needed: settings.min_points,
            max_coordinate: settings.max_coordinate,
        });
    }
    Ok(())
}

/// The drawn `points` without those farther than a diameter from their
/// median (when enough remain), checked for the object's extent.
fn kept_near_median(
    mut points: Vec<[f64; 3]>,
    diameter: f64,
    settings: &CleanSettings,
) -> Result<Vec<Point3>, CloudProblem> {
    let median = [0, 1, 2].map(|k| median(points.iter().map(|p| p[k]).collect()));
    let near = |p: &[f64; 3]| distance(p, &median) <= diameter;
    if points.iter().filter(|p| near(p)).count() >= settings.min_points {
        points.retain(near);
    }
    let extent = (0..3)
        .map(|k| {
            let (lo, hi) = points
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
                    (lo.min(p[k]), hi.max(p[k]))
                });
            (hi - lo).powi(2)
        })
        .sum::<f64>()
        .sqrt();
    if extent > settings.max_extent_diameters * diameter {
        return Err(CloudProblem::TooWide { extent, diameter });
    }
    if extent < settings.min_extent_diameters * diameter {
        return Err(CloudProblem::TooSmall { extent, diameter });
    }
    Ok(points.iter().map(|p| p.map(|c| c as f32)).collect())
}

/// `count` distinct indices of `0..n` (all of them when `count >= n`),
/// drawn with `seed`, ascending. Floyd's algorithm: `count` draws, whatever `n`.
pub fn draw(n: usize, count: usize, seed: u64) -> Vec<usize> {
    if count >= n {
        return (0..n).collect();
    }
    if n / 64 <= 16 * count {
        // A bit per index: no hashing, and read out in order without a sort.
        // At most 16 words a draw, so memory stays bounded by `count` (what
        // `clean_cloud` promises, whatever the cloud's size); beyond, a hash set.
        let mut chosen = vec![0u64; n.div_ceil(64)];
        floyd(n, count, seed, |i| {
            let (word, bit) = (i / 64, 1u64 << (i % 64));
            let fresh = chosen[word] & bit == 0;
            chosen[word] |= bit;
            fresh
        });
        return chosen
            .iter()
            .enumerate()
            .flat_map(|(word, &bits)| {
                let mut bits = bits;
                std::iter::from_fn(move || {
                    (bits != 0).then(|| {
                        let bit = bits.trailing_zeros() as usize;
                        bits &= bits - 1;
                        word * 64 + bit
                    })
                })
            })
            .collect();
    }
    let mut chosen = HashSet::with_capacity(count);
    floyd(n, count, seed, |i| chosen.insert(i));
    let mut drawn: Vec<usize> = chosen.into_iter().collect();
    drawn.sort_unstable();
    drawn
}

/// Floyd's draw of `count` of `0..n` (`count < n`) into a set: `insert(i)`
/// adds `i` and says whether it was not there yet.
fn floyd(n: usize, count: usize, seed: u64, mut insert: impl FnMut(usize) -> bool) {
    let mut rng = SplitMix64::new(seed);
    for j in n - count..n {
        let t = ((rng.next_u64() as u128 * (j as u128 + 1)) >> 64) as usize; // uniform in 0..=j
        if !insert(t) {
            insert(j);
        }
    }
}

/// The median of `values` (the mean of the two middle ones for an even count;
/// `values` not empty).
pub(crate) fn median(mut values: Vec<f64>) -> f64 {
    let n = values.len();
    let (below, middle, _) = values.select_nth_unstable_by(n / 2, f64::total_cmp);
    let middle = *middle;
    if n % 2 == 1 {
        return middle;
    }
    let lower = below.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    0.5 * (lower + middle)
}

/// Median z of `points` (camera frame, metres; NaN for none) as numpy's
/// `np.median` of their float32 z gives it: the middle value, or for an
/// even count the two middle ones added and halved in float32.
pub fn median_depth(points: &[Point3]) -> f64 {
    let mut z: Vec<f32> = points.iter().map(|p| p[2]).collect();
    let n = z.len();
    if n == 0 {
        return f64::NAN;
    }
    let (below, middle, _) = z.select_nth_unstable_by(n / 2, f32::total_cmp);
    let middle = *middle;
    if n % 2 == 1 {
        return middle as f64;
    }
    let lower = below.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    ((lower + middle) / 2.0) as f64
}

fn distance(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>().sqrt()
}

/// Tuning of [`prepare_query`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct QuerySettings {
    /// How to find the object's points; None keeps every point.
    pub segment: Option<SegmentSettings>,
    /// The segmentation is used only when it keeps at least this many points.
    pub min_points: usize,
    /// Points of the map.
    pub map_points: usize,
    /// The map's first points that are the query's keypoints.
    pub keypoints: usize,
}

/// An observed cloud made ready for the codebook.
#[derive(Clone, Debug, PartialEq)]
pub struct Query {
    /// Camera-frame points kept as the object, metres.
    pub points: Vec<Point3>,
    /// Median distance between neighbouring points, metres (0 without segmentation).
    pub spacing: f64,
    /// Centroid of `points`, camera frame, metres.
    pub centroid: Vector3<f64>,
    /// Viewpoint correction: camera frame → frame whose +z is the centroid ray.
    pub r_corr: Rotation,
    /// The corrected, centred, scaled and resampled map.
    pub map: Vec<Point3>,
    /// The map's first `keypoints` points, back in the camera frame, metres.
    pub keypoints: Vec<Point3>,
    /// Median z of `points`, metres ([`median_depth`]).
    pub median_depth: f64,
}

/// Stage 1 on cleaned `points` ([`clean_cloud`]) of an object `diameter`
/// metres across whose maps are scaled by `scale`; see the module's step 2.
pub fn prepare_query(
    mut points: Vec<Point3>,
    diameter: f64,
    scale: f32,
    settings: &QuerySettings,
) -> Result<Query, CloudProblem> {
    let mut spacing = 0.0;
    if let Some(segment_settings) = &settings.segment {
        let found = segment(&points, diameter, segment_settings);
        spacing = found.spacing;
        if found.keep.iter().filter(|k| **k).count() >= settings.min_points {
            let mut keep = found.keep.iter();
            points.retain(|_| *keep.next().expect("one flag per point"));
        }
    }
    let sum = points.iter().fold(Vector3::zeros(), |s, p| {
        s + Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64)
    });
    let centroid = sum / points.len() as f64;
    let r_corr = ray_alignment(&centroid).ok_or(CloudProblem::AtCameraCentre)?;
    let corrected: Vec<Point3> = points
        .iter()
        .map(|p| {
            let q = r_corr * (Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64) - centroid);
            [q.x as f32, q.y as f32, q.z as f32]
        })
        .collect();
    let (map, _) = normalize_to_map(&corrected, scale, settings.map_points);
    let back: Matrix3<f32> = r_corr.transpose().cast();
    let origin: Vector3<f32> = centroid.cast();
    let keypoints = map
        .iter()
        .take(settings.keypoints)
        .map(|m| {
            let p = back * (Vector3::from(*m) / scale) + origin;
            [p.x, p.y, p.z]
        })
        .collect();
    Ok(Query {
        median_depth: median_depth(&points),
        points,
        spacing,
        centroid,
        r_corr,
        map,
        keypoints,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIMITS: CleanSettings = CleanSettings {
        max_points: 2048,
        seed: 0,
        min_points: 32,
        max_coordinate: 1e6,
        max_extent_diameters: 5.0,
        min_extent_diameters: 0.02,
    };

    /// A 10 cm square patch of `n` × `n` points at 0.6 m depth, off-axis.
    fn patch(n: usize) -> Vec<[f64; 3]> {
        (0..n * n)
            .map(|i| {
                let (a, b) = ((i % n) as f64 / n as f64, (i / n) as f64 / n as f64);
                [0.1 + 0.1 * a, -0.05 + 0.1 * b, 0.6 + 0.02 * a]
            })
            .collect()
    }

    fn cleaned(cloud: &[[f64; 3]], settings: &CleanSettings) -> Result<Vec<Point3>, CloudProblem> {
        clean_cloud(cloud.len(), |i| cloud[i], 0.15, settings)
    }

    #[test]
    fn a_depth_frame_cleans_to_the_points_of_its_back_projected_cloud() {
        // 120 × 90 px: a slanted surface, holes, a far leak and an absurd pixel, a ring-shaped mask.
        let (width, height) = (120usize, 90usize);
        let camera = Pinhole {
            fx: 100.0,
            fy: 101.0,
            cx: 60.3,
            cy: 44.8,
        };
        let depth: Vec<f64> = (0..width * height)
            .map(|i| match i % 97 {
                0 => 0.0,
                1 => f64::NAN,
                2 => 9000.0,
                3 => 2e9,
                _ => 600.0 + (i % width) as f64 * 0.5,
            })
            .collect();
        let mask: Vec<bool> = (0..width * height)
            .map(|i| {
                let (u, v) = ((i % width) as f64 - 55.0, (i / width) as f64 - 40.0);
                (15.0..35.0).contains(&(u * u + v * v).sqrt())
            })
            .collect();
        let limits = CleanSettings {
            max_points: 500,
            max_coordinate: 1e5,
            ..LIMITS
        };
        for settings in [
            limits,
            CleanSettings {
                max_points: 100_000,
                ..limits
            },
        ] {
            let cloud = back_project(&depth, &mask, width, &camera, 1000.0);
            let expected = clean_cloud(cloud.len(), |i| cloud[i], 0.3, &settings);
            let got = clean_depth_cloud(&depth, &mask, width, &camera, 1000.0, 0.3, &settings);
            assert_eq!(got, expected);
            assert!(got.unwrap().len() > 300);
        }
        let few = CleanSettings {
            min_points: 100_000,
            ..limits
        };
        let cloud = back_project(&depth, &mask, width, &camera, 1000.0);
        assert_eq!(
            clean_depth_cloud(&depth, &mask, width, &camera, 1000.0, 0.3, &few),
            clean_cloud(cloud.len(), |i| cloud[i], 0.3, &few)
        );
    }

    #[test]
    fn garbage_rows_and_a_far_leak_are_dropped_and_large_clouds_drawn_reproducibly() {
        let mut cloud = patch(20);
        cloud.push([f64::NAN, 0.0, 0.6]);
        cloud.push([0.0, 2e6, 0.6]);
        cloud.push([0.5, 0.5, 3.0]); // a leak several metres behind
        let points = cleaned(&cloud, &LIMITS).unwrap();
        assert_eq!(points.len(), 400);
        assert!(points.iter().all(|p| p[2] < 1.0));

        let big = patch(100);
        let drawn = cleaned(&big, &LIMITS).unwrap();
        assert_eq!(drawn.len(), 2048);
        assert_eq!(drawn, cleaned(&big, &LIMITS).unwrap());
        let distinct: HashSet<[u32; 3]> = drawn.iter().map(|p| p.map(f32::to_bits)).collect();
        assert_eq!(distinct.len(), 2048);
        let reseeded = cleaned(&big, &CleanSettings { seed: 1, ..LIMITS }).unwrap();
        assert_ne!(drawn, reseeded);
    }

    #[test]
    fn clouds_that_cannot_be_the_object_name_the_problem() {
        let few = &patch(20)[..31];
        assert!(matches!(
            cleaned(few, &LIMITS),
            Err(CloudProblem::TooFewPoints { valid: 31, .. })
        ));
        let millimetres: Vec<[f64; 3]> = patch(20).iter().map(|p| p.map(|c| c * 1000.0)).collect();
        assert!(matches!(
            cleaned(&millimetres, &LIMITS),
            Err(CloudProblem::TooWide { .. })
        ));
        let coincident = vec![[0.1, 0.0, 0.6]; 100];
        let problem = cleaned(&coincident, &LIMITS).unwrap_err();
        assert!(problem.to_string().contains("coincide"), "{problem}");
    }

    #[test]
    fn back_projection_keeps_measured_masked_pixels_in_row_major_order() {
        let camera = Pinhole {
            fx: 500.0,
            fy: 400.0,
            cx: 1.5,
            cy: 1.0,
        };
        let depth: Vec<u16> = vec![0, 1000, 1000, 2000, 800, 0, 1000, 1000, 500, 500, 500, 500];
        let mut mask = vec![false; 12];
        for i in [1, 3, 4, 5, 9] {
            mask[i] = true;
        }
        let points = back_project(&depth, &mask, 4, &camera, 1000.0);
        // pixel 5 has no depth; the rest in order 1, 3, 4, 9.
        assert_eq!(points.len(), 4);
        assert_eq!(
            points[0],
            [(1.0 - 1.5) * 1.0 / 500.0, (0.0 - 1.0) * 1.0 / 400.0, 1.0]
        );
        assert_eq!(points[1], [(3.0 - 1.5) * 2.0 / 500.0, -2.0 / 400.0, 2.0]);
        assert_eq!(points[2], [(0.0 - 1.5) * 0.8 / 500.0, 0.0, 0.8]);
        assert_eq!(points[3], [(1.0 - 1.5) * 0.5 / 500.0, 0.5 / 400.0, 0.5]);
        let nan_depth = [f32::NAN, -1.0, 0.5];
        assert_eq!(
            back_project(&nan_depth, &[true; 3], 3, &camera, 1.0).len(),
            1
        );
    }

    #[test]
    fn a_draw_by_bits_is_the_draw_by_hashing() {
        for (n, count, seed) in [
            (20_000, 1_024, 1),
            (1_025, 1_024, 3),
            (64, 63, 0),
            (100_000, 2_048, 7),
            (5, 1, 2),
        ] {
            let mut hashed = HashSet::new();
            floyd(n, count, seed, |i| hashed.insert(i));
            let mut hashed: Vec<usize> = hashed.into_iter().collect();
            hashed.sort_unstable();
            assert_eq!(draw(n, count, seed), hashed, "{n} {count}");
        }
        // Far more indices than draws: hashed, same rule.
        assert_eq!(draw(10_000_000, 3, 9).len(), 3);
    }

    #[test]
    fn a_pixel_is_measured_and_within_bounds_as_its_point_says() {
        let depths = [
            0.0,
            -1.0,
            f64::NAN,
            f64::INFINITY,
            1e-320,
            1e-300,
            1e-12,
            0.4,
            1.0,
            999.0,
            1000.0,
            1000.000001,
            4.0e3,
            1e300,
            f64::MAX,
        ];
        for (fx, fy, cx, cy) in [
            (500.0, 520.0, 3.5, 2.0),
            (1e-200, 1e-300, 0.0, 1.0),
            (1e300, 2.0, 1e10, -3.0),
        ] {
            for depth_scale in [1.0, 1000.0, 1e-300, 1e300, 3.0] {
                let camera = Pinhole { fx, fy, cx, cy };
                let area = MaskBox {
                    top: 1,
                    bottom: 4,
                    left: 2,
                    right: 9,
                };
                let lens = BoxLens::new(&camera, 16, &area, depth_scale);
                for limit in [1000.0, 1.0, 1e-6, f64::INFINITY] {
                    for u in 0..7 {
                        for row in 0..3 {
                            for d in depths {
                                assert_eq!(
                                    lens.measured_within(u, row, d, limit),
                                    lens.point(u, row, d).map(|p| within(&p, limit)),
                                    "u {u} row {row} d {d} scale {depth_scale} fx {fx} limit {limit}"
                                );
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn draws_are_distinct_ascending_reproducible_and_cover_small_sets() {
        let drawn = draw(10_000, 300, 5);
        assert_eq!(drawn.len(), 300);
        assert!(drawn.windows(2).all(|w| w[0] < w[1]) && drawn[299] < 10_000);
        assert_eq!(drawn, draw(10_000, 300, 5));
        assert_ne!(drawn, draw(10_000, 300, 6));
        assert_eq!(draw(4, 9, 0), vec![0, 1, 2, 3]);
        // Roughly uniform: each half of the range gets about half the draws.
        let low = draw(100_000, 5_000, 1)
            .iter()
            .filter(|&&i| i < 50_000)
            .count();
        assert!((2_300..2_700).contains(&low), "{low}");
    }

    #[test]
    fn median_of_odd_and_even_counts() {
        assert_eq!(median(vec![3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(vec![4.0, 1.0, 3.0, 2.0]), 2.5);
    }

    #[test]
    fn keypoints_are_the_map_back_in_the_camera_frame() {
        let points = cleaned(&patch(30), &LIMITS).unwrap();
        let settings = QuerySettings {
            segment: None,
            min_points: 32,
            map_points: 128,
            keypoints: 16,
        };
        let query = prepare_query(points.clone(), 0.15, 5.0, &settings).unwrap();
        assert_eq!((query.map.len(), query.keypoints.len()), (128, 16));
        let ray = query.r_corr * query.centroid.normalize();
        assert!((ray - Vector3::z()).norm() < 1e-9);
        for k in &query.keypoints {
            let nearest = points
                .iter()
                .map(|p| (0..3).map(|i| (p[i] - k[i]).powi(2)).sum::<f32>())
                .fold(f32::INFINITY, f32::min);
            assert!(nearest.sqrt() < 1e-5, "a keypoint {k:?} is no cloud point");
        }
    }
}
