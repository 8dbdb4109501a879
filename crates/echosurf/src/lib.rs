//! echosurf: anatomical surfaces straight from tracked freehand 3D ultrasound.
//!
//! Data flows one way through the stage modules:
//! [`io`] (tracked sequences, calibration) -> [`segment`] (boundary bands) -> [`samples`] (3D points with
//! intensity) -> [`rbf`] (one biharmonic spline fitted to all samples) -> [`surface`] (iso-surface by
//! regularised marching tetrahedra) -> [`io`] (meshes). [`metrics`] scores meshes against truth and
//! `render` (the `render` feature) draws previews. No stage calls a later one. The simulator
//! (`echosurf-sim`), the bench harness (`echosurf-bench`) and the test helpers (`echosurf-testkit`) are
//! crates of their own that depend on this one.
//!
//! Geometry is `f64` throughout (glam `DVec3` / `DMat4`), in millimetres unless a name says otherwise.
//!
//! A sphere of radius 5 mm, given as an analytic field, surfaced by the same regularised marching
//! tetrahedra that surface a fit (examples/ holds longer ones: a whole sweep, a fit, a custom field):
//!
//! ```
//! use echosurf::surface::{extract_surfaces, FnField, SurfaceDomain, SurfaceOptions};
//! use glam::DVec3;
//!
//! // Value 5 - |p|, positive inside; its gradient points inward.
//! let sphere = FnField(|p: DVec3| (5.0 - p.length(), -p.normalize_or_zero()));
//! let domain = SurfaceDomain {
//!     bounds_min_mm: DVec3::splat(-6.0),
//!     bounds_max_mm: DVec3::splat(6.0),
//!     ..SurfaceDomain::default()
//! };
//! let options = SurfaceOptions { resolution_mm: 1.0, ..SurfaceOptions::default() };
//! let meshes = extract_surfaces(&sphere, &[0.0], &domain, &options)?;
//! let mesh = &meshes[0];
//! assert!(mesh.topology().is_closed_manifold());
//! // Every vertex is moved onto the level, so it lies on the sphere to within the surfacer's tolerance.
//! let worst_mm = mesh.vertices.iter().map(|v| (v.length() - 5.0).abs()).fold(0.0, f64::max);
//! assert!(worst_mm < 1e-3, "a vertex lies {worst_mm} mm off the sphere");
//! # Ok::<(), echosurf::Error>(())
//! ```

pub mod budget;
pub mod error;
pub mod io;
pub mod line_echo;
pub mod mesh;
pub mod metrics;
pub mod pipeline;
pub mod progress;
pub mod rbf;
#[cfg(feature = "render")]
pub mod render;
pub mod resources;
pub mod samples;
pub mod segment;
mod serde_forms;
pub mod spatial;
pub mod surface;
pub mod voxel;

pub use error::{Error, FormatProblem, OptionName, OptionsErrorKind, Phrase, Result};
