//! Atomic output: data goes to a hidden temporary file in the destination folder, which is renamed over
//! the destination only once it is complete and flushed. A crash or Ctrl-C leaves the old file (or none).
//!
//! An application that handles Ctrl-C installs a [`TempFileRegistry`] to learn of the temporary files
//! in flight and remove them (the CLI does); after a SIGKILL nothing can run, so the next write into the
//! same folder removes leftovers whose process is gone ([`remove_stale_temp_files`]).

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use crate::{Error, Result};

/// Learns of the temporary files [`write_atomic`] creates, so an application's Ctrl-C or
/// out-of-memory handler can remove the unfinished ones. The application owns the registry (its paths,
/// its lock, its handler) and installs it once with [`set_temp_file_registry`].
pub trait TempFileRegistry: Sync {
    /// `tmp` is about to be created.
    fn add(&self, tmp: &Path);
    /// `tmp` is finished with: run `settle` (its rename into place, or its removal) and forget `tmp`,
    /// as one step for a handler that removes the registered files (so it sees every temporary file
    /// either still in flight or already renamed).
    fn settle(&self, tmp: &Path, settle: &mut dyn FnMut());
}

/// The registry the application installed, if any: set once by the application, never by the
/// library.
static REGISTRY: OnceLock<&'static dyn TempFileRegistry> = OnceLock::new();

/// Installs the application's registry of temporary files; false if one was installed already.
pub fn set_temp_file_registry(registry: &'static dyn TempFileRegistry) -> bool {
    REGISTRY.set(registry).is_ok()
}

const TEMP_MARKER: &str = ".echosurf-tmp-";

/// Where an output's bytes go, once links are followed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Destination {
    /// A regular file (existing or not yet there), written through a temporary file and a rename.
    File(PathBuf),
    /// A character device such as `/dev/null`, or one of this process's open streams (`/dev/stdout`,
    /// `/dev/fd/N`, `/proc/self/fd/N`): written to directly (appended to), never replaced.
    Direct(PathBuf),
}

/// This process's own open files by number: the kernel's links there name pipes and terminals that
/// cannot be followed as paths, and replacing what they point at would pull a file from under the shell.
fn is_own_stream(path: &Path) -> bool {
    let text = path.to_string_lossy();
    matches!(text.as_ref(), "/dev/stdout" | "/dev/stderr")
        || ["/dev/fd/", "/proc/self/fd/", "/proc/thread-self/fd/"]
            .iter()
            .any(|prefix| text.starts_with(prefix))
}

/// Where writing `path` puts the bytes: a symbolic link is followed to its target (which is then
/// written atomically; a link whose target is not there yet names the file to create); a character
/// device or an open stream of this process (`/dev/stdout`) is written directly; a folder, FIFO,
/// socket or block device is refused.
pub fn destination(path: &Path) -> Result<Destination> {
    let mut target = path.to_path_buf();
    // Follow a chain of links by hand: `canonicalize` fails on a link whose target does not exist yet.
    for _ in 0..40 {
        if is_own_stream(&target) {
            return Ok(Destination::Direct(target));
        }
        let Ok(meta) = std::fs::symlink_metadata(&target) else {
            return Ok(Destination::File(target));
        };
        if meta.file_type().is_symlink() {
            let link = std::fs::read_link(&target).map_err(|e| Error::io(path, e))?;
            target = match target.parent() {
                Some(dir) if link.is_relative() => dir.join(link),
                _ => link,
            };
            continue;
        }
        return classify(path, target, &meta);
    }
    Err(Error::InvalidInput(format!(
        "{}: too many levels of symbolic links",
        path.display()
    )))
}

fn classify(path: &Path, target: PathBuf, meta: &std::fs::Metadata) -> Result<Destination> {
    let kind = meta.file_type();
    if kind.is_file() {
        return Ok(Destination::File(target));
    }
    if kind.is_dir() {
        return Err(Error::InvalidInput(format!(
            "{}: that is a folder; name a file",
            path.display()
        )));
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if kind.is_char_device() {
            return Ok(Destination::Direct(target));
        }
        let what = if kind.is_block_device() {
            "a block device"
        } else if kind.is_fifo() {
            "a named pipe (FIFO)"
        } else if kind.is_socket() {
            "a socket"
        } else {
            "a special file"
        };
        Err(Error::InvalidInput(format!(
            "{}: that is {what}, not a regular file; echosurf writes only regular files and \
             character devices such as /dev/null",
            path.display()
        )))
    }
    #[cfg(not(unix))]
    Err(Error::InvalidInput(format!(
        "{}: not a regular file",
        path.display()
    )))
}

/// Writes `path` atomically: `fill` writes the whole content into a buffered temporary file, renamed
/// over the destination when complete. A symbolic link is followed (its target is replaced, the link
/// stays); a character device is written directly; other special files are refused ([`destination`]).
pub fn write_atomic<F>(path: &Path, fill: F) -> Result<()>
where
    F: FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
{
    let target = match destination(path)? {
        Destination::File(target) => target,
        Destination::Direct(device) => return write_direct(path, &device, fill),
    };
    let tmp = temp_path(&target);
    remove_stale_temp_files(tmp.parent().unwrap_or(Path::new(".")));
    let registry = REGISTRY.get();
    if let Some(registry) = registry {
        registry.add(&tmp);
    }
    let mut written = Some((|| -> std::io::Result<()> {
        let file = File::create(&tmp)?;
        let mut writer = BufWriter::with_capacity(1 << 20, file);
        fill(&mut writer)?;
        writer.flush()?;
        let file = writer.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()?;
        Ok(())
    })());
    let mut outcome = Ok(());
    let mut settle = || {
        outcome = match written.take() {
            Some(Ok(())) => std::fs::rename(&tmp, &target).map_err(|e| {
                let _ = std::fs::remove_file(&tmp);
                Error::io(path, e)
            }),
            Some(Err(e)) => {
                let _ = std::fs::remove_file(&tmp);
                Err(Error::io(path, e))
            }
            None => Ok(()),
        };
    };
    match registry {
        Some(registry) => registry.settle(&tmp, &mut settle),
        None => settle(),
    }
    outcome
}

/// Writes straight into a device or stream (no temporary file: it cannot be replaced). Appends, so
/// `>> log` behind `/dev/stdout` keeps what was there.
fn write_direct<F>(path: &Path, device: &Path, fill: F) -> Result<()>
where
    F: FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
{
    let result = (|| -> std::io::Result<()> {
        let file = std::fs::OpenOptions::new().append(true).open(device)?;
        let mut writer = BufWriter::with_capacity(1 << 16, file);
        fill(&mut writer)?;
        writer.flush()
    })();
    result.map_err(|e| Error::io(path, e))
}

/// Removes `.NAME.echosurf-tmp-PID` files in `dir` left by echosurf processes that no longer run (killed
/// with SIGKILL mid-write). Liveness is read from `/proc/PID`; where `/proc` is absent nothing is removed.
/// Returns how many files were removed.
pub fn remove_stale_temp_files(dir: &Path) -> usize {
    if !Path::new("/proc/self").exists() {
        return 0;
    }
    let dir = if dir.as_os_str().is_empty() {
        Path::new(".")
    } else {
        dir
    };
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    let me = std::process::id();
    let mut removed = 0;
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        if !name.starts_with('.') {
            continue;
        }
        let Some(pid) = name
            .rsplit_once(TEMP_MARKER)
            .and_then(|(_, pid)| pid.parse::<u32>().ok())
        else {
            continue;
        };
        if pid == me || Path::new(&format!("/proc/{pid}")).exists() {
            continue;
        }
        if entry.file_type().is_ok_and(|t| t.is_file())
            && std::fs::remove_file(entry.path()).is_ok()
        {
            removed += 1;
        }
    }
    removed
}

/// Writes bytes atomically.
pub fn write_bytes_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic(path, |w| w.write_all(bytes))
}

/// `dir/.name.echosurf-tmp-PID`: hidden, in the same folder (so rename stays on one file system), and
/// recognisable so a later cleanup can remove leftovers of a killed run.
pub fn temp_path(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "output".into());
    let tmp_name = format!(".{name}{TEMP_MARKER}{}", std::process::id());
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir.join(tmp_name),
        _ => PathBuf::from(tmp_name),
    }
}

/// Writes an 8-bit PNG atomically: `pixels` row-major, `colour` samples per pixel (grey, RGB, ...).
pub fn write_png_atomic(
    path: &Path,
    width: u32,
    height: u32,
    colour: png::ColorType,
    pixels: &[u8],
) -> Result<()> {
    if pixels.len() != width as usize * height as usize * colour.samples() {
        return Err(Error::InvalidInput(format!(
            "{}: image buffer does not match {width}x{height} {colour:?}",
            path.display()
        )));
    }
    write_atomic(path, |w| encode_png8(w, width, height, colour, pixels))
}

/// Encodes an 8-bit PNG (deterministic bytes); the caller checks that `pixels` fits the size.
pub fn encode_png8(
    w: impl Write,
    width: u32,
    height: u32,
    colour: png::ColorType,
    pixels: &[u8],
) -> std::io::Result<()> {
    let mut encoder = png::Encoder::new(w, width, height);
    encoder.set_color(colour);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header().map_err(std::io::Error::other)?;
    writer
        .write_image_data(pixels)
        .map_err(std::io::Error::other)?;
    writer.finish().map_err(std::io::Error::other)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn failed_write_leaves_no_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.bin");
        let err = write_atomic(&path, |w| {
            w.write_all(b"partial")?;
            Err(std::io::Error::other("interrupted"))
        });
        assert!(err.is_err());
        assert!(!path.exists());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn stale_temp_files_of_dead_processes_are_removed_live_ones_kept() {
        let dir = tempfile::tempdir().unwrap();
        // PIDs are below 2^22 on Linux, so this one cannot be running.
        let dead = dir.path().join(".mesh.ply.echosurf-tmp-4194999");
        let mine = temp_path(&dir.path().join("model.esrbf"));
        let unrelated = dir.path().join(".hidden-user-file");
        for p in [&dead, &mine, &unrelated] {
            std::fs::write(p, b"x").unwrap();
        }
        write_bytes_atomic(&dir.path().join("out.bin"), b"data").unwrap();
        if Path::new("/proc/self").exists() {
            assert!(!dead.exists());
        }
        assert!(mine.exists(), "a live process's temp file must stay");
        assert!(unrelated.exists());
        assert!(dir.path().join("out.bin").exists());
    }

    #[cfg(unix)]
    #[test]
    fn a_link_is_followed_and_its_target_replaced_a_device_written_directly() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("target.bin");
        std::fs::write(&target, b"old").unwrap();
        let link = dir.path().join("link.bin");
        std::os::unix::fs::symlink("target.bin", &link).unwrap();
        write_bytes_atomic(&link, b"new").unwrap();
        assert!(
            std::fs::symlink_metadata(&link)
                .unwrap()
                .file_type()
                .is_symlink()
        );
        assert_eq!(std::fs::read(&target).unwrap(), b"new");
        // A dangling link names the file to create.
        let dangling = dir.path().join("dangling.bin");
        std::os::unix::fs::symlink("made.bin", &dangling).unwrap();
        write_bytes_atomic(&dangling, b"made").unwrap();
        assert_eq!(std::fs::read(dir.path().join("made.bin")).unwrap(), b"made");
        let null = Path::new("/dev/null");
        if null.exists() {
            assert_eq!(destination(null).unwrap(), Destination::Direct(null.into()));
            write_bytes_atomic(null, b"gone").unwrap();
            assert_eq!(
                destination(Path::new("/dev/stdout")).unwrap(),
                Destination::Direct("/dev/stdout".into())
            );
            use std::os::unix::fs::FileTypeExt;
            assert!(
                std::fs::metadata(null)
                    .unwrap()
                    .file_type()
                    .is_char_device()
            );
        }
        let err = write_bytes_atomic(dir.path(), b"x")
            .unwrap_err()
            .to_string();
        assert!(err.contains("folder"), "{err}");
    }

    #[test]
    fn replaces_existing_file_whole() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.bin");
        std::fs::write(&path, b"old").unwrap();
        write_bytes_atomic(&path, b"new content").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"new content");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }
}
