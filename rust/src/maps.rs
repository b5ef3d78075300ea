//! Maps: what a camera sees of the model, expressed in its view frame,
//! centred on the visible points, scaled into the unit sphere and resampled
//! to a fixed number of points. The same normalisation applies to an
//! observed cloud at query time ([`normalize_to_map`]).

use rayon::prelude::*;

use crate::model::StandardModel;
use crate::sampling::farthest_point_sample;
use crate::threads;
use crate::views::Rotation;
use crate::visibility::visible_mask;
use crate::Point3;

/// One viewpoint's map and where it came from.
#[derive(Clone, Debug)]
pub struct ViewMap {
    /// `m` points, view frame, centred on the visible points, unit-sphere scale.
    pub points: Vec<Point3>,
    /// Centroid of the visible points, model frame, metres; with the pose's
    /// rotation it turns an observed centroid into a translation.
    pub centroid: [f64; 3],
    /// How many model points the camera sees.
    pub visible: usize,
}

/// All viewpoints' maps, flattened view-major: `points[v * m + i]`.
#[derive(Clone, Debug)]
pub struct Maps {
    pub points: Vec<Point3>,
    pub centroids: Vec<[f64; 3]>,
    pub visible: Vec<u32>,
    pub points_per_map: usize,
}

/// The map of `model` seen through a camera with rotation object → view `rotation`.
pub fn view_map(model: &StandardModel, rotation: &Rotation, m: usize) -> ViewMap {
    let r = rotation.cast::<f32>();
    let rotate = |p: &Point3| {
        let v = r * nalgebra::Vector3::new(p[0], p[1], p[2]);
        [v.x, v.y, v.z]
    };
    let in_view: Vec<Point3> = model.points.iter().map(rotate).collect();
    let normals: Vec<Point3> = model.normals.iter().map(rotate).collect();
    let mask = visible_mask(&in_view, &normals, model.spacing as f32);
    let seen: Vec<Point3> = in_view
        .iter()
        .zip(&mask)
        .filter(|(_, v)| **v)
        .map(|(p, _)| *p)
        .collect();
    if seen.is_empty() {
        return ViewMap {
            points: vec![[0.0; 3]; m],
            centroid: [0.0; 3],
            visible: 0,
        };
    }
    let (points, centroid_view) = normalize_to_map(&seen, model.scale as f32, m);
    let c = rotation.transpose()
        * nalgebra::Vector3::new(
            centroid_view[0] as f64,
            centroid_view[1] as f64,
            centroid_view[2] as f64,
        );
    ViewMap {
        points,
        centroid: [c.x, c.y, c.z],
        visible: seen.len(),
    }
}

/// Maps of every viewpoint, computed in parallel.
pub fn compute_maps(model: &StandardModel, rotations: &[Rotation], m: usize) -> Maps {
    let per_view: Vec<ViewMap> = threads::install(|| {
        rotations
            .par_iter()
            .map(|r| view_map(model, r, m))
            .collect()
    });
    let mut maps = Maps {
        points: Vec::with_capacity(rotations.len() * m),
        centroids: Vec::with_capacity(rotations.len()),
        visible: Vec::with_capacity(rotations.len()),
        points_per_map: m,
    };
    for view in per_view {
        maps.points.extend(view.points);
        maps.centroids.push(view.centroid);
        maps.visible.push(view.visible as u32);
    }
    maps
}

/// Centres `points` on their centroid, multiplies by `scale`, and resamples
/// them to `m` points by farthest-point sampling. Returns the map and the
/// centroid (in the points' own frame and units). `points` must be non-empty.
pub fn normalize_to_map(points: &[Point3], scale: f32, m: usize) -> (Vec<Point3>, Point3) {
    let inv_n = 1.0 / points.len() as f64;
    let mut sum = [0.0f64; 3];
    for p in points {
        for k in 0..3 {
            sum[k] += p[k] as f64;
        }
    }
    let centroid = sum.map(|s| (s * inv_n) as f32);
    let chosen = farthest_point_sample(points, m);
    let map = chosen
        .iter()
        .map(|&i| {
            let p = points[i as usize];
            [0, 1, 2].map(|k| (p[k] - centroid[k]) * scale)
        })
        .collect();
    (map, centroid)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::tests::cube_mesh;
    use crate::views::{view_rotation, viewpoints};
    use nalgebra::Vector3;

    fn cube_model() -> StandardModel {
        let (v, f) = cube_mesh(0.05);
        StandardModel::from_mesh(&v, &f, 4096, 1).unwrap()
    }

    #[test]
    fn cube_seen_along_z_shows_exactly_its_top_face() {
        let model = cube_model();
        // Camera on +z looking down −z: only the +z face faces it.
        let r = view_rotation(&Vector3::z());
        let to_view = |p: &Point3| {
            let v = r.cast::<f32>() * Vector3::new(p[0], p[1], p[2]);
            [v.x, v.y, v.z]
        };
        let pts: Vec<Point3> = model.points.iter().map(to_view).collect();
        let nrm: Vec<Point3> = model.normals.iter().map(to_view).collect();
        let mask = visible_mask(&pts, &nrm, model.spacing as f32);
        for ((p, n), v) in model.points.iter().zip(&model.normals).zip(&mask) {
            let on_top = n[2] > 0.99;
            assert_eq!(*v, on_top, "point {p:?} normal {n:?}");
        }
        let map = view_map(&model, &r, 512);
        assert_eq!(map.visible, mask.iter().filter(|&&v| v).count());
        // The visible centroid is the top face's centre (model frame).
        assert!((map.centroid[2] - 0.05).abs() < 2e-3 && map.centroid[0].abs() < 3e-3);
        // The top face is flat: all map points share one depth (z = 0 after centring).
        assert!(map.points.iter().all(|p| p[2].abs() < 1e-4));
    }

    #[test]
    fn maps_are_centred_scaled_and_sized() {
        let model = cube_model();
        let (_, rotations) = viewpoints(64);
        let maps = compute_maps(&model, &rotations, 256);
        assert_eq!(maps.points.len(), 64 * 256);
        for v in 0..64 {
            let map = &maps.points[v * 256..(v + 1) * 256];
            assert!(maps.visible[v] > 256);
            let r = map
                .iter()
                .map(|p| (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt())
                .fold(0.0, f32::max);
            assert!(r <= 2.0 + 1e-4, "map must stay in the scaled frame: {r}");
            // Centred on all visible points, so the FPS subset's mean is near 0.
            let mean: Vec<f32> = (0..3)
                .map(|k| map.iter().map(|p| p[k]).sum::<f32>() / 256.0)
                .collect();
            assert!(mean.iter().all(|m| m.abs() < 0.1), "{mean:?}");
        }
    }

    #[test]
    fn normalising_recovers_centroid_and_scale() {
        let points: Vec<Point3> = (0..100).map(|i| [i as f32, 2.0, 3.0]).collect();
        let (map, centroid) = normalize_to_map(&points, 0.5, 10);
        assert_eq!(centroid, [49.5, 2.0, 3.0]);
        assert_eq!(map.len(), 10);
        let xs: Vec<f32> = map.iter().map(|p| p[0]).collect();
        assert!(xs.contains(&(-49.5 * 0.5)) && xs.contains(&(49.5 * 0.5)));
    }
}
