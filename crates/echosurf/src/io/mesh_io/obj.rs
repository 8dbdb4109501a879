//! Meshes as Wavefront OBJ: `v`/`vn`/`f` reader with polygons and negative indices, and writer.

use super::Space;
use super::has_normals;
use super::header_text;
use crate::Error;
use crate::FormatProblem;
use crate::Result;
use crate::io::polygons::push_polygon;
use crate::io::polygons::unit_normals;
use crate::mesh::Mesh;
use glam::DVec3;
use std::io::Write;
use std::path::Path;

pub(super) fn write_obj(path: &Path, mesh: &Mesh, space: Space) -> Result<()> {
    let normals = has_normals(mesh);
    crate::io::atomic::write_atomic(path, |w| {
        writeln!(w, "# {}", header_text(space))?;
        // `{}` prints the shortest decimal that reads back to the same f64, so OBJ round-trips exactly.
        for v in &mesh.vertices {
            writeln!(w, "v {} {} {}", v.x, v.y, v.z)?;
        }
        if normals {
            for n in &mesh.normals {
                writeln!(w, "vn {} {} {}", n.x, n.y, n.z)?;
            }
        }
        for t in &mesh.triangles {
            let [a, b, c] = t.map(|i| i as u64 + 1);
            if normals {
                writeln!(w, "f {a}//{a} {b}//{b} {c}//{c}")?;
            } else {
                writeln!(w, "f {a} {b} {c}")?;
            }
        }
        Ok(())
    })
}

pub(super) fn parse_obj(path: &Path, bytes: &[u8]) -> Result<Mesh> {
    let text = std::str::from_utf8(bytes)
        .map_err(|_| Error::format(path, FormatProblem::Corrupt, "OBJ file is not valid text"))?;
    let mut vertices = Vec::new();
    let mut file_normals = Vec::new();
    // (OBJ vertex index, OBJ normal index) pairs seen on face corners.
    let mut corner_normals: Vec<(u32, u32)> = Vec::new();
    let mut triangles = Vec::new();
    let mut polygon = Vec::new();
    for (line_no, line) in text.lines().enumerate() {
        let at = |problem, msg: &str| {
            Error::format(path, problem, format!("OBJ line {}: {msg}", line_no + 1))
        };
        let mut tokens = line.split_whitespace();
        match tokens.next() {
            Some(kind @ ("v" | "vn")) => {
                let mut xyz = [0.0; 3];
                for c in &mut xyz {
                    *c = tokens
                        .next()
                        .and_then(|t| t.parse::<f64>().ok())
                        .ok_or_else(|| at(FormatProblem::BadValue, "needs three numbers"))?;
                }
                let p = DVec3::from(xyz);
                if !p.is_finite() {
                    return Err(at(FormatProblem::BadValue, "coordinate is not finite"));
                }
                if kind == "v" {
                    vertices.push(p);
                } else {
                    file_normals.push(p);
                }
            }
            Some("f") => {
                polygon.clear();
                for corner in tokens {
                    let mut parts = corner.split('/');
                    let v = resolve_obj_index(parts.next(), vertices.len()).ok_or_else(|| {
                        at(
                            FormatProblem::BadValue,
                            &format!("bad vertex index in {corner:?}"),
                        )
                    })?;
                    let _texture = parts.next();
                    if let Some(n) = parts.next().filter(|s| !s.is_empty()) {
                        let n =
                            resolve_obj_index(Some(n), file_normals.len()).ok_or_else(|| {
                                at(
                                    FormatProblem::BadValue,
                                    &format!("bad normal index in {corner:?}"),
                                )
                            })?;
                        corner_normals.push((v, n));
                    }
                    polygon.push(v);
                }
                push_polygon(
                    path,
                    &format!("OBJ line {}", line_no + 1),
                    &polygon,
                    vertices.len(),
                    &mut triangles,
                )?;
            }
            _ => {} // comments, vt, groups, materials, smoothing, lines, points
        }
    }
    if u32::try_from(vertices.len()).is_err() {
        return Err(Error::format(
            path,
            FormatProblem::Unsupported,
            "more than 2^32 vertices",
        ));
    }
    let normals = per_vertex_normals(vertices.len(), &file_normals, &corner_normals);
    Ok(Mesh {
        vertices,
        normals,
        triangles,
    })
}

/// OBJ indices are 1-based, negative ones count back from the latest element. `None` if out of range.
pub(super) fn resolve_obj_index(token: Option<&str>, count: usize) -> Option<u32> {
    let i: i64 = token?.parse().ok()?;
    let zero_based = match i {
        1.. => i - 1,
        ..=-1 => count as i64 + i,
        0 => return None,
    };
    (0..count as i64)
        .contains(&zero_based)
        .then(|| u32::try_from(zero_based).ok())
        .flatten()
}

/// OBJ normals belong to face corners; a [`Mesh`] has one per vertex. Keep them only when every vertex
/// that has one is given the same normal by all its corners and every vertex has one.
pub(super) fn per_vertex_normals(
    vertex_count: usize,
    file_normals: &[DVec3],
    corners: &[(u32, u32)],
) -> Vec<DVec3> {
    if corners.is_empty() {
        return Vec::new();
    }
    let mut assigned: Vec<Option<DVec3>> = vec![None; vertex_count];
    for &(v, n) in corners {
        let normal = file_normals[n as usize];
        match assigned[v as usize] {
            None => assigned[v as usize] = Some(normal),
            Some(existing) if existing == normal => {}
            Some(_) => return Vec::new(),
        }
    }
    let all: Option<Vec<DVec3>> = assigned.into_iter().collect();
    all.map(|ns| unit_normals(ns.into_iter()))
        .unwrap_or_default()
}
