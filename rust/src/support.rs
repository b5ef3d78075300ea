//! The surface an object stands on or in front of (a table, a wall), found
//! in the depth frame around the object's cloud, and the cloud's points on it.
//!
//! A detector's mask takes such points where it spills; where a table meets
//! the object there is no depth jump for the cloud's own segmentation
//! ([`crate::segment`]) to drop them by. Around the mask, the frame shows the
//! surface where the object cannot bias it.

use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use crate::query::{median, Pinhole};
use crate::rng::SplitMix64;
use crate::Point3;

/// How the support plane is looked for and when it is trusted.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SupportSettings {
    /// The frame's depth is read at one pixel per cell of this many pixels,
    /// in the cells more than 1 and at most 3 cells off those the cloud
    /// covers (6–12 px: past a
    /// detector's spill, on what lies around the object).
    pub cell_px: usize,
    /// Planes tried, each through 3 of those pixels (fixed draws) ...
    pub trials: usize,
    /// ... the best holding at least this share of them ...
    pub min_share: f64,
    /// ... within this distance of it, metres, or 0.01 × the diameter if larger.
    pub fit_tolerance: f64,
    /// A cloud point lies on the plane within 3 robust σ of the ring's own
    /// distances to it, or this, metres, if larger ...
    pub min_tolerance: f64,
    /// ... and the plane is a support when at least this share of the other
    /// points lies on the camera's side of it (the object stands on it or in
    /// front of it, not behind: an occluder's face, or the object's own face
    /// that a cut mask left outside, has the object behind it) ...
    pub in_front: f64,
    /// ... and at most this share of the cloud lies on it.
    pub max_share: f64,
}

impl Default for SupportSettings {
    fn default() -> Self {
        Self {
            cell_px: 4,
            trials: 256,
            min_share: 0.5,
            fit_tolerance: 0.003,
            min_tolerance: 0.002,
            in_front: 0.9,
            max_share: 0.5,
        }
    }
}

/// Least-squares refits of the best drawn plane to its ring points.
const REFITS: usize = 2;
/// Fewest measured ring pixels a plane is looked for in.
const MIN_RING_PIXELS: usize = 24;
/// Seed of the planes' fixed draws (the same every call).
const DRAW_SEED: u64 = 0x5EED_7AB1E;

/// Per point of `points` (camera frame, metres): whether it lies on the
/// support plane that the `width`-wide row-major `depth` image (`depth /
/// depth_scale` metres; not finite or ≤ 0: no measurement) shows around the
/// points' silhouette. All false when the surroundings show no such plane,
/// when the rest of the points do not stand on its camera side, or when
/// more than `settings.max_share` of them lie on it.
pub fn on_support_plane<T: Copy + Into<f64>>(
    points: &[Point3],
    depth: &[T],
    width: usize,
    camera: &Pinhole,
    depth_scale: f64,
    diameter: f64,
    settings: &SupportSettings,
) -> Vec<bool> {
    let none = vec![false; points.len()];
    let height = depth.len().checked_div(width).unwrap_or(0);
    let ring = match ring_points(points, depth, width, height, camera, depth_scale, settings) {
        Some(ring) => ring,
        None => return none,
    };
    let Some((centre, normal, spread)) =
        fit_plane(&ring, settings.fit_tolerance.max(0.01 * diameter), settings)
    else {
        return none;
    };
    let tolerance = (3.0 * spread).max(settings.min_tolerance);
    let heights: Vec<f64> = points
        .iter()
        .map(|p| (Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64) - centre).dot(&normal))
        .collect();
    let on: Vec<bool> = heights.iter().map(|h| h.abs() < tolerance).collect();
    let on_count = on.iter().filter(|&&o| o).count();
    let others = points.len() - on_count;
    let in_front = heights.iter().filter(|h| **h > tolerance).count();
    if on_count as f64 > settings.max_share * points.len() as f64
        || others == 0
        || (in_front as f64) < settings.in_front * others as f64
    {
        return none;
    }
    on
}

/// Camera-frame points (metres) of the measured pixels at the centres of the
/// cells more than 1 and at most 3 cells off those the points' projections
/// onto the image cover, row-major; None
/// when fewer than [`MIN_RING_PIXELS`].
fn ring_points<T: Copy + Into<f64>>(
    points: &[Point3],
    depth: &[T],
    width: usize,
    height: usize,
    camera: &Pinhole,
    depth_scale: f64,
    settings: &SupportSettings,
) -> Option<Vec<Vector3<f64>>> {
    if points.is_empty() || width == 0 || height == 0 {
        return None;
    }
    let cell = settings.cell_px.max(1);
    let (fx, fy) = (camera.fx as f32, camera.fy as f32);
    let pixels: Vec<(f64, f64)> = points
        .iter()
        .map(|p| {
            let z = (p[2] as f64).max(1e-6);
            (
                (p[0] * fx) as f64 / z + camera.cx,
                (p[1] * fy) as f64 / z + camera.cy,
            )
        })
        // Only points the image can show (a cloud cut from it: all).
        .filter(|(u, v)| (-1.0..=width as f64).contains(u) && (-1.0..=height as f64).contains(v))
        .collect();
    let (u_min, u_max, v_min, v_max) = pixels.iter().fold(
        (
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ),
        |(a, b, c, d), &(u, v)| (a.min(u), b.max(u), c.min(v), d.max(v)),
    );
    if !(u_min.is_finite() && u_max.is_finite() && v_min.is_finite() && v_max.is_finite()) {
        return None;
    }
    let pad = 4 * cell as i64;
    let (c0, r0) = ((u_min as i64 - pad).max(0), (v_min as i64 - pad).max(0));
    let c1 = (u_max as i64 + pad + 1).min(width as i64);
    let r1 = (v_max as i64 + pad + 1).min(height as i64);
    if r1 <= r0 || c1 <= c0 {
        return None;
    }
    let rows = ((r1 - r0) as usize).div_ceil(cell);
    let cols = ((c1 - c0) as usize).div_ceil(cell);
    let mut seen = vec![false; rows * cols];
    for &(u, v) in pixels
        .iter()
        .filter(|(u, v)| u.is_finite() && v.is_finite())
    {
        let r = (((v - r0 as f64) / cell as f64).floor() as i64).clamp(0, rows as i64 - 1) as usize;
        let c = (((u - c0 as f64) / cell as f64).floor() as i64).clamp(0, cols as i64 - 1) as usize;
        seen[r * cols + c] = true;
    }
    let (outer, inner) = (dilate(&seen, rows, cols, 3), dilate(&seen, rows, cols, 1));
    let mut ring = Vec::new();
    for r in 0..rows {
        for c in 0..cols {
            if !outer[r * cols + c] || inner[r * cols + c] {
                continue;
            }
            let pr = (r0 as usize + r * cell + cell / 2).min(height - 1);
            let pc = (c0 as usize + c * cell + cell / 2).min(width - 1);
            let z = depth[pr * width + pc].into() / depth_scale;
            if z.is_finite() && z > 0.0 {
                let x = (pc as f64 - camera.cx) * z / camera.fx;
                let y = (pr as f64 - camera.cy) * z / camera.fy;
                ring.push(Vector3::new(x, y, z));
            }
        }
    }
    (ring.len() >= MIN_RING_PIXELS).then_some(ring)
}

/// A `rows` × `cols` row-major grid of flags grown by a Euclidean disk of
/// `radius` cells.
fn dilate(flags: &[bool], rows: usize, cols: usize, radius: i64) -> Vec<bool> {
    // The disk's half-width on each row offset: a run of cells per row.
    let half: Vec<i64> = (-radius..=radius)
        .map(|dr| {
            (0..=radius)
                .take_while(|dc| dr * dr + dc * dc <= radius * radius)
                .count() as i64
                - 1
        })
        .collect();
    let (rows, cols) = (rows as i64, cols as i64);
    let mut out = vec![false; flags.len()];
    for r in 0..rows {
        for c in 0..cols {
            if !flags[(r * cols + c) as usize] {
                continue;
            }
            for (dr, &w) in (-radius..=radius).zip(&half) {
                let rr = r + dr;
                if (0..rows).contains(&rr) {
                    let (from, to) = ((c - w).max(0), (c + w).min(cols - 1));
                    out[(rr * cols + from) as usize..=(rr * cols + to) as usize].fill(true);
                }
            }
        }
    }
    out
}

/// The plane through 3 ring points that the most ring points lie within
/// `tolerance` of, refitted [`REFITS`] times to the ring points within
/// `tolerance` of it by their least-spread direction (None if fewer than 3
/// are): a
/// point on it, its unit normal towards the camera, and those points'
/// robust spread about it (1.4826 × the median absolute deviation of their
/// distances, metres); None when the best holds fewer than
/// `settings.min_share` of the ring.
fn fit_plane(
    ring: &[Vector3<f64>],
    tolerance: f64,
    settings: &SupportSettings,
) -> Option<(Vector3<f64>, Vector3<f64>, f64)> {
    let n = ring.len();
    let mut draws = SplitMix64::new(DRAW_SEED);
    let mut pick = || ((draws.next_f64() * n as f64) as usize).min(n - 1);
    let mut best: Option<(usize, Vector3<f64>, f64)> = None;
    for _ in 0..settings.trials {
        let (a, b, c) = (ring[pick()], ring[pick()], ring[pick()]);
        let normal = (b - a).cross(&(c - a));
        let length = normal.norm();
        if length <= 1e-12 {
            continue;
        }
        let normal = normal / length;
        let offset = a.dot(&normal);
        let fits = ring
            .iter()
            .filter(|p| (p.dot(&normal) - offset).abs() < tolerance)
            .count();
        if best.is_none_or(|(most, _, _)| fits > most) {
            best = Some((fits, normal, offset));
        }
    }
    let (fits, normal, offset) = best?;
    if (fits as f64) < settings.min_share * n as f64 {
        return None;
    }
    // Refitted to the points within `tolerance`, then to those within
    // `tolerance` of the refit: near-equal draws end on the same plane.
    let (mut centre, mut normal) = (normal * offset, normal);
    let mut on_plane: Vec<&Vector3<f64>> = Vec::new();
    for _ in 0..REFITS {
        let offset = centre.dot(&normal);
        on_plane = ring
            .iter()
            .filter(|p| (p.dot(&normal) - offset).abs() < tolerance)
            .collect();
        if on_plane.len() < 3 {
            return None;
        }
        centre = on_plane.iter().copied().sum::<Vector3<f64>>() / on_plane.len() as f64;
        let scatter = on_plane
            .iter()
            .map(|p| (*p - centre) * (*p - centre).transpose())
            .sum::<Matrix3<f64>>();
        if !scatter.iter().all(|x| x.is_finite()) {
            return None; // depths beyond any sensor's (overflowing squares)
        }
        let eigen = SymmetricEigen::new(scatter);
        normal = eigen
            .eigenvectors
            .column(eigen.eigenvalues.imin())
            .into_owned();
        if normal.dot(&centre) > 0.0 {
            normal = -normal; // towards the camera
        }
    }
    let residuals: Vec<f64> = on_plane
        .iter()
        .map(|p| (*p - centre).dot(&normal))
        .collect();
    Some((
        centre,
        normal,
        1.4826 * median_absolute_deviation(&residuals),
    ))
}

/// Median of |x − median(x)| (the middle two averaged for an even count;
/// `values` not empty).
fn median_absolute_deviation(values: &[f64]) -> f64 {
    let centre = median(values.to_vec());
    median(values.iter().map(|x| (x - centre).abs()).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    const CAMERA: Pinhole = Pinhole {
        fx: 150.0,
        fy: 150.0,
        cx: 80.0,
        cy: 60.0,
    };
    const WIDTH: usize = 160;
    const HEIGHT: usize = 120;

    #[test]
    fn dilation_sets_every_cell_within_the_disk_of_a_flag() {
        let mut draws = SplitMix64::new(3);
        for (rows, cols, radius) in [(9, 13, 3), (7, 5, 1), (4, 4, 0), (12, 3, 4), (1, 9, 2)] {
            let flags: Vec<bool> = (0..rows * cols).map(|_| draws.next_f64() < 0.1).collect();
            let grown = dilate(&flags, rows, cols, radius);
            for (cell, &set) in grown.iter().enumerate() {
                let (r, c) = ((cell / cols) as i64, (cell % cols) as i64);
                let near = flags.iter().enumerate().any(|(other, &flag)| {
                    let (dr, dc) = ((other / cols) as i64 - r, (other % cols) as i64 - c);
                    flag && dr * dr + dc * dc <= radius * radius
                });
                assert_eq!(set, near, "{rows}x{cols} r {radius} cell {cell}");
            }
        }
    }

    /// A ball of radius 5 cm resting on a table seen 45° from above, or
    /// (`in_front`) a wall 5 cm in front of the ball's centre hiding its
    /// upper half: the depth image (metres, 0: nothing) and the cloud of
    /// the ball's silhouette grown by 3 px, with which points are the ball's.
    fn scene(in_front: bool) -> (Vec<f32>, Vec<Point3>, Vec<bool>) {
        let centre = Vector3::new(0.0, 0.0, 0.6);
        let radius = 0.05;
        let up = Vector3::new(0.0, -1.0, -1.0).normalize();
        let (plane_point, plane_normal) = if in_front {
            (
                centre - Vector3::new(0.0, 0.0, radius),
                Vector3::new(0.0, 0.0, -1.0),
            )
        } else {
            (centre - radius * up, up)
        };
        let mut depth = vec![0.0f32; WIDTH * HEIGHT];
        let mut ball = vec![false; WIDTH * HEIGHT];
        for v in 0..HEIGHT {
            for u in 0..WIDTH {
                let ray = Vector3::new(
                    (u as f64 - CAMERA.cx) / CAMERA.fx,
                    (v as f64 - CAMERA.cy) / CAMERA.fy,
                    1.0,
                );
                let plane_t = plane_point.dot(&plane_normal) / ray.dot(&plane_normal);
                let (a, b, c) = (
                    ray.dot(&ray),
                    -2.0 * ray.dot(&centre),
                    centre.dot(&centre) - radius * radius,
                );
                let disc = b * b - 4.0 * a * c;
                let ball_t = (disc >= 0.0).then(|| (-b - disc.sqrt()) / (2.0 * a));
                // The wall in front covers only the image's upper half.
                let plane_t = if in_front && v >= HEIGHT / 2 {
                    -1.0
                } else {
                    plane_t
                };
                let t = match ball_t {
                    Some(t) if plane_t <= 0.0 || t < plane_t => {
                        ball[v * WIDTH + u] = true;
                        t
                    }
                    _ if plane_t > 0.0 => plane_t,
                    _ => 0.0,
                };
                depth[v * WIDTH + u] = t as f32; // z of the hit (the ray's z is 1)
            }
        }
        let (mut cloud, mut on_ball) = (Vec::new(), Vec::new());
        for v in 0..HEIGHT as i64 {
            for u in 0..WIDTH as i64 {
                let near_ball = (-3..=3i64).any(|dv| {
                    (-3..=3i64).any(|du| {
                        let (vv, uu) = (v + dv, u + du);
                        (0..HEIGHT as i64).contains(&vv)
                            && (0..WIDTH as i64).contains(&uu)
                            && ball[(vv * WIDTH as i64 + uu) as usize]
                    })
                });
                let z = depth[(v * WIDTH as i64 + u) as usize];
                if near_ball && z > 0.0 {
                    let x = (u as f64 - CAMERA.cx) * z as f64 / CAMERA.fx;
                    let y = (v as f64 - CAMERA.cy) * z as f64 / CAMERA.fy;
                    cloud.push([x as f32, y as f32, z]);
                    on_ball.push(ball[(v * WIDTH as i64 + u) as usize]);
                }
            }
        }
        (depth, cloud, on_ball)
    }

    #[test]
    fn the_table_under_a_ball_is_found_and_the_ball_kept() {
        let (depth, cloud, on_ball) = scene(false);
        let on = on_support_plane(
            &cloud,
            &depth,
            WIDTH,
            &CAMERA,
            1.0,
            0.1,
            &SupportSettings::default(),
        );
        // (points, points taken) of the ball's or of the rest.
        let taken = |of_ball: bool| {
            on.iter()
                .zip(&on_ball)
                .filter(|(_, b)| **b == of_ball)
                .fold((0, 0), |(n, t), (o, _)| (n + 1, t + *o as usize))
        };
        let ((table, table_taken), (ball, ball_taken)) = (taken(false), taken(true));
        assert!(table > 50 && ball > 200);
        assert!(table_taken as f64 >= 0.95 * table as f64);
        // Only the ball's points within millimetres of where it touches the table.
        assert!(ball_taken as f64 <= 0.03 * ball as f64);
    }

    #[test]
    fn the_same_table_in_millimetres_gives_the_same_points() {
        let (depth, cloud, _) = scene(false);
        let millimetres: Vec<u16> = depth.iter().map(|z| (z * 1000.0).round() as u16).collect();
        let settings = SupportSettings::default();
        let metres = on_support_plane(&cloud, &depth, WIDTH, &CAMERA, 1.0, 0.1, &settings);
        let mm = on_support_plane(&cloud, &millimetres, WIDTH, &CAMERA, 1000.0, 0.1, &settings);
        let agree = metres.iter().zip(&mm).filter(|(a, b)| a == b).count();
        assert!(agree as f64 >= 0.98 * metres.len() as f64);
    }

    #[test]
    fn an_occluder_in_front_is_never_taken_for_a_support() {
        let (depth, cloud, on_ball) = scene(true);
        assert!(on_ball.iter().any(|b| !b)); // the occluder's face is in the cloud
        let on = on_support_plane(
            &cloud,
            &depth,
            WIDTH,
            &CAMERA,
            1.0,
            0.1,
            &SupportSettings::default(),
        );
        assert!(!on.contains(&true));
    }

    #[test]
    fn no_surroundings_no_points_or_no_image_take_nothing() {
        let (_, cloud, _) = scene(false);
        let settings = SupportSettings::default();
        let empty = vec![0.0f32; WIDTH * HEIGHT];
        assert!(
            !on_support_plane(&cloud, &empty, WIDTH, &CAMERA, 1.0, 0.1, &settings).contains(&true)
        );
        assert!(on_support_plane(&[], &empty, WIDTH, &CAMERA, 1.0, 0.1, &settings).is_empty());
        assert!(
            !on_support_plane(&cloud, &[] as &[f32], 0, &CAMERA, 1.0, 0.1, &settings)
                .contains(&true)
        );
        let far = vec![[f32::NAN, 0.0, 0.5]; 3];
        assert!(
            !on_support_plane(&far, &empty, WIDTH, &CAMERA, 1.0, 0.1, &settings).contains(&true)
        );
        // Points off the image or behind the camera: nothing, no overflow.
        let off = vec![[1e30, -1e30, 0.5], [1.0, 1.0, -1.0], [0.0, 0.0, 0.0]];
        assert!(
            !on_support_plane(&off, &empty, WIDTH, &CAMERA, 1.0, 0.1, &settings).contains(&true)
        );
    }
}
