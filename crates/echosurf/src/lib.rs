//! echosurf: anatomical surfaces straight from tracked freehand 3D ultrasound.
//!
//! Data flows one way through the stage modules:
//! [`io`] (tracked sequences, calibration) -> [`segment`] (boundary bands) -> [`samples`] (3D points with
//! intensity) -> [`rbf`] (one biharmonic spline fitted to all samples) -> [`surface`] (iso-surface by
//! regularised marching tetrahedra) -> [`io`] (meshes). [`simulate`] makes test sweeps with ground truth,
//! [`metrics`] scores meshes against truth and [`render`] draws previews. No stage calls a later one.
//!
//! Geometry is `f64` throughout (glam `DVec3` / `DMat4`), in millimetres unless a name says otherwise.

pub mod bench;
pub mod budget;
pub mod error;
pub mod io;
pub mod mesh;
pub mod metrics;
pub mod pipeline;
pub mod progress;
pub mod rbf;
pub mod render;
pub mod resources;
pub mod samples;
pub mod segment;
pub mod simulate;
pub(crate) mod spatial;
pub mod surface;
pub mod voxel;

pub use error::{Error, FormatProblem, Result};
