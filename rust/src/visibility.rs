//! Which model points a camera sees: back-face culling by normal, then a
//! z-buffer of splatted points (orthographic along the view's +z axis) for
//! self-occlusion. Orthographic is a sound approximation: the object spans a
//! few degrees of a real camera's field of view at working distance, and the
//! query is rotated onto the optical axis before matching.

use crate::Point3;

/// A point is front-facing when its normal points towards the camera by more
/// than this cosine (grazing points are as good as invisible to a sensor).
const FACING_COSINE: f32 = 0.05;
/// Depth slope cap (|∇z| = tan of the surface tilt), about 76°.
const MAX_DEPTH_SLOPE: f32 = 4.0;

/// Visibility flags for points and unit normals given in the view frame
/// (camera at −z infinity looking along +z). `spacing` is the model's mean
/// point spacing, in the same units as the points; it sets the z-buffer's
/// cell size.
pub fn visible_mask(points: &[Point3], normals: &[Point3], spacing: f32) -> Vec<bool> {
    let front: Vec<bool> = normals.iter().map(|n| n[2] < -FACING_COSINE).collect();
    let Some(grid) = Grid::covering(points, &front, spacing) else {
        return front;
    };

    // Each front-facing point splats its depth over its cell and the 8 around
    // it, so a surface leaves no holes for the one behind to show through.
    // The buffer has a border of one cell all round, so every splat lies
    // whole inside it: cell (x, y) is `depth[(y + 1) * row + x + 1]`.
    let row = grid.width + 2;
    let mut depth = vec![f32::INFINITY; row * (grid.height + 2)];
    for (p, _) in points.iter().zip(&front).filter(|(_, f)| **f) {
        let (cx, cy) = grid.cell(p);
        for y in cy..cy + 3 {
            for d in &mut depth[y * row + cx..y * row + cx + 3] {
                *d = d.min(p[2]);
            }
        }
    }

    // A point is seen when nothing lies clearly in front of it. The splat
    // reaches ~2 cells, over which the point's own surface changes depth by
    // up to 2·cell·slope, so the tolerance grows with the slope.
    points
        .iter()
        .zip(normals)
        .zip(&front)
        .map(|((p, n), &is_front)| {
            if !is_front {
                return false;
            }
            let slope = ((n[0] * n[0] + n[1] * n[1]).sqrt() / -n[2]).min(MAX_DEPTH_SLOPE);
            let tolerance = 0.5 * spacing + 2.0 * grid.cell_size * slope;
            let (cx, cy) = grid.cell(p);
            p[2] <= depth[(cy + 1) * row + cx + 1] + tolerance
        })
        .collect()
}

struct Grid {
    min_x: f32,
    min_y: f32,
    cell_size: f32,
    width: usize,
    height: usize,
}

impl Grid {
    /// A grid over the selected points' x–y extent; `None` when there is
    /// nothing to cover or the spacing is unusable.
    fn covering(points: &[Point3], selected: &[bool], cell_size: f32) -> Option<Self> {
        if !(cell_size > 0.0 && cell_size.is_finite()) {
            return None;
        }
        let (mut min_x, mut min_y) = (f32::INFINITY, f32::INFINITY);
        let (mut max_x, mut max_y) = (f32::NEG_INFINITY, f32::NEG_INFINITY);
        for (p, _) in points.iter().zip(selected).filter(|(_, s)| **s) {
            min_x = min_x.min(p[0]);
            min_y = min_y.min(p[1]);
            max_x = max_x.max(p[0]);
            max_y = max_y.max(p[1]);
        }
        if min_x > max_x {
            return None;
        }
        // Bounded grid even for a spacing far too small for the extent.
        // Clamped before the cast: a tiny spacing would otherwise saturate to
        // usize::MAX and wrap to an empty grid on the `+ 1`.
        let width = ((max_x - min_x) / cell_size).min(4095.0) as usize + 1;
        let height = ((max_y - min_y) / cell_size).min(4095.0) as usize + 1;
        let cell_size = cell_size
            .max((max_x - min_x) / 4095.0)
            .max((max_y - min_y) / 4095.0);
        Some(Self {
            min_x,
            min_y,
            cell_size,
            width,
            height,
        })
    }

    fn cell(&self, p: &Point3) -> (usize, usize) {
        let x = ((p[0] - self.min_x) / self.cell_size) as usize;
        let y = ((p[1] - self.min_y) / self.cell_size) as usize;
        (x.min(self.width - 1), y.min(self.height - 1))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    /// Square of `k × k` points at depth `z`, normals facing the camera (−z).
    fn plate(k: usize, z: f32, step: f32) -> (Vec<Point3>, Vec<Point3>) {
        let mut points = Vec::new();
        for i in 0..k {
            for j in 0..k {
                points.push([i as f32 * step, j as f32 * step, z]);
            }
        }
        let normals = vec![[0.0, 0.0, -1.0]; points.len()];
        (points, normals)
    }

    #[test]
    fn near_plate_hides_the_plate_behind_it() {
        let (mut points, mut normals) = plate(20, 0.0, 0.05);
        let (back, back_normals) = plate(20, 1.0, 0.05);
        points.extend(back);
        normals.extend(back_normals);
        let mask = visible_mask(&points, &normals, 0.05);
        assert!(mask[..400].iter().all(|&v| v), "front plate fully visible");
        assert!(mask[400..].iter().all(|&v| !v), "back plate fully hidden");
    }

    #[test]
    fn partly_covered_plate_shows_its_uncovered_part() {
        let (mut points, mut normals) = plate(10, 0.0, 0.05); // x in [0, 0.45]
        let (back, back_normals) = plate(20, 1.0, 0.05); // x in [0, 0.95]
        points.extend(back);
        normals.extend(back_normals);
        let mask = visible_mask(&points, &normals, 0.05);
        for (p, v) in points[100..].iter().zip(&mask[100..]) {
            if p[0] > 0.6 || p[1] > 0.6 {
                assert!(v, "uncovered back point {p:?} must be visible");
            }
            if p[0] < 0.4 && p[1] < 0.4 {
                assert!(!v, "covered back point {p:?} must be hidden");
            }
        }
    }

    #[test]
    fn a_spacing_far_too_small_still_gives_a_bounded_grid() {
        let (points, normals) = plate(20, 0.0, 50.0);
        for spacing in [1e-30, f32::MIN_POSITIVE, 1e-45] {
            let mask = visible_mask(&points, &normals, spacing);
            assert!(
                mask.iter().all(|&v| v),
                "a lone plate is fully visible (spacing {spacing})"
            );
        }
    }

    #[test]
    fn sphere_shows_its_near_half() {
        let mut rng = SplitMix64::new(5);
        let mut points = Vec::new();
        while points.len() < 4000 {
            let p = [0, 1, 2].map(|_| (2.0 * rng.next_f64() - 1.0) as f32);
            let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
            if r > 0.1 && r <= 1.0 {
                points.push(p.map(|v| v / r));
            }
        }
        let normals = points.clone();
        let mask = visible_mask(&points, &normals, 0.05);
        let seen = mask.iter().filter(|&&v| v).count() as f64 / points.len() as f64;
        assert!((seen - 0.475).abs() < 0.03, "saw {seen}");
        for (p, v) in points.iter().zip(&mask) {
            assert_eq!(*v, p[2] < -FACING_COSINE, "convex: visible iff facing");
        }
    }
}
