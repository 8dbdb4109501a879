//! PLUS device-set configuration XML: the Image->Probe calibration and the volume reconstruction settings.

use std::path::Path;

use super::sequence::Calibration;
use crate::{Error, Result};

pub fn read_calibration(path: &Path) -> Result<Calibration> {
    let _ = path;
    Err(Error::InvalidInput(
        "PLUS config reading is not implemented yet".into(),
    ))
}

/// Writes a minimal PLUS device set holding the calibration (and clip rectangle) that PLUS and echosurf read.
pub fn write_calibration(path: &Path, calibration: &Calibration) -> Result<()> {
    let _ = (path, calibration);
    Err(Error::InvalidInput(
        "PLUS config writing is not implemented yet".into(),
    ))
}
