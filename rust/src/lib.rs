//! Geometry and search core of edgepose.
//!
//! Units are metres unless a name says otherwise; frames follow OpenCV
//! (x right, y down, z forward). Everything here builds and tests without
//! Python; the pyo3 layer lives in [`python`] behind the `python` feature.

pub mod confidence;
pub mod error;
pub mod flips;
pub mod grouping;
pub mod hypotheses;
pub mod index;
pub mod maps;
pub mod model;
pub mod pairs;
pub mod query;
pub mod refine;
pub mod rng;
pub mod sampling;
pub mod scoring;
pub mod search;
pub mod segment;
pub mod support;
pub mod threads;
pub mod track;
pub mod views;
pub mod visibility;

#[cfg(feature = "python")]
mod python;

/// A point or vector in 3-D, single precision (clouds and maps).
pub type Point3 = [f32; 3];

pub use error::GeometryError;
pub use grouping::{features_of_maps, map_neighbours, MapFeatures};
pub use index::{ModelIndex, Pose};
pub use maps::{compute_maps, normalize_to_map, view_map, Maps, ViewMap};
pub use model::StandardModel;
pub use query::{
    back_project, clean_cloud, clean_depth_cloud, prepare_query, CleanSettings, CloudProblem,
    Pinhole, Query, QuerySettings,
};
pub use refine::IcpResult;
pub use sampling::farthest_point_sample;
pub use scoring::{score_poses, DepthGrid, PoseScore, SceneDepth, ScoreSettings};
pub use search::{top_k, verify};
pub use segment::{segment, SegmentSettings, Segmentation};
pub use support::{on_support_plane, SupportSettings};
pub use views::{fibonacci_directions, ray_alignment, view_rotation, viewpoints, Rotation};
pub use visibility::visible_mask;
