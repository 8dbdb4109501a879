//! Checks on where a command writes, made before any work, so a mistake costs no minutes of
//! computing and destroys nothing: an output never replaces one of the run's inputs (`segment
//! sweep.mha --out sweep.mha` would otherwise destroy the recording), no two outputs of one run share
//! a file (the later would silently replace the earlier), each output's name ends in the extension of
//! what is written into it (a PNG picture is not written into `view.jpg`), and its folder exists.

use std::path::{Path, PathBuf};

use echosurf::io::atomic::{Destination, destination};
use echosurf::io::mesh_io::MESH_EXTENSIONS;

/// What an output file holds, which fixes the extensions its name may end in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Holds {
    /// A triangle mesh: PLY, STL, OBJ or VTK, chosen by the extension.
    Mesh,
    /// A PNG picture.
    Png,
    /// A PLUS MetaImage sequence or volume.
    MetaImage,
    /// A PLY point cloud.
    PointCloud,
    /// A PLY mesh with per-vertex values and colours.
    ColouredMesh,
    /// JSON, a model: whatever the name.
    AnyName,
}

impl Holds {
    fn extensions(self) -> &'static [&'static str] {
        match self {
            Holds::Mesh => &MESH_EXTENSIONS,
            Holds::Png => &["png"],
            Holds::MetaImage => &["mha"],
            Holds::PointCloud | Holds::ColouredMesh => &["ply"],
            Holds::AnyName => &[],
        }
    }

    fn description(self) -> &'static str {
        match self {
            Holds::Mesh => "a mesh is written as PLY, STL, OBJ or VTK by the extension",
            Holds::Png => "the picture is written as PNG",
            Holds::MetaImage => "this is written as a MetaImage file with its data inside",
            Holds::PointCloud => "the point cloud is written as PLY",
            Holds::ColouredMesh => "a mesh with vertex colours is written as PLY",
            Holds::AnyName => "",
        }
    }
}

/// One file a command will write.
#[derive(Debug, Clone)]
pub struct Output {
    /// The option that names it, as the user typed it (`--out`, `--preview`).
    pub option: String,
    pub path: PathBuf,
    pub holds: Holds,
}

/// An output file, the option that names it and what it holds.
pub fn output(option: impl Into<String>, path: &Path, holds: Holds) -> Output {
    Output {
        option: option.into(),
        path: path.to_path_buf(),
        holds,
    }
}

/// Refuses an output that is the same file as one of `inputs` or as another output, whose name does
/// not end in an extension of what it holds, that is a folder or a special file other than a character
/// device, whose folder does not exist, or that cannot be written. Paths are compared resolved (links
/// followed, `.`/`..` removed) and existing files also by device and inode, so `./a.mha`, `dir/../a.mha`,
/// a hard or symbolic link to it are one file; an output that does not exist yet is resolved through
/// its folder. Writability is tried for real (a probe file created and removed), so a read-only folder
/// fails here rather than after the work.
pub fn check_outputs(inputs: &[PathBuf], outputs: &[Output]) -> anyhow::Result<()> {
    let inputs: Vec<(PathBuf, Option<FileId>, &PathBuf)> = inputs
        .iter()
        .map(|p| (resolved(p), file_id(p), p))
        .collect();
    let mut seen: Vec<(PathBuf, &str)> = Vec::with_capacity(outputs.len());
    for Output {
        option,
        path,
        holds,
    } in outputs
    {
        let destination = destination(path).map_err(|e| anyhow::anyhow!("{option} {e}"))?;
        let device = matches!(destination, Destination::Direct(_));
        let target = match &destination {
            Destination::File(p) | Destination::Direct(p) => resolved(p),
        };
        let id = file_id(&target);
        if let Some((_, _, input)) = inputs
            .iter()
            .find(|(p, input_id, _)| *p == target || (id.is_some() && *input_id == id))
        {
            anyhow::bail!(
                "{option} {}: that is {}, an input of this run; echosurf does not write over what it \
                 reads, so name another output file",
                path.display(),
                input.display()
            );
        }
        if let Some((_, earlier)) = seen.iter().find(|(p, _)| *p == target && !device) {
            anyhow::bail!(
                "{earlier} and {option} both name {}; each output needs a file of its own",
                path.display()
            );
        }
        let extensions = holds.extensions();
        let extension = path
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase());
        if !extensions.is_empty() && !extension.is_some_and(|e| extensions.contains(&e.as_str())) {
            let listed: Vec<String> = extensions.iter().map(|e| format!(".{e}")).collect();
            anyhow::bail!(
                "{option} {}: {}, so the file name must end in {}",
                path.display(),
                holds.description(),
                listed.join(", ")
            );
        }
        match &destination {
            Destination::Direct(device) => {
                std::fs::OpenOptions::new()
                    .append(true)
                    .open(device)
                    .map_err(|e| {
                        anyhow::anyhow!("{option} {}: cannot write to it: {e}", path.display())
                    })?;
            }
            Destination::File(file) => {
                let folder = folder_of(file);
                if !folder.is_dir() {
                    anyhow::bail!(
                        "{option} {}: the folder {} does not exist (echosurf does not create it)",
                        path.display(),
                        folder.display()
                    );
                }
                check_writable_folder(folder)
                    .map_err(|e| anyhow::anyhow!("{option} {}: {e}", path.display()))?;
            }
        }
        seen.push((target, option));
    }
    Ok(())
}

/// Refuses a folder echosurf cannot create files in: creates a hidden probe file there and removes it
/// (permission bits say nothing of a read-only mount, ACLs or running as root).
pub fn check_writable_folder(folder: &Path) -> anyhow::Result<()> {
    let probe = folder.join(format!(".echosurf-probe-{}", std::process::id()));
    match std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
    {
        Ok(_) => {
            let _ = std::fs::remove_file(&probe);
            Ok(())
        }
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(()),
        Err(e) => anyhow::bail!(
            "cannot create files in the folder {}: {e}",
            folder.display()
        ),
    }
}

/// Device and inode of an existing file (links followed), which identify it whatever the path.
type FileId = (u64, u64);

fn file_id(path: &Path) -> Option<FileId> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        std::fs::metadata(path).ok().map(|m| (m.dev(), m.ino()))
    }
    #[cfg(not(unix))]
    {
        let _ = path;
        None
    }
}

/// The path with links and `.`/`..` resolved; for a file not there yet, its folder's resolved path
/// joined with its name; as given if even the folder cannot be resolved (the write then says why).
fn resolved(path: &Path) -> PathBuf {
    if let Ok(full) = path.canonicalize() {
        return full;
    }
    match path.file_name() {
        Some(name) => folder_of(path)
            .canonicalize()
            .map(|d| d.join(name))
            .unwrap_or_else(|_| path.to_path_buf()),
        None => path.to_path_buf(),
    }
}

/// The folder a file goes in: its parent, or the working folder for a bare name.
fn folder_of(path: &Path) -> &Path {
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    }
}

#[cfg(test)]
mod tests {
    use super::{Holds, check_outputs, output};
    use std::path::{Path, PathBuf};

    #[test]
    fn an_output_that_is_an_input_or_another_output_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("sweep.mha");
        std::fs::write(&input, b"data").unwrap();
        std::fs::create_dir(dir.path().join("sub")).unwrap();
        let inputs = vec![input.clone()];
        let roundabout = dir.path().join("sub").join("..").join("sweep.mha");
        let err = check_outputs(&inputs, &[output("--out", &roundabout, Holds::MetaImage)])
            .unwrap_err()
            .to_string();
        assert!(
            err.starts_with("--out ") && err.contains("an input"),
            "{err}"
        );
        #[cfg(unix)]
        {
            let link = dir.path().join("link.mha");
            std::os::unix::fs::symlink(&input, &link).unwrap();
            assert!(check_outputs(&inputs, &[output("--out", &link, Holds::MetaImage)]).is_err());
        }

        let mesh = dir.path().join("mesh.ply");
        let same_mesh = dir.path().join("sub").join("..").join("mesh.ply");
        let report = dir.path().join("report.json");
        let err = check_outputs(
            &inputs,
            &[
                output("--out", &mesh, Holds::Mesh),
                output("--report", &report, Holds::AnyName),
                output("--samples", &same_mesh, Holds::PointCloud),
            ],
        )
        .unwrap_err()
        .to_string();
        assert!(err.starts_with("--out and --samples both name"), "{err}");

        let preview = dir.path().join("mesh.png");
        let outputs = [
            output("--out", &mesh, Holds::Mesh),
            output("--preview", &preview, Holds::Png),
        ];
        check_outputs(&inputs, &outputs).unwrap();
        let folder_named_ply = dir.path().join("folder.ply");
        std::fs::create_dir(&folder_named_ply).unwrap();
        let err = check_outputs(&inputs, &[output("--out", &folder_named_ply, Holds::Mesh)])
            .unwrap_err()
            .to_string();
        assert!(err.contains("that is a folder; name a file"), "{err}");
        let nowhere = dir.path().join("missing").join("mesh.ply");
        let err = check_outputs(&inputs, &[output("--out", &nowhere, Holds::Mesh)])
            .unwrap_err()
            .to_string();
        assert!(err.contains("missing does not exist"), "{err}");
        // A relative output with no folder part is resolved in the working folder.
        check_outputs(&inputs, &[output("--out", Path::new("m.ply"), Holds::Mesh)]).unwrap();
        let gone = [PathBuf::from("/nonexistent/a.mha")];
        check_outputs(&gone, &[output("--out", &mesh, Holds::Mesh)]).unwrap();
    }

    #[test]
    fn an_output_named_for_another_format_is_refused() {
        let refused = |name: &str, holds: Holds| {
            let outputs = [output("--out", Path::new(name), holds)];
            check_outputs(&[], &outputs).map_err(|e| e.to_string())
        };
        for name in ["m.ply", "m.STL", "m.obj"] {
            assert!(refused(name, Holds::Mesh).is_ok(), "{name}");
        }
        let err = refused("m.xyz", Holds::Mesh).unwrap_err();
        assert!(err.ends_with("must end in .ply, .stl, .obj, .vtk"), "{err}");
        assert!(refused("mesh", Holds::Mesh).is_err());
        assert!(refused("view.jpg", Holds::Png).unwrap_err().contains("PNG"));
        assert!(refused("view.PNG", Holds::Png).is_ok());
        assert!(refused("masks.png", Holds::MetaImage).is_err());
        assert!(refused("masks.seq.mha", Holds::MetaImage).is_ok());
        assert!(refused("points.stl", Holds::PointCloud).is_err());
        assert!(refused("report.txt", Holds::AnyName).is_ok());
        assert!(refused("model", Holds::AnyName).is_ok());
    }
}
