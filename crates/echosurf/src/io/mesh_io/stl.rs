//! Meshes as STL: binary writer; binary and ASCII reader, welding the triangle soup's corners.

use super::Space;
use super::header_text;
use super::write_f32s;
use crate::Error;
use crate::FormatProblem;
use crate::Result;
use crate::mesh::Mesh;
use glam::DVec3;
use std::collections::HashMap;
use std::io::Write;
use std::path::Path;

pub(super) fn write_stl(path: &Path, mesh: &Mesh, space: Space) -> Result<()> {
    crate::io::atomic::write_atomic(path, |w| {
        // The header must not start with "solid", or readers may take the file for ASCII STL.
        let mut header = [b' '; 80];
        let text = header_text(space);
        header[..text.len()].copy_from_slice(text.as_bytes());
        w.write_all(&header)?;
        w.write_all(&(mesh.triangles.len() as u32).to_le_bytes())?;
        for &t in &mesh.triangles {
            let n = mesh.triangle_unit_normal(t);
            write_f32s(w, &[n.x, n.y, n.z])?;
            for i in t {
                let v = mesh.vertices[i as usize];
                write_f32s(w, &[v.x, v.y, v.z])?;
            }
            w.write_all(&[0, 0])?;
        }
        Ok(())
    })
}

/// Welds triangle-soup corners that are bit-identical (after folding -0 into +0).
#[derive(Default)]
pub(super) struct Welder {
    index: HashMap<[u64; 3], u32>,
    vertices: Vec<DVec3>,
}

impl Welder {
    fn add(&mut self, p: DVec3) -> u32 {
        let key = [p.x + 0.0, p.y + 0.0, p.z + 0.0].map(f64::to_bits);
        *self.index.entry(key).or_insert_with(|| {
            self.vertices.push(p + DVec3::ZERO);
            (self.vertices.len() - 1) as u32
        })
    }
}

pub(super) const STL_HEADER: usize = 84;
pub(super) const STL_FACET: usize = 50;

pub(super) fn parse_stl(path: &Path, bytes: &[u8]) -> Result<Mesh> {
    if bytes.len() >= STL_HEADER {
        let count = u32::from_le_bytes(bytes[80..84].try_into().expect("4 bytes")) as usize;
        let expected = STL_HEADER as u64 + STL_FACET as u64 * count as u64;
        if expected == bytes.len() as u64 {
            return parse_binary_stl(path, bytes, count);
        }
        if !looks_like_ascii_stl(bytes) {
            let problem = if (bytes.len() as u64) < expected {
                FormatProblem::Truncated
            } else {
                FormatProblem::SizeMismatch
            };
            return Err(Error::format(
                path,
                problem,
                format!(
                    "binary STL header promises {count} triangles ({expected} bytes) but the file has {} bytes",
                    bytes.len()
                ),
            ));
        }
    } else if !looks_like_ascii_stl(bytes) {
        return Err(Error::format(
            path,
            FormatProblem::Truncated,
            format!("{} bytes is too short for an STL file", bytes.len()),
        ));
    }
    parse_ascii_stl(path, bytes)
}

pub(super) fn looks_like_ascii_stl(bytes: &[u8]) -> bool {
    bytes.trim_ascii_start().starts_with(b"solid") && bytes.iter().take(4096).all(|&b| b.is_ascii())
}

pub(super) fn parse_binary_stl(path: &Path, bytes: &[u8], count: usize) -> Result<Mesh> {
    let mut welder = Welder::default();
    let mut triangles = Vec::with_capacity(count);
    for (f, facet) in bytes[STL_HEADER..].chunks_exact(STL_FACET).enumerate() {
        let mut corner = [0u32; 3];
        for (k, c) in corner.iter_mut().enumerate() {
            let at = 12 + 12 * k;
            let xyz: [f64; 3] = std::array::from_fn(|a| {
                f32::from_le_bytes(
                    facet[at + 4 * a..at + 4 * a + 4]
                        .try_into()
                        .expect("4 bytes"),
                ) as f64
            });
            let p = DVec3::from(xyz);
            if !p.is_finite() {
                return Err(Error::format(
                    path,
                    FormatProblem::BadValue,
                    format!("STL triangle {f} has a non-finite corner ({p})"),
                ));
            }
            *c = welder.add(p);
        }
        triangles.push(corner);
    }
    Ok(Mesh {
        vertices: welder.vertices,
        normals: Vec::new(),
        triangles,
    })
}

pub(super) fn parse_ascii_stl(path: &Path, bytes: &[u8]) -> Result<Mesh> {
    let text = std::str::from_utf8(bytes)
        .map_err(|_| Error::format(path, FormatProblem::Corrupt, "ASCII STL is not valid text"))?;
    let bad = |msg: String| Error::format(path, FormatProblem::BadValue, msg);
    let lines = text.lines().enumerate();
    let mut welder = Welder::default();
    let mut triangles = Vec::new();
    let mut corners: Vec<u32> = Vec::with_capacity(3);
    let mut in_solid = false;
    let mut in_loop = false;
    for (line_no, line) in lines {
        let mut tokens = line.split_whitespace();
        let Some(keyword) = tokens.next() else {
            continue;
        };
        let at = |msg: &str| bad(format!("ASCII STL line {}: {msg}", line_no + 1));
        match keyword {
            "solid" if !in_solid => in_solid = true,
            "endsolid" if in_solid && !in_loop => in_solid = false,
            "facet" if in_solid && !in_loop => {}
            "outer" if in_solid && !in_loop => {
                in_loop = true;
                corners.clear();
            }
            "vertex" if in_loop => {
                let xyz: Vec<f64> = tokens
                    .map(|t| t.parse::<f64>())
                    .collect::<std::result::Result<_, _>>()
                    .map_err(|_| at("vertex coordinate is not a number"))?;
                let [x, y, z] = xyz[..] else {
                    return Err(at("vertex needs three coordinates"));
                };
                let p = DVec3::new(x, y, z);
                if !p.is_finite() {
                    return Err(at("vertex coordinate is not finite"));
                }
                if corners.len() == 3 {
                    return Err(at("facet has more than three vertices"));
                }
                corners.push(welder.add(p));
            }
            "endloop" if in_loop => {
                let [a, b, c] = corners[..] else {
                    return Err(at("facet does not have three vertices"));
                };
                triangles.push([a, b, c]);
                in_loop = false;
            }
            "endfacet" if in_solid && !in_loop => {}
            _ => return Err(at(&format!("unexpected {keyword:?}"))),
        }
    }
    if in_solid || in_loop {
        return Err(Error::format(
            path,
            FormatProblem::Truncated,
            "ASCII STL ends inside a solid (no `endsolid`)",
        ));
    }
    Ok(Mesh {
        vertices: welder.vertices,
        normals: Vec::new(),
        triangles,
    })
}
