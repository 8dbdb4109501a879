//! Checks on where a command writes, made before any work: an output never replaces one of the run's
//! inputs (`segment sweep.mha --out sweep.mha` would otherwise destroy the recording), and no two
//! outputs of one run share a file (the later would silently replace the earlier).

use std::path::{Path, PathBuf};

/// Refuses `outputs` (each with the option that names it) that are the same file as one of `inputs`
/// or as each other. Paths are compared resolved, so `./a.mha`, `dir/../a.mha` and a symbolic link to
/// it are one file; an output that does not exist yet is resolved through its folder.
pub fn refuse_overwriting_inputs(
    inputs: &[PathBuf],
    outputs: &[(String, PathBuf)],
) -> anyhow::Result<()> {
    let inputs: Vec<(PathBuf, &PathBuf)> = inputs.iter().map(|p| (resolved(p), p)).collect();
    let mut seen: Vec<(PathBuf, &str)> = Vec::with_capacity(outputs.len());
    for (option, output) in outputs {
        let target = resolved(output);
        if let Some((_, input)) = inputs.iter().find(|(p, _)| *p == target) {
            anyhow::bail!(
                "{option} {}: that is {}, an input of this run; echosurf does not write over what it \
                 reads, so name another output file",
                output.display(),
                input.display()
            );
        }
        if let Some((_, earlier)) = seen.iter().find(|(p, _)| *p == target) {
            anyhow::bail!(
                "{earlier} and {option} both name {}; each output needs a file of its own",
                output.display()
            );
        }
        seen.push((target, option));
    }
    Ok(())
}

/// An output file and the option that names it, as [`refuse_overwriting_inputs`] takes them.
pub fn output(option: impl Into<String>, path: &Path) -> (String, PathBuf) {
    (option.into(), path.to_path_buf())
}

/// The path with links and `.`/`..` resolved; for a file not there yet, its folder's resolved path
/// joined with its name; as given if even the folder cannot be resolved (the write then says why).
fn resolved(path: &Path) -> PathBuf {
    if let Ok(full) = path.canonicalize() {
        return full;
    }
    match (path.parent(), path.file_name()) {
        (Some(dir), Some(name)) => {
            let dir = if dir.as_os_str().is_empty() {
                Path::new(".")
            } else {
                dir
            };
            dir.canonicalize()
                .map(|d| d.join(name))
                .unwrap_or_else(|_| path.to_path_buf())
        }
        _ => path.to_path_buf(),
    }
}

#[cfg(test)]
mod tests {
    use super::{output, refuse_overwriting_inputs};
    use std::path::{Path, PathBuf};

    #[test]
    fn an_output_that_is_an_input_or_another_output_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("sweep.mha");
        std::fs::write(&input, b"data").unwrap();
        std::fs::create_dir(dir.path().join("sub")).unwrap();
        let inputs = vec![input.clone()];
        let roundabout = dir.path().join("sub").join("..").join("sweep.mha");
        let err = refuse_overwriting_inputs(&inputs, &[output("--out", &roundabout)])
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
            assert!(refuse_overwriting_inputs(&inputs, &[output("--out", &link)]).is_err());
        }

        let mesh = dir.path().join("mesh.ply");
        let same_mesh = dir.path().join("sub").join("..").join("mesh.ply");
        let err = refuse_overwriting_inputs(
            &inputs,
            &[output("--out", &mesh), output("--preview", &same_mesh)],
        )
        .unwrap_err()
        .to_string();
        assert!(err.starts_with("--out and --preview both name"), "{err}");

        let preview = dir.path().join("mesh.png");
        refuse_overwriting_inputs(
            &inputs,
            &[output("--out", &mesh), output("--preview", &preview)],
        )
        .unwrap();
        // A relative output with no folder part is resolved in the working folder.
        refuse_overwriting_inputs(&inputs, &[output("--out", Path::new("mesh.ply"))]).unwrap();
        refuse_overwriting_inputs(
            &[PathBuf::from("/nonexistent/a.mha")],
            &[output("--out", &mesh)],
        )
        .unwrap();
    }
}
