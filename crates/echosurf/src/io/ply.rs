//! Point-cloud PLY: `vertex` with float `x y z` plus named float scalar properties (binary little-endian
//! written, ASCII and binary accepted on input, extra properties kept).

use std::path::Path;

use glam::DVec3;

use crate::{Error, Result};

/// Points (mm, Reference frame) with named per-point scalars such as `intensity`, `value`, `gx`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PointCloud {
    pub positions: Vec<DVec3>,
    /// (name, one value per point), in file order.
    pub scalars: Vec<(String, Vec<f32>)>,
}

impl PointCloud {
    /// The scalar called `name`, if present.
    pub fn scalar(&self, name: &str) -> Option<&[f32]> {
        self.scalars
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_slice())
    }
}

pub fn read_point_cloud(path: &Path) -> Result<PointCloud> {
    let _ = path;
    Err(Error::InvalidInput(
        "PLY point reading is not implemented yet".into(),
    ))
}

pub fn write_point_cloud(path: &Path, cloud: &PointCloud) -> Result<()> {
    let _ = (path, cloud);
    Err(Error::InvalidInput(
        "PLY point writing is not implemented yet".into(),
    ))
}
