//! Viewpoints: directions on a Fibonacci sphere, each with a virtual camera
//! (OpenCV convention: x right, y down, z forward) looking at the object's
//! centre.

use nalgebra::{Matrix3, Vector3};

/// Rotation object → view frame: `p_view = R_v · p_obj` (row-major rows are
/// the view axes expressed in object coordinates).
pub type Rotation = Matrix3<f64>;

/// `n` unit directions (object frame, pointing from the object's centre to
/// the camera), near-uniform on the sphere.
pub fn fibonacci_directions(n: usize) -> Vec<Vector3<f64>> {
    let golden_angle = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..n)
        .map(|i| {
            let z = 1.0 - (2.0 * i as f64 + 1.0) / n as f64;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let phi = golden_angle * i as f64;
            Vector3::new(r * phi.cos(), r * phi.sin(), z)
        })
        .collect()
}

/// Rotation object → view frame of a camera placed along `direction` and
/// looking at the object's centre.
///
/// The optical axis is `-direction`. The image's "down" axis is the object's
/// −z projected onto the image plane (−y when the view is within ~8° of the
/// z axis), so every direction gets one fixed, documented rotation.
pub fn view_rotation(direction: &Vector3<f64>) -> Rotation {
    let z_axis = -direction.normalize();
    let up = if z_axis.z.abs() < 0.99 {
        Vector3::z()
    } else {
        Vector3::y()
    };
    let y_axis = -(up - z_axis * up.dot(&z_axis)).normalize();
    let x_axis = y_axis.cross(&z_axis);
    Matrix3::from_rows(&[x_axis.transpose(), y_axis.transpose(), z_axis.transpose()])
}

/// Viewpoint correction: the smallest rotation (camera frame → corrected
/// frame) that turns the ray through `centroid` (camera frame, metres) onto
/// the optical axis +z. An observed cloud rotated by it looks as if the
/// camera faced the object head-on, like the codebook's virtual cameras.
/// None when `centroid` is zero or not finite (no ray).
pub fn ray_alignment(centroid: &Vector3<f64>) -> Option<Rotation> {
    let norm = centroid.norm();
    if !norm.is_finite() || norm == 0.0 {
        return None;
    }
    let ray = centroid / norm;
    let axis = ray.cross(&Vector3::z());
    let (s, c) = (axis.norm(), ray.z);
    if s < 1e-12 {
        return Some(if c > 0.0 {
            Matrix3::identity()
        } else {
            Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0))
        });
    }
    let skew = (axis / s).cross_matrix();
    Some(Matrix3::identity() + skew * s + skew * skew * (1.0 - c))
}

/// Directions and their view rotations for `n` viewpoints.
pub fn viewpoints(n: usize) -> (Vec<Vector3<f64>>, Vec<Rotation>) {
    let directions = fibonacci_directions(n);
    let rotations = directions.iter().map(view_rotation).collect();
    (directions, rotations)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ray_alignment_turns_the_centroid_ray_onto_the_optical_axis() {
        for centroid in [
            Vector3::new(0.2, -0.1, 0.7),
            Vector3::new(0.0, 0.0, 0.5),
            Vector3::new(0.0, 0.0, -0.5),
            Vector3::new(-1.0, 0.3, 0.1),
        ] {
            let r = ray_alignment(&centroid).unwrap();
            assert!((r * r.transpose() - Matrix3::identity()).norm() < 1e-12);
            assert!((r.determinant() - 1.0).abs() < 1e-12);
            assert!((r * centroid.normalize() - Vector3::z()).norm() < 1e-12);
        }
        assert!(ray_alignment(&Vector3::zeros()).is_none());
        assert!(ray_alignment(&Vector3::new(f64::NAN, 0.0, 1.0)).is_none());
    }

    fn nearest_angles_deg(dirs: &[Vector3<f64>]) -> Vec<f64> {
        dirs.iter()
            .enumerate()
            .map(|(i, a)| {
                dirs.iter()
                    .enumerate()
                    .filter(|(j, _)| *j != i)
                    .map(|(_, b)| a.dot(b).clamp(-1.0, 1.0).acos().to_degrees())
                    .fold(f64::INFINITY, f64::min)
            })
            .collect()
    }

    #[test]
    fn directions_are_unit_and_near_uniform() {
        let dirs = fibonacci_directions(2100);
        assert_eq!(dirs.len(), 2100);
        for d in &dirs {
            assert!((d.norm() - 1.0).abs() < 1e-12);
        }
        // Ideal spacing for N points on a sphere ≈ sqrt(4π/N) rad ≈ 4.4° here.
        let angles = nearest_angles_deg(&dirs);
        let min = angles.iter().cloned().fold(f64::INFINITY, f64::min);
        let max = angles.iter().cloned().fold(0.0, f64::max);
        let mean = angles.iter().sum::<f64>() / angles.len() as f64;
        assert!(mean > 3.5 && mean < 4.6, "mean spacing {mean}°");
        assert!(min > 0.6 * mean, "closest pair {min}° vs mean {mean}°");
        assert!(max < 1.5 * mean, "largest gap {max}° vs mean {mean}°");
        // Balanced: the mean direction is near the origin.
        let centroid: Vector3<f64> = dirs.iter().sum::<Vector3<f64>>() / dirs.len() as f64;
        assert!(centroid.norm() < 1e-3);
    }

    #[test]
    fn rotations_are_proper_and_look_at_the_centre() {
        let (dirs, rots) = viewpoints(2100);
        for (d, r) in dirs.iter().zip(&rots) {
            let err = (r * r.transpose() - Matrix3::identity()).abs().max();
            assert!(err < 1e-12, "not orthonormal: {err}");
            assert!((r.determinant() - 1.0).abs() < 1e-12);
            // The camera sits on +direction, so the centre is straight ahead (+z).
            let ahead = r * (-d);
            assert!((ahead - Vector3::z()).norm() < 1e-12);
        }
    }

    #[test]
    fn image_down_axis_follows_object_minus_z() {
        // Camera on +x looking at the centre: object's +z must appear "up" (−y).
        let r = view_rotation(&Vector3::x());
        let up_in_view = r * Vector3::z();
        assert!((up_in_view - (-Vector3::y())).norm() < 1e-12);
    }
}
