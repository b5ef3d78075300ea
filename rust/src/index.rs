//! The model's surface with a kd-tree, and rigid poses: shared by
//! verification ([`crate::search`]), scoring ([`crate::scoring`]) and ICP
//! ([`crate::refine`]).

use std::num::NonZero;

use kiddo::immutable::float::kdtree::ImmutableKdTree;
use kiddo::SquaredEuclidean;
use nalgebra::{Matrix3, Vector3};

use crate::Point3;

/// The model's kd-tree: leaves of 8 points, not kiddo's default 32. ICP,
/// scoring and verification query it tens of thousands of times per
/// estimate for points near the surface, where small leaves are faster:
/// ICP on 1,024 points × 20 iterations took 25–30 % less time on the YCB
/// models (e.g. 6.1 → 4.3 ms), 4 and 16 were slower, 128 twice as slow.
/// Nearest neighbours are exact whatever the leaf size.
type ModelTree = ImmutableKdTree<f32, u32, 3, 8>;

/// The model's points and normals with a kd-tree over the points (model
/// frame, metres). Immutable, so many threads may query it at once.
pub struct ModelIndex {
    tree: ModelTree,
    points: Vec<Point3>,
    normals: Vec<Point3>,
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
        Self {
            tree,
            points,
            normals,
        }
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

    /// Index and squared distance of the model point nearest to `p` (model frame).
    pub fn nearest(&self, p: &[f32; 3]) -> (usize, f32) {
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
