//! The standard model: an object's surface as evenly spread points with
//! outward normals, centred, plus the numbers every later stage needs
//! (scale to the unit sphere, diameter, point spacing).

use std::num::NonZero;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

use crate::error::GeometryError;
use crate::rng::SplitMix64;
use crate::sampling::farthest_point_sample;
use crate::threads;
use crate::Point3;

/// Surface samples drawn per kept point before farthest-point thinning.
const OVERSAMPLING: usize = 4;

#[derive(Clone, Debug)]
pub struct StandardModel {
    /// Surface points, metres, model frame (original frame shifted by `centre`).
    pub points: Vec<Point3>,
    /// Unit outward normals, one per point, model frame.
    pub normals: Vec<Point3>,
    /// Where the model frame's origin lies in the original mesh frame, metres.
    pub centre: [f64; 3],
    /// `1 / max‖p‖`: multiplies model-frame metres into the unit sphere.
    pub scale: f64,
    /// Largest distance between two model points, metres.
    pub diameter: f64,
    /// Mean distance from a point to its nearest neighbour, metres.
    pub spacing: f64,
}

impl StandardModel {
    /// Samples `n` evenly spread points on a triangle mesh (vertices in
    /// metres): area-weighted random samples, thinned by farthest-point
    /// sampling; normals are the faces' normals.
    pub fn from_mesh(
        vertices: &[[f64; 3]],
        faces: &[[u32; 3]],
        n: usize,
        seed: u64,
    ) -> Result<Self, GeometryError> {
        let (points, normals) = sample_surface(vertices, faces, n * OVERSAMPLING, seed)?;
        Self::from_points(&points, &normals, n)
    }

    /// Builds a model from surface points with normals (metres), thinned to
    /// `n` points by farthest-point sampling when there are more.
    pub fn from_points(
        points: &[Point3],
        normals: &[Point3],
        n: usize,
    ) -> Result<Self, GeometryError> {
        if points.is_empty() {
            return Err(GeometryError::Empty("model point cloud"));
        }
        if points.len() != normals.len() {
            return Err(GeometryError::LengthMismatch {
                what: "model points and normals",
                left: points.len(),
                right: normals.len(),
            });
        }
        if n < 16 {
            return Err(GeometryError::InvalidParameter(format!(
                "a model needs at least 16 points, asked for {n}"
            )));
        }
        if points
            .iter()
            .chain(normals)
            .flatten()
            .any(|v| !v.is_finite())
        {
            return Err(GeometryError::NonFinite("model points or normals"));
        }
        let keep: Vec<usize> = if points.len() > n {
            farthest_point_sample(points, n)
                .into_iter()
                .map(|i| i as usize)
                .collect()
        } else {
            (0..points.len()).collect()
        };

        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for &i in &keep {
            for k in 0..3 {
                lo[k] = lo[k].min(points[i][k] as f64);
                hi[k] = hi[k].max(points[i][k] as f64);
            }
        }
        let centre = [
            0.5 * (lo[0] + hi[0]),
            0.5 * (lo[1] + hi[1]),
            0.5 * (lo[2] + hi[2]),
        ];
        let centred: Vec<Point3> = keep
            .iter()
            .map(|&i| {
                let p = points[i];
                [
                    (p[0] as f64 - centre[0]) as f32,
                    (p[1] as f64 - centre[1]) as f32,
                    (p[2] as f64 - centre[2]) as f32,
                ]
            })
            .collect();
        let mut unit_normals: Vec<Point3> = keep.iter().map(|&i| normalized(normals[i])).collect();
        orient_outward(&centred, &mut unit_normals);

        let radius = centred.iter().map(|p| norm(*p) as f64).fold(0.0, f64::max);
        if radius <= 0.0 {
            return Err(GeometryError::InvalidParameter(
                "model has no extent: all points coincide".into(),
            ));
        }
        let diameter = diameter(&centred);
        let spacing = mean_nearest_neighbour_distance(&centred);
        Ok(Self {
            points: centred,
            normals: unit_normals,
            centre,
            scale: 1.0 / radius,
            diameter,
            spacing,
        })
    }
}

/// Area-weighted random points on a triangle mesh with their faces' unit
/// normals (right-hand winding). Zero-area faces are never chosen.
pub fn sample_surface(
    vertices: &[[f64; 3]],
    faces: &[[u32; 3]],
    count: usize,
    seed: u64,
) -> Result<(Vec<Point3>, Vec<Point3>), GeometryError> {
    if vertices.is_empty() || faces.is_empty() {
        return Err(GeometryError::Empty("mesh"));
    }
    if vertices.iter().flatten().any(|v| !v.is_finite()) {
        return Err(GeometryError::NonFinite("mesh vertices"));
    }
    let mut cumulative = Vec::with_capacity(faces.len());
    let mut face_normals = Vec::with_capacity(faces.len());
    let mut total = 0.0f64;
    for (f, face) in faces.iter().enumerate() {
        for &index in face {
            if index as usize >= vertices.len() {
                return Err(GeometryError::FaceIndexOutOfRange {
                    face: f,
                    index,
                    vertices: vertices.len(),
                });
            }
        }
        let [a, b, c] = face.map(|i| vertices[i as usize]);
        let cross = cross3(sub3(b, a), sub3(c, a));
        let twice_area = (cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2]).sqrt();
        total += 0.5 * twice_area;
        cumulative.push(total);
        face_normals.push(if twice_area > 0.0 {
            [
                (cross[0] / twice_area) as f32,
                (cross[1] / twice_area) as f32,
                (cross[2] / twice_area) as f32,
            ]
        } else {
            [0.0; 3]
        });
    }
    if total <= 0.0 || !total.is_finite() {
        return Err(GeometryError::DegenerateMesh);
    }

    let mut rng = SplitMix64::new(seed);
    let mut points = Vec::with_capacity(count);
    let mut normals = Vec::with_capacity(count);
    for _ in 0..count {
        let target = rng.next_f64() * total;
        // First face whose cumulative area exceeds the target; zero-area faces
        // share their predecessor's cumulative value and are skipped.
        let f = cumulative
            .partition_point(|&c| c <= target)
            .min(faces.len() - 1);
        let [a, b, c] = faces[f].map(|i| vertices[i as usize]);
        let (mut u, mut v) = (rng.next_f64(), rng.next_f64());
        if u + v > 1.0 {
            u = 1.0 - u;
            v = 1.0 - v;
        }
        let p = [0, 1, 2].map(|k| (a[k] + u * (b[k] - a[k]) + v * (c[k] - a[k])) as f32);
        points.push(p);
        normals.push(face_normals[f]);
    }
    Ok((points, normals))
}

/// Flips every normal when most of them point towards the centre: some
/// meshes are wound inside-out, and visibility relies on outward normals.
fn orient_outward(points: &[Point3], normals: &mut [Point3]) {
    let inward = points
        .iter()
        .zip(normals.iter())
        .filter(|(p, n)| dot(**p, **n) < 0.0)
        .count();
    if 2 * inward > points.len() {
        for n in normals.iter_mut() {
            *n = [-n[0], -n[1], -n[2]];
        }
    }
}

/// Largest pairwise distance, exact (O(n²), parallel: once per model).
pub fn diameter(points: &[Point3]) -> f64 {
    threads::install(|| {
        points
            .par_iter()
            .enumerate()
            .map(|(i, p)| {
                points[i + 1..]
                    .iter()
                    .map(|q| {
                        let d = sub3f(*p, *q);
                        dot(d, d)
                    })
                    .fold(0.0f32, f32::max)
            })
            .reduce(|| 0.0, f32::max)
    })
    .sqrt() as f64
}

/// Mean distance from each point to its nearest other point.
pub fn mean_nearest_neighbour_distance(points: &[Point3]) -> f64 {
    if points.len() < 2 {
        return 0.0;
    }
    let tree: ImmutableKdTree<f32, 3> = ImmutableKdTree::new_from_slice(points);
    let two = NonZero::new(2).expect("2 is non-zero");
    let distances: Vec<f64> = threads::install(|| {
        points
            .par_iter()
            .map(|p| {
                let found = tree.nearest_n::<SquaredEuclidean>(p, two);
                // The nearest hit is the point itself (distance 0), or a duplicate.
                found.last().map_or(0.0, |nn| (nn.distance as f64).sqrt())
            })
            .collect()
    });
    // Summed in order, not by rayon's reduction tree (which depends on how the
    // work was split): the same model gives the same spacing to the last bit.
    distances.iter().sum::<f64>() / points.len() as f64
}

fn normalized(v: Point3) -> Point3 {
    let n = norm(v);
    if n > 0.0 {
        [v[0] / n, v[1] / n, v[2] / n]
    } else {
        v
    }
}

fn norm(v: Point3) -> f32 {
    dot(v, v).sqrt()
}

fn dot(a: Point3, b: Point3) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn sub3f(a: Point3, b: Point3) -> Point3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn sub3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Axis-aligned cube of side `2·half`, outward (counter-clockwise) winding.
    pub(crate) fn cube_mesh(half: f64) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
        let h = half;
        let vertices = vec![
            [-h, -h, -h],
            [h, -h, -h],
            [h, h, -h],
            [-h, h, -h],
            [-h, -h, h],
            [h, -h, h],
            [h, h, h],
            [-h, h, h],
        ];
        let faces = vec![
            [0, 2, 1],
            [0, 3, 2], // -z
            [4, 5, 6],
            [4, 6, 7], // +z
            [0, 1, 5],
            [0, 5, 4], // -y
            [3, 7, 6],
            [3, 6, 2], // +y
            [0, 4, 7],
            [0, 7, 3], // -x
            [1, 2, 6],
            [1, 6, 5], // +x
        ];
        (vertices, faces)
    }

    #[test]
    fn cube_model_is_centred_scaled_and_has_outward_normals() {
        let (mut v, f) = cube_mesh(0.05);
        for p in v.iter_mut() {
            p[0] += 1.0; // off-origin mesh: the centre must be found
        }
        let model = StandardModel::from_mesh(&v, &f, 1024, 3).unwrap();
        assert_eq!(model.points.len(), 1024);
        assert!((model.centre[0] - 1.0).abs() < 2e-3 && model.centre[1].abs() < 2e-3);
        // Corners are at √3·0.05 from the centre; FPS keeps points near them.
        let radius = 1.0 / model.scale;
        assert!(
            (radius - 0.05 * 3f64.sqrt()).abs() < 3e-3,
            "radius {radius}"
        );
        assert!(
            (model.diameter - 0.1 * 3f64.sqrt()).abs() < 6e-3,
            "diameter {}",
            model.diameter
        );
        for (p, n) in model.points.iter().zip(&model.normals) {
            assert!(dot(*p, *n) > 0.0, "normal {n:?} at {p:?} points inward");
            assert!((norm(*n) - 1.0).abs() < 1e-5);
        }
        // Six faces of area 0.01 m² and 1024 points: spacing ≈ sqrt(0.06/1024).
        let expected = (0.06f64 / 1024.0).sqrt();
        assert!(
            model.spacing > 0.6 * expected && model.spacing < 1.4 * expected,
            "{}",
            model.spacing
        );
    }

    #[test]
    fn spacing_does_not_depend_on_the_thread_count() {
        let (v, f) = cube_mesh(0.05);
        let points = StandardModel::from_mesh(&v, &f, 4096, 5).unwrap().points;
        let with = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| mean_nearest_neighbour_distance(&points))
        };
        let one = with(1);
        for threads in [2, 3, 7] {
            assert_eq!(with(threads).to_bits(), one.to_bits(), "{threads} threads");
        }
    }

    #[test]
    fn inside_out_mesh_gets_its_normals_flipped() {
        let (v, mut f) = cube_mesh(0.05);
        for face in f.iter_mut() {
            face.swap(1, 2);
        }
        let model = StandardModel::from_mesh(&v, &f, 512, 3).unwrap();
        assert!(model
            .points
            .iter()
            .zip(&model.normals)
            .all(|(p, n)| dot(*p, *n) > 0.0));
    }

    #[test]
    fn sampling_is_area_weighted_and_seeded() {
        // Two triangles: one of area 0.5, one of area 0.05 (ten times smaller).
        let v = vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [5.0, 0.0, 0.0],
            [5.1, 0.0, 0.0],
            [5.0, 1.0, 0.0],
        ];
        let f = vec![[0, 1, 2], [3, 4, 5]];
        let (p, _) = sample_surface(&v, &f, 11_000, 9).unwrap();
        let big = p.iter().filter(|q| q[0] < 2.0).count() as f64;
        assert!((big / 11_000.0 - 10.0 / 11.0).abs() < 0.01);
        let (p2, _) = sample_surface(&v, &f, 11_000, 9).unwrap();
        assert_eq!(p, p2);
    }

    #[test]
    fn bad_meshes_give_named_errors() {
        let (v, _) = cube_mesh(0.05);
        assert_eq!(
            sample_surface(&v, &[], 10, 0),
            Err(GeometryError::Empty("mesh"))
        );
        assert_eq!(
            sample_surface(&v, &[[0, 1, 99]], 10, 0),
            Err(GeometryError::FaceIndexOutOfRange {
                face: 0,
                index: 99,
                vertices: 8
            })
        );
        assert_eq!(
            sample_surface(&v, &[[0, 0, 1]], 10, 0),
            Err(GeometryError::DegenerateMesh)
        );
        let mut nan = v.clone();
        nan[0][0] = f64::NAN;
        assert_eq!(
            sample_surface(&nan, &[[0, 1, 2]], 10, 0),
            Err(GeometryError::NonFinite("mesh vertices"))
        );
    }
}
