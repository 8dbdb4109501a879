//! `--space ras|lps`, shared by every command that writes a mesh, and the coordinates every report
//! states (which tracking frame the numbers are in, and in which of Slicer's spaces they are written).

use echosurf::io::Space;

/// The coordinate system of the meshes a command writes.
#[derive(Debug, Clone, clap::Args)]
pub struct SpaceArg {
    /// Coordinates of the meshes written: `ras` (the tracking frame's own numbers, which is how 3D
    /// Slicer places a PLUS sequence loaded with the Sequences module, so the mesh overlays it) or
    /// `lps` (x and y negated). Each file is tagged SPACE=RAS or SPACE=LPS as Slicer reads it.
    #[arg(long = "space", default_value = "ras", value_parser = parse_space)]
    pub space: Space,
}

/// `ras` or `lps`, any case.
pub fn parse_space(text: &str) -> Result<Space, String> {
    Space::parse(text).ok_or_else(|| format!("`{text}`: expected ras or lps"))
}

/// `report` as JSON with a `coordinates` object: the tracking frame (`Reference` or `Tracker`) the
/// mesh coordinates are in, and the space they were written in.
pub fn with_coordinates(
    report: &impl serde::Serialize,
    frame: &str,
    space: Space,
) -> anyhow::Result<serde_json::Value> {
    let mut value = serde_json::to_value(report)?;
    let object = value
        .as_object_mut()
        .ok_or_else(|| anyhow::anyhow!("a report serialises to a JSON object"))?;
    object.insert(
        "coordinates".into(),
        serde_json::json!({ "frame": frame, "space": space }),
    );
    Ok(value)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spaces_parse_and_reports_state_frame_and_space() {
        assert_eq!(parse_space("LPS"), Ok(Space::Lps));
        assert_eq!(parse_space(" ras"), Ok(Space::Ras));
        assert!(parse_space("ijk").unwrap_err().contains("ras or lps"));
        let v = with_coordinates(&serde_json::json!({"a": 1}), "Reference", Space::Lps).unwrap();
        assert_eq!(v["coordinates"]["frame"], "Reference");
        assert_eq!(v["coordinates"]["space"], "LPS");
        assert_eq!(v["a"], 1);
        assert!(with_coordinates(&3, "Tracker", Space::Ras).is_err());
    }
}
