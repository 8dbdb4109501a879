//! Standard output whose errors are reported rather than panicked on (`println!` panics): a closed
//! pipe (`echosurf inspect --json | head`) ends the run quietly, a full disk (`> /dev/full`) is an error.

use std::io::Write;

/// A failed write to standard output.
#[derive(Debug)]
pub struct StdoutError(pub std::io::Error);

impl std::fmt::Display for StdoutError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "writing to standard output: {}", self.0)
    }
}

impl std::error::Error for StdoutError {}

impl StdoutError {
    /// The reader went away (EPIPE): nothing is wrong with the run, only nobody reads on.
    pub fn is_broken_pipe(&self) -> bool {
        self.0.kind() == std::io::ErrorKind::BrokenPipe
    }
}

/// Writes to standard output (what `out!` and `outln!` call).
pub fn write_out(args: std::fmt::Arguments<'_>) -> Result<(), StdoutError> {
    std::io::stdout()
        .lock()
        .write_fmt(args)
        .map_err(StdoutError)
}

/// Flushes standard output, so an error on the last buffered bytes is reported too.
pub fn flush_out() -> Result<(), StdoutError> {
    std::io::stdout().lock().flush().map_err(StdoutError)
}

/// `print!` that returns the write error from the enclosing function (`?`).
macro_rules! out {
    ($($arg:tt)*) => {
        $crate::stdout::write_out(format_args!($($arg)*))?
    };
}

/// `println!` that returns the write error from the enclosing function (`?`).
macro_rules! outln {
    () => {
        $crate::stdout::write_out(format_args!("\n"))?
    };
    ($($arg:tt)*) => {
        $crate::stdout::write_out(format_args!("{}\n", format_args!($($arg)*)))?
    };
}
