//! The coordinate-system tag a mesh file carries (`SPACE=RAS`/`LPS`), read from and written into
//! each format's header.

use super::looks_like_ascii_stl;
use crate::mesh::Mesh;
use glam::DVec3;

/// The anatomical coordinate system a mesh file's numbers are in, as 3D Slicer names it: RAS (+x
/// right, +y anterior, +z superior) or LPS (+x left, +y posterior: x and y negated). echosurf's working
/// coordinates are RAS: the tracking frame's numbers as Slicer shows them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "UPPERCASE")]
pub enum Space {
    /// The working coordinates unchanged.
    #[default]
    Ras,
    /// x and y negated (a half turn about z: the winding of triangles stays valid).
    Lps,
}

impl Space {
    /// `RAS` or `LPS`, the spelling of the tag.
    pub fn name(self) -> &'static str {
        match self {
            Space::Ras => "RAS",
            Space::Lps => "LPS",
        }
    }

    /// The tag Slicer writes and looks for: `SPACE=RAS` or `SPACE=LPS`.
    pub fn tag(self) -> &'static str {
        match self {
            Space::Ras => "SPACE=RAS",
            Space::Lps => "SPACE=LPS",
        }
    }

    /// `ras` or `lps` (any case).
    pub fn parse(text: &str) -> Option<Space> {
        match text.trim().to_ascii_lowercase().as_str() {
            "ras" => Some(Space::Ras),
            "lps" => Some(Space::Lps),
            _ => None,
        }
    }

    /// The space a tag in `text` names, as Slicer finds it: the first of `SPACE=RAS`, `SPACE=LPS`
    /// anywhere in the text (RAS looked for first, as Slicer does).
    pub fn find_tag(text: &[u8]) -> Option<Space> {
        let has = |tag: &str| text.windows(tag.len()).any(|w| w == tag.as_bytes());
        if has(Space::Ras.tag()) {
            Some(Space::Ras)
        } else if has(Space::Lps.tag()) {
            Some(Space::Lps)
        } else {
            None
        }
    }

    /// `mesh` (in working RAS coordinates) in this space, or back: the change is its own inverse.
    pub fn convert(self, mesh: &Mesh) -> Mesh {
        match self {
            Space::Ras => mesh.clone(),
            Space::Lps => {
                let flip = |v: &DVec3| DVec3::new(-v.x, -v.y, v.z);
                Mesh {
                    vertices: mesh.vertices.iter().map(flip).collect(),
                    normals: mesh.normals.iter().map(flip).collect(),
                    triangles: mesh.triangles.clone(),
                }
            }
        }
    }
}

/// The first line of what echosurf writes into a mesh's comment or header: what it is and its space.
pub(super) fn header_text(space: Space) -> String {
    format!("echosurf mesh, mm. {}", space.tag())
}

/// The tag in a PLY header's first comment that has one.
pub(super) fn ply_space(bytes: &[u8]) -> Option<Space> {
    bytes
        .split(|&b| b == b'\n')
        .take_while(|line| line.trim_ascii() != b"end_header")
        .filter(|line| line.starts_with(b"comment") || line.starts_with(b"obj_info"))
        .find_map(Space::find_tag)
}

/// The tag in a binary STL's 80-byte header, or in an ASCII STL's `solid` line.
pub(super) fn stl_space(bytes: &[u8]) -> Option<Space> {
    let header = if looks_like_ascii_stl(bytes) {
        bytes.split(|&b| b == b'\n').next().unwrap_or_default()
    } else {
        &bytes[..bytes.len().min(80)]
    };
    Space::find_tag(header)
}

/// The tag in the comment lines an OBJ file opens with.
pub(super) fn obj_space(bytes: &[u8]) -> Option<Space> {
    bytes
        .split(|&b| b == b'\n')
        .map(<[u8]>::trim_ascii)
        .filter(|line| !line.is_empty())
        .take_while(|line| line.starts_with(b"#"))
        .find_map(Space::find_tag)
}
