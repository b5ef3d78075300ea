//! Errors of the geometry core. Each names the input problem plainly; the
//! Python layer turns them into `edgepose` exceptions.

use std::fmt;

#[derive(Debug, Clone, PartialEq)]
pub enum GeometryError {
    /// A mesh or cloud with nothing in it.
    Empty(&'static str),
    /// A face refers to a vertex that does not exist.
    FaceIndexOutOfRange {
        face: usize,
        index: u32,
        vertices: usize,
    },
    /// All faces have zero area: nothing to sample.
    DegenerateMesh,
    /// NaN or infinite coordinates where finite ones are required.
    NonFinite(&'static str),
    /// Two arrays that must pair up have different lengths.
    LengthMismatch {
        what: &'static str,
        left: usize,
        right: usize,
    },
    /// A parameter outside its valid range.
    InvalidParameter(String),
}

impl fmt::Display for GeometryError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Empty(what) => write!(f, "{what} is empty"),
            Self::FaceIndexOutOfRange {
                face,
                index,
                vertices,
            } => write!(
                f,
                "face {face} refers to vertex {index}, but the mesh has only {vertices} vertices"
            ),
            Self::DegenerateMesh => write!(f, "mesh has zero surface area (all faces degenerate)"),
            Self::NonFinite(what) => write!(f, "{what} contains NaN or infinite values"),
            Self::LengthMismatch { what, left, right } => {
                write!(f, "{what}: lengths differ ({left} vs {right})")
            }
            Self::InvalidParameter(msg) => write!(f, "{msg}"),
        }
    }
}

impl std::error::Error for GeometryError {}
