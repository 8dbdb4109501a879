//! One error type for the whole library. Every error that comes from a user's file names that file, so a
//! user with a folder of sweeps can tell which one is broken and why.

use std::path::{Path, PathBuf};

/// What is wrong with a file's content. Tests match on this rather than on message text.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FormatProblem {
    /// The file ends before the data its header promises.
    Truncated,
    /// A header size disagrees with the data that is actually there (or is absurd).
    SizeMismatch,
    /// A compressed stream or binary section does not decode.
    Corrupt,
    /// A required field or element is absent.
    MissingField,
    /// A field is present but its value does not parse or is not finite.
    BadValue,
    /// A valid file of a kind or variant echosurf does not handle.
    Unsupported,
    /// A sequence in which no frame can be used.
    NoValidFrames,
    /// A transform needed to place the frames is missing.
    MissingTransform,
}

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The operating system refused to read or write a file.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A file's content is malformed or unusable.
    #[error("{}: {message}", path.display())]
    Format {
        path: PathBuf,
        problem: FormatProblem,
        message: String,
    },
    /// Parameters or in-memory data that cannot be processed (no file involved).
    #[error("{0}")]
    InvalidInput(String),
    /// A numerical procedure failed (singular system, no convergence, non-finite values).
    #[error("{0}")]
    Numerical(String),
    /// The work would exceed a memory or size budget; the message says what would fit.
    #[error("{0}")]
    ResourceLimit(String),
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    pub fn io(path: impl AsRef<Path>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.as_ref().to_path_buf(),
            source,
        }
    }

    pub fn format(
        path: impl AsRef<Path>,
        problem: FormatProblem,
        message: impl Into<String>,
    ) -> Self {
        Error::Format {
            path: path.as_ref().to_path_buf(),
            problem,
            message: message.into(),
        }
    }

    /// The format problem, if this is a file-content error.
    pub fn problem(&self) -> Option<FormatProblem> {
        match self {
            Error::Format { problem, .. } => Some(*problem),
            _ => None,
        }
    }
}
