//! The crate's spatial indexes, one per kind of query:
//!
//! - [`PointBuckets`] (`point_buckets.rs`): points in a uniform grid of buckets, for "any / every point
//!   within a radius" (region of trust, the oriented-point sheet, echoes backing a mesh piece).
//! - [`KdTree`] (`kdtree.rs`): points split by count into cells that tile a box, with box queries (the
//!   partition-of-unity fit's patches).
//! - [`BoxTree`] (`box_tree.rs`): a bounding-volume hierarchy over boxes, for "which boxes hold this
//!   point" (the partition of unity's weight supports) and "which item is nearest" under an exact
//!   distance; [`TriangleBvh`] (`triangle_bvh.rs`) is it over a mesh's triangles, with
//!   [`closest_point_on_triangle`] (`triangle.rs`) as the distance (the comparison's distances, the
//!   simulator's mesh phantoms).
//! - `cell_grid.rs`: packed integer cell keys and the hash maps and sets keyed by them (the surfacing
//!   lattice's nodes, cells and edges; the buckets' order).
//!
//! The fast solver's tree (`rbf::tree`) is not among them: it is the treecode's cluster tree (tight
//! boxes carrying interpolation proxies), not a query index.

mod box_tree;
pub(crate) mod cell_grid;
mod kdtree;
mod point_buckets;
mod triangle;
mod triangle_bvh;

pub(crate) use box_tree::BoxTree;
pub(crate) use kdtree::KdTree;
pub use point_buckets::PointBuckets;
pub use triangle::{TriangleFeature, closest_feature_on_triangle, closest_point_on_triangle};
pub use triangle_bvh::{Nearest, TriangleBvh};
