//! NRRD PLUS sequence reader (`.igs.nrrd`, raw or gzip encoding, `key:=value` custom fields).

use std::path::Path;

use super::sequence::TrackedSequence;
use crate::{Error, Result};

pub fn read_sequence(path: &Path) -> Result<TrackedSequence> {
    let _ = path;
    Err(Error::InvalidInput(
        "NRRD reading is not implemented yet".into(),
    ))
}
