//! MetaImage (`.mha`, `.mhd` + `.raw`/`.zraw`) PLUS sequence reader and writer.

use std::path::Path;

use super::sequence::TrackedSequence;
use crate::{Error, Result};

pub fn read_sequence(path: &Path) -> Result<TrackedSequence> {
    let _ = path;
    Err(Error::InvalidInput(
        "MetaImage reading is not implemented yet".into(),
    ))
}

pub fn write_sequence(path: &Path, sequence: &TrackedSequence, compress: bool) -> Result<()> {
    let _ = (path, sequence, compress);
    Err(Error::InvalidInput(
        "MetaImage writing is not implemented yet".into(),
    ))
}
