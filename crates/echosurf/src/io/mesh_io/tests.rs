use super::*;
use glam::DVec3;

/// An octahedron with outward normals: closed, 6 vertices, 8 triangles.
fn octahedron() -> Mesh {
    let vertices = vec![
        DVec3::X * 2.5,
        -DVec3::X,
        DVec3::Y * 1.25,
        -DVec3::Y,
        DVec3::Z * 0.1,
        -DVec3::Z,
    ];
    let triangles = vec![
        [0, 2, 4],
        [2, 1, 4],
        [1, 3, 4],
        [3, 0, 4],
        [2, 0, 5],
        [1, 2, 5],
        [3, 1, 5],
        [0, 3, 5],
    ];
    let normals = vertices.iter().map(|v: &DVec3| v.normalize()).collect();
    Mesh {
        vertices,
        normals,
        triangles,
    }
}

fn to_f32(m: &Mesh) -> Mesh {
    let r = |v: &DVec3| v.as_vec3().as_dvec3();
    Mesh {
        vertices: m.vertices.iter().map(r).collect(),
        normals: m.normals.iter().map(|n| r(n).normalize()).collect(),
        triangles: m.triangles.clone(),
    }
}

#[test]
fn the_listed_extensions_are_the_formats_read_and_written() {
    for ext in MESH_EXTENSIONS {
        assert!(format_of(Path::new(&format!("m.{ext}"))).is_some(), "{ext}");
        assert!(format_of(Path::new(&format!("m.{}", ext.to_uppercase()))).is_some());
    }
    assert!(format_of(Path::new("m.xyz")).is_none());
    assert!(format_of(Path::new("ply")).is_none());
}

#[test]
fn every_format_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = octahedron();
    let ply = dir.path().join("m.PLY");
    write_mesh(&ply, &mesh).unwrap();
    assert_eq!(read_mesh(&ply).unwrap(), to_f32(&mesh));

    let obj = dir.path().join("m.obj");
    write_mesh(&obj, &mesh).unwrap();
    assert_eq!(
        read_mesh(&obj).unwrap(),
        mesh,
        "OBJ keeps full f64 precision"
    );

    let vtk = dir.path().join("m.vtk");
    write_mesh(&vtk, &mesh).unwrap();
    assert_eq!(read_mesh(&vtk).unwrap(), to_f32(&mesh));

    let stl = dir.path().join("m.stl");
    write_mesh(&stl, &mesh).unwrap();
    let back = read_mesh(&stl).unwrap();
    let expected = Mesh {
        normals: vec![],
        ..to_f32(&mesh)
    };
    // Welding renumbers vertices in first-use order: compare triangles by position.
    assert_eq!(back.triangles.len(), 8);
    assert_eq!(back.vertices.len(), 6);
    for (t, u) in back.triangles.iter().zip(&expected.triangles) {
        assert_eq!(
            t.map(|i| back.vertices[i as usize]),
            u.map(|i| expected.vertices[i as usize])
        );
    }
    assert!(back.topology().is_closed_manifold());
    // Facet normals written point outward.
    let bytes = std::fs::read(&stl).unwrap();
    assert_eq!(bytes.len(), 84 + 50 * 8);
    let n0: Vec<f32> = (0..3)
        .map(|k| f32::from_le_bytes(bytes[84 + 4 * k..88 + 4 * k].try_into().unwrap()))
        .collect();
    let c = DVec3::new(2.5, 1.25, 0.1);
    assert!(DVec3::new(n0[0] as f64, n0[1] as f64, n0[2] as f64).dot(c) > 0.0);

    // Without normals as well, and an empty mesh.
    let bare = Mesh {
        normals: vec![],
        ..mesh.clone()
    };
    for p in [&ply, &obj, &vtk] {
        write_mesh(p, &bare).unwrap();
        assert!(read_mesh(p).unwrap().normals.is_empty());
        write_mesh(p, &Mesh::default()).unwrap();
        assert_eq!(read_mesh(p).unwrap(), Mesh::default());
    }
}

#[test]
fn vertex_values_and_colours_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = octahedron();
    let n = mesh.vertices.len();
    let values: Vec<f32> = (0..n).map(|i| 0.25 * i as f32).collect();
    let colours: Vec<[u8; 3]> = (0..n).map(|i| [i as u8, 100, 255 - i as u8]).collect();
    let path = dir.path().join("map.ply");
    write_ply_with_vertex_values(&path, &mesh, "distance_mm", &values, &colours, Space::Ras)
        .unwrap();
    // Still a mesh to every reader, with the values and colours as vertex properties.
    assert_eq!(read_mesh(&path).unwrap(), to_f32(&mesh));
    let cloud = crate::io::read_point_cloud(&path).unwrap();
    assert_eq!(cloud.scalar("distance_mm").unwrap(), values.as_slice());
    for (k, channel) in ["red", "green", "blue"].into_iter().enumerate() {
        let got: Vec<u8> = cloud
            .scalar(channel)
            .unwrap()
            .iter()
            .map(|&c| c as u8)
            .collect();
        let want: Vec<u8> = colours.iter().map(|c| c[k]).collect();
        assert_eq!(got, want, "{channel}");
    }
    assert_eq!(read_vertex_colours(&path).unwrap(), Some(colours.clone()));
    // A plain PLY, and the formats without vertex colours: none.
    let plain = dir.path().join("plain.ply");
    write_mesh(&plain, &mesh).unwrap();
    assert_eq!(read_vertex_colours(&plain).unwrap(), None);
    let stl = dir.path().join("plain.stl");
    write_mesh(&stl, &mesh).unwrap();
    assert_eq!(read_vertex_colours(&stl).unwrap(), None);
    // Wrong counts or a name that clashes: refused, nothing written.
    let refused = dir.path().join("refused.ply");
    for (name, values, colours) in [
        ("distance_mm", &values[1..], colours.as_slice()),
        ("distance_mm", values.as_slice(), &colours[1..]),
        ("red", values.as_slice(), colours.as_slice()),
        ("two words", values.as_slice(), colours.as_slice()),
    ] {
        let written =
            write_ply_with_vertex_values(&refused, &mesh, name, values, colours, Space::Lps);
        assert!(written.is_err());
        assert!(!refused.exists());
    }
}

#[test]
fn foreign_variants_are_read() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("q.ply");
    // ASCII PLY with a quad, extra properties and the `vertex_index` spelling.
    std::fs::write(
        &path,
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n\
         property float z\nproperty uchar red\nelement face 1\nproperty uchar flags\n\
         property list uint8 uint vertex_index\nend_header\n\
         0 0 0 1\n1 0 0 1\n1 1 0 1\n0 1 0 1\n7 4 0 1 2 3\n",
    )
    .unwrap();
    let m = read_mesh(&path).unwrap();
    assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);

    let path = dir.path().join("q.obj");
    std::fs::write(
        &path,
        "# quad\nv 0 0 0\nv 1 0 0\nv 1 1 0 1.0\nv 0 1 0\nvt 0 0\nvn 0 0 2\ng x\n\
         f 1/1/1 2/1/1 -2/1/1 -1/1/1\n",
    )
    .unwrap();
    let m = read_mesh(&path).unwrap();
    assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
    assert_eq!(m.normals, vec![DVec3::Z; 4]);

    let path = dir.path().join("a.stl");
    std::fs::write(
        &path,
        "solid t\n facet normal 0 0 1\n  outer loop\n   vertex 0 0 0\n   vertex 1 0 0\n\
         vertex 0 1 0\n  endloop\n endfacet\n facet normal 0 0 1\n outer loop\n vertex 1 0 0\n\
         vertex 1 1 0\n vertex 0 1 0\n endloop\n endfacet\nendsolid t\n",
    )
    .unwrap();
    let m = read_mesh(&path).unwrap();
    assert_eq!(m.vertices.len(), 4, "shared corners are welded");
    assert_eq!(m.triangles, vec![[0, 1, 2], [1, 3, 2]]);
    assert_eq!(m.topology().boundary_edges, 4);
}

#[test]
fn hostile_meshes_give_format_errors() {
    let dir = tempfile::tempdir().unwrap();
    let ply_head = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
                    property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n\
                    0 0 0\n1 0 0\n0 1 0\n";
    let vtk_head = "# vtk DataFile Version 4.2\nt\nASCII\nDATASET POLYDATA\nPOINTS 3 float\n\
                    0 0 0\n1 0 0\n0 1 0\n"
        .to_string();
    let mut stl_bin = vec![0u8; 80];
    stl_bin.extend_from_slice(&1000u32.to_le_bytes());
    stl_bin.extend_from_slice(&[0u8; 50]);
    let mut stl_nan = vec![0u8; 80];
    stl_nan.extend_from_slice(&1u32.to_le_bytes());
    stl_nan.extend_from_slice(&[0u8; 12]);
    stl_nan.extend_from_slice(&f32::NAN.to_le_bytes());
    stl_nan.extend_from_slice(&[0u8; 34]);
    let cases: Vec<(&str, Vec<u8>, FormatProblem)> = vec![
        (
            "a.ply",
            format!("{ply_head}3 0 1 3\n").into_bytes(),
            FormatProblem::BadValue,
        ),
        (
            "b.ply",
            format!("{ply_head}3 0 1 -1\n").into_bytes(),
            FormatProblem::BadValue,
        ),
        (
            "c.ply",
            format!("{ply_head}2 0 1\n").into_bytes(),
            FormatProblem::BadValue,
        ),
        (
            "d.ply",
            format!("{ply_head}3 0 1\n").into_bytes(),
            FormatProblem::Truncated,
        ),
        (
            "e.ply",
            ply_head.replace("face 1", "face 1000000000").into_bytes(),
            FormatProblem::SizeMismatch,
        ),
        ("f.stl", stl_bin, FormatProblem::Truncated),
        ("g.stl", stl_nan, FormatProblem::BadValue),
        (
            "h.stl",
            b"solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0\n".to_vec(),
            FormatProblem::BadValue,
        ),
        (
            "i.stl",
            b"solid x\nfacet normal 0 0 1\nouter loop\n".to_vec(),
            FormatProblem::Truncated,
        ),
        ("j.stl", b"abc".to_vec(), FormatProblem::Truncated),
        (
            "k.obj",
            b"v 0 0 0\nv 1 0 0\nf 1 2 3\n".to_vec(),
            FormatProblem::BadValue,
        ),
        (
            "l.obj",
            b"v 0 0 0\nv 1 0 0\nv 1 1 0\nf 0 1 2\n".to_vec(),
            FormatProblem::BadValue,
        ),
        ("m.obj", b"v 0 nan 0\n".to_vec(), FormatProblem::BadValue),
        ("n.obj", b"v 0 0\n".to_vec(), FormatProblem::BadValue),
        ("o.off", b"OFF\n".to_vec(), FormatProblem::Unsupported),
        (
            "p.vtk",
            vtk_head
                .replace("POINTS 3", "POINTS 3000000000")
                .into_bytes(),
            FormatProblem::Truncated,
        ),
        (
            "q.vtk",
            format!("{vtk_head}POLYGONS 1 4\n3 0 1 3\n").into_bytes(),
            FormatProblem::BadValue,
        ),
        (
            "r.vtk",
            format!("{vtk_head}POLYGONS 1 4\n3 0 1\n").into_bytes(),
            FormatProblem::Truncated,
        ),
        (
            "s.vtk",
            format!("{vtk_head}POLYGONS 2 4\n3 0 1 2\n").into_bytes(),
            FormatProblem::SizeMismatch,
        ),
        (
            "t.vtk",
            vtk_head
                .replace("POLYDATA", "UNSTRUCTURED_GRID")
                .into_bytes(),
            FormatProblem::Unsupported,
        ),
        (
            "u.vtk",
            vtk_head.replace("1 0 0", "1 nan 0").into_bytes(),
            FormatProblem::BadValue,
        ),
        (
            "v.vtk",
            b"# vtk DataFile Version 4.2\nx\nBINARY\nDATASET POLYDATA\nPOINTS 9 float\n\0\0"
                .to_vec(),
            FormatProblem::Truncated,
        ),
        ("w.vtk", vtk_head.into_bytes(), FormatProblem::MissingField),
        ("x.vtk", b"solid\n".to_vec(), FormatProblem::Unsupported),
    ];
    for (name, bytes, problem) in cases {
        let path = dir.path().join(name);
        std::fs::write(&path, &bytes).unwrap();
        let err = read_mesh(&path).unwrap_err();
        assert_eq!(err.problem(), Some(problem), "{name}: {err}");
        assert!(err.to_string().contains(name), "{err}");
    }
}

#[test]
fn writer_refuses_inconsistent_meshes() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("x.ply");
    let mut m = octahedron();
    m.triangles.push([0, 1, 6]);
    assert!(matches!(write_mesh(&path, &m), Err(Error::InvalidInput(_))));
    let mut m = octahedron();
    m.normals.pop();
    assert!(matches!(write_mesh(&path, &m), Err(Error::InvalidInput(_))));
    assert!(matches!(
        write_mesh(&dir.path().join("x.off"), &octahedron()),
        Err(Error::InvalidInput(_))
    ));
    assert!(!path.exists());
}

#[test]
fn mutated_files_never_panic() {
    use rand::{Rng, SeedableRng};
    let dir = tempfile::tempdir().unwrap();
    let mut originals = Vec::new();
    for name in ["m.ply", "m.stl", "m.obj", "m.vtk"] {
        let path = dir.path().join(name);
        write_mesh(&path, &octahedron()).unwrap();
        originals.push((name, std::fs::read(&path).unwrap()));
    }
    originals.push(("a.vtk", ASCII_VTK_5.to_vec()));
    originals.push((
        "a.ply",
        b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n\
0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
            .to_vec(),
    ));
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let path = Path::new("fuzz");
    for (name, original) in &originals {
        for _ in 0..400 {
            let mut bytes = original.clone();
            match rng.random_range(0..3) {
                0 => bytes.truncate(rng.random_range(0..bytes.len())),
                1 => {
                    for _ in 0..rng.random_range(1..4) {
                        let i = rng.random_range(0..bytes.len());
                        bytes[i] = rng.random();
                    }
                }
                _ => {
                    // Digits and header words are where parsers go wrong: overwrite with some.
                    let i = rng.random_range(0..bytes.len());
                    let junk: &[u8] = [&b"9999999999"[..], b"-1", b"\xff\xff\xff\x7f", b"nan"]
                        [rng.random_range(0..4)];
                    for (k, &b) in junk.iter().enumerate() {
                        if let Some(x) = bytes.get_mut(i + k) {
                            *x = b;
                        }
                    }
                }
            }
            // A format error, or a mesh that is safe to use; any panic fails the test.
            let result = match name.rsplit('.').next() {
                Some("ply") => parse_ply_mesh(path, &bytes),
                Some("stl") => parse_stl(path, &bytes),
                Some("vtk") => crate::io::vtk::read(path, &bytes).map(|v| v.mesh),
                _ => parse_obj(path, &bytes),
            };
            match result {
                Ok(m) => {
                    assert!(m.vertices.iter().all(|v| v.is_finite()));
                    assert!(
                        m.triangles
                            .iter()
                            .flatten()
                            .all(|&i| (i as usize) < m.vertices.len())
                    );
                    assert!(m.normals.is_empty() || m.normals.len() == m.vertices.len());
                }
                Err(e) => assert!(e.problem().is_some(), "{e}"),
            }
            let _ = crate::io::ply::PlyFile::parse(path, &bytes);
        }
    }
}

/// A version-5 ASCII VTK file as VTK 9 writes it: offsets and connectivity, a quad and a strip.
const ASCII_VTK_5: &[u8] = b"# vtk DataFile Version 5.1\nvtk output SPACE=LPS\nASCII\n\
DATASET POLYDATA\nPOINTS 5 double\n0 0 0 1 0 0 1 1 0\n0 1 0 2 1 0\n\n\
POLYGONS 2 4\nOFFSETS vtktypeint64\n0 4\nCONNECTIVITY vtktypeint64\n0 1 2 3\n\
TRIANGLE_STRIPS 2 4\nOFFSETS vtktypeint64\n0 4\nCONNECTIVITY vtktypeint64\n1 4 2 3\n\
CELL_DATA 3\nFIELD FieldData 1\n";

#[test]
fn foreign_vtk_variants_are_read() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("v5.vtk");
    std::fs::write(&path, ASCII_VTK_5).unwrap();
    let (m, space) = read_mesh_and_space(&path).unwrap();
    assert_eq!(space, Some(Space::Lps));
    // Quad fanned, strip split with alternating winding; LPS read into RAS.
    assert_eq!(
        m.triangles,
        vec![[0, 1, 2], [0, 2, 3], [1, 4, 2], [2, 4, 3]]
    );
    assert_eq!(m.vertices[1], DVec3::new(-1.0, 0.0, 0.0));
    assert_eq!(m.vertices[4], DVec3::new(-2.0, -1.0, 0.0));
    // Version 4 ASCII with lines, vertices and normals; untagged: read as RAS.
    let path = dir.path().join("v4.vtk");
    std::fs::write(
        &path,
        "# vtk DataFile Version 3.0\r\nno tag\r\nASCII\r\nDATASET POLYDATA\r\n\
         POINTS 3 float\r\n0 0 0 1 0 0 0 1 0\r\nVERTICES 1 2\r\n1 0\r\nLINES 1 3\r\n2 0 1\r\n\
         POLYGONS 1 4\r\n3 0 1 2\r\nPOINT_DATA 3\r\nNORMALS n float\r\n0 0 2 0 0 1 0 0 1\r\n",
    )
    .unwrap();
    let (m, space) = read_mesh_and_space(&path).unwrap();
    assert_eq!(space, None);
    assert_eq!(m.triangles, vec![[0, 1, 2]]);
    assert_eq!(m.vertices[1], DVec3::X);
    assert_eq!(m.normals, vec![DVec3::Z; 3]);
}

#[test]
fn every_format_round_trips_its_space_tag() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = octahedron();
    for ext in MESH_EXTENSIONS {
        for space in [Space::Ras, Space::Lps] {
            let path = dir.path().join(format!("m_{}.{ext}", space.name()));
            write_mesh_in(&path, &mesh, space).unwrap();
            let (back, tag) = read_mesh_and_space(&path).unwrap();
            assert_eq!(tag, Some(space), "{ext}");
            let want = if ext == "obj" {
                mesh.clone()
            } else {
                to_f32(&mesh)
            };
            if ext == "stl" {
                assert_eq!(back.vertices.len(), 6);
                let (lo, hi) = back.bounds().unwrap();
                assert_eq!((lo, hi), want.bounds().unwrap(), "{ext} {space:?}");
            } else {
                assert_eq!(back, want, "{ext} {space:?}");
            }
            // The tag is where Slicer looks: the file's text holds it once.
            let bytes = std::fs::read(&path).unwrap();
            assert_eq!(Space::find_tag(&bytes), Some(space));
        }
    }
    // The coloured PLY too.
    let n = mesh.vertices.len();
    let path = dir.path().join("map.ply");
    write_ply_with_vertex_values(
        &path,
        &mesh,
        "d",
        &vec![0.0; n],
        &vec![[0; 3]; n],
        Space::Lps,
    )
    .unwrap();
    let (back, tag) = read_mesh_and_space(&path).unwrap();
    assert_eq!((back, tag), (to_f32(&mesh), Some(Space::Lps)));
}

#[test]
fn lps_and_ras_files_differ_in_the_tag_and_the_signs_of_x_and_y_only() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = octahedron();
    for ext in MESH_EXTENSIONS {
        let ras_path = dir.path().join(format!("ras.{ext}"));
        let lps_path = dir.path().join(format!("lps.{ext}"));
        write_mesh_in(&ras_path, &mesh, Space::Ras).unwrap();
        write_mesh_in(&lps_path, &mesh, Space::Lps).unwrap();
        let ras = std::fs::read(&ras_path).unwrap();
        let lps = std::fs::read(&lps_path).unwrap();
        // As stored: x and y negated, z, triangles and everything else the same.
        let format = format_of(&ras_path).unwrap();
        let (stored_ras, _) = parse_mesh(&ras_path, format, &ras).unwrap();
        let (stored_lps, _) = parse_mesh(&lps_path, format, &lps).unwrap();
        assert_eq!(Space::Lps.convert(&stored_ras), stored_lps, "{ext}");
        // Byte for byte: with the tag put back, binary files differ only in sign bits (x, y and
        // their normals) and OBJ only in the minus signs of the first two numbers on a line.
        let mut lps = lps;
        let tag_at = lps.windows(9).position(|w| w == b"SPACE=LPS").unwrap();
        lps[tag_at..tag_at + 9].copy_from_slice(b"SPACE=RAS");
        assert_eq!(ras.len(), lps.len(), "{ext}");
        if ext == "obj" {
            let (r, l) = (
                String::from_utf8(ras).unwrap(),
                String::from_utf8(lps).unwrap(),
            );
            for (a, b) in r.lines().zip(l.lines()) {
                let (a, b): (Vec<&str>, Vec<&str>) =
                    (a.split(' ').collect(), b.split(' ').collect());
                for (k, (x, y)) in a.iter().zip(&b).enumerate() {
                    if (k == 1 || k == 2) && (a[0] == "v" || a[0] == "vn") {
                        let negated = x
                            .strip_prefix('-')
                            .map(str::to_owned)
                            .unwrap_or(format!("-{x}"));
                        assert_eq!(*y, negated, "{ext}: {a:?} {b:?}");
                    } else {
                        assert_eq!(x, y, "{ext}");
                    }
                }
            }
        } else {
            let differing: Vec<usize> = (0..ras.len()).filter(|&i| ras[i] != lps[i]).collect();
            assert!(!differing.is_empty(), "{ext}");
            for i in differing {
                assert_eq!(
                    ras[i] ^ lps[i],
                    0x80,
                    "{ext}: byte {i} differs beyond a sign bit"
                );
            }
        }
    }
}

#[test]
fn reads_the_fcal_phantom_cad_model() {
    // A binary STL whose 80-byte header starts with "solid": must not be taken for ASCII.
    let path = Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../../shared/data/real/fCal_1.0.stl"
    ));
    if !path.exists() {
        eprintln!("skipping: {} not present", path.display());
        return;
    }
    let m = read_mesh(path).unwrap();
    assert_eq!(m.triangles.len(), (1_289_884 - 84) / 50);
    let (lo, hi) = m.bounds().unwrap();
    let size = hi - lo;
    // The fCal 1.0 phantom is a box of some tens of millimetres on each side.
    assert!(
        size.min_element() > 10.0 && size.max_element() < 500.0,
        "{size}"
    );
    let topo = m.topology();
    assert!(topo.components >= 1);
    assert!(m.area_mm2() > 0.0);
}
