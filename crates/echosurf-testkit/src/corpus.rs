//! The hostile corpus: broken, lying and malicious variants of real files, generated into a folder at test
//! time (nothing big is committed). Each case says which reader it targets and how the CLI reaches it.

use std::io::Write;
use std::path::{Path, PathBuf};

use super::{SMALL_H, SMALL_W};

/// Which user-facing entry point a case goes through.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Target {
    /// A tracked sequence the reader must reject (`echosurf inspect`).
    Sequence,
    /// A tracked sequence that reads but cannot be placed in space (`echosurf extract`): NaN/singular
    /// matrices, no valid pose.
    SequenceForExtract,
    /// A PLUS device-set XML (`echosurf reconstruct --calibration`).
    Config,
    /// An initial band (`echosurf extract --init`).
    InitialBand,
    /// A point cloud (`echosurf fit`).
    PointCloud,
    /// A mesh (`echosurf compare`).
    Mesh,
    /// A saved model (`echosurf eval`).
    Model,
    /// A reconstructed volume (library only: no CLI command reads volumes).
    Volume,
}

#[derive(Debug, Clone)]
pub struct Case {
    pub path: PathBuf,
    pub target: Target,
    /// Words of which at least one must appear in the error (case-insensitive): the problem, not just
    /// "error".
    pub problem_words: &'static [&'static str],
}

/// The valid companions the CLI cases need (config, sequence, mesh, cloud), written into `dir`.
#[derive(Debug)]
pub struct Companions {
    pub config: PathBuf,
    pub sequence: PathBuf,
    pub mesh: PathBuf,
    pub cloud: PathBuf,
}

pub fn companions(dir: &Path) -> Companions {
    let config = dir.join("good_config.xml");
    std::fs::copy(
        super::real("PlusDeviceSet_NwirePhantomFreehand_vtkVolumeReconstructorTest2.xml"),
        &config,
    )
    .unwrap();
    let sequence = dir.join("good_sequence.mha");
    echosurf::io::write_sequence(&sequence, super::small_sequence(), false).unwrap();
    let mesh = dir.join("good_mesh.ply");
    echosurf::io::write_mesh(&mesh, &super::small_mesh()).unwrap();
    let cloud = dir.join("good_cloud.ply");
    echosurf::io::write_point_cloud(&cloud, &super::small_cloud()).unwrap();
    Companions {
        config,
        sequence,
        mesh,
        cloud,
    }
}

fn split_header(bytes: &[u8], marker: &[u8]) -> (Vec<u8>, Vec<u8>) {
    let end = bytes
        .windows(marker.len())
        .position(|w| w == marker)
        .expect("header marker")
        + marker.len();
    (bytes[..end].to_vec(), bytes[end..].to_vec())
}

/// Replaces the value of header line `key = ...` (MetaImage) or `key: ...` (NRRD).
fn set_field(header: &[u8], key: &str, value: &str) -> Vec<u8> {
    let text = String::from_utf8_lossy(header);
    let mut out = String::new();
    let mut found = false;
    for line in text.split_inclusive('\n') {
        let k = line.split(['=', ':']).next().unwrap_or("").trim();
        if k == key && !found {
            let sep = if line.contains(" = ") { " = " } else { ": " };
            out.push_str(&format!("{key}{sep}{value}\n"));
            found = true;
        } else {
            out.push_str(line);
        }
    }
    assert!(found, "no header field {key}");
    out.into_bytes()
}

/// Applies `f` to every header line whose key contains `needle`.
fn map_lines(header: &[u8], needle: &str, f: impl Fn(&str) -> Option<String>) -> Vec<u8> {
    let text = String::from_utf8_lossy(header);
    let mut out = String::new();
    for line in text.split_inclusive('\n') {
        let key = line.split('=').next().unwrap_or("");
        if key.contains(needle) {
            if let Some(l) = f(line) {
                out.push_str(&l);
            }
        } else {
            out.push_str(line);
        }
    }
    out.into_bytes()
}

fn zlib(data: &[u8]) -> Vec<u8> {
    let mut enc = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::best());
    enc.write_all(data).unwrap();
    enc.finish().unwrap()
}

/// Writes every corpus file into `dir` and returns the cases. The 100 MB header line is streamed to disk.
pub fn generate(dir: &Path) -> Vec<Case> {
    let seeds = super::seeds(dir);
    let mut cases = Vec::new();
    let mut add =
        |name: &str, bytes: &[u8], target: Target, problem_words: &'static [&'static str]| {
            let path = dir.join(name);
            std::fs::write(&path, bytes).unwrap();
            cases.push(Case {
                path,
                target,
                problem_words,
            });
        };
    use Target::*;
    const TRUNC: &[&str] = &["trunc", "ends", "short", "missing", "promises", "only"];
    const SIZE: &[&str] = &[
        "size",
        "trunc",
        "promises",
        "large",
        "exceed",
        "budget",
        "fit in memory",
    ];
    const VALUE: &[&str] = &[
        "value",
        "invalid",
        "not ",
        "unsupported",
        "finite",
        "(read:",
    ];

    // --- MetaImage sequence (real N-wire header, 4 cropped frames) ---
    let (head, data) = split_header(&seeds["seq_raw.mha"], b"ElementDataFile = LOCAL\n");
    let whole = [head.clone(), data.clone()].concat();
    add("seq_empty.igs.mha", b"", Sequence, TRUNC);
    add(
        "seq_cut_mid_header_line.igs.mha",
        &head[..head.len() / 2],
        Sequence,
        TRUNC,
    );
    add(
        "seq_cut_before_data_line.igs.mha",
        &head[..head.len() - "ElementDataFile = LOCAL\n".len()],
        Sequence,
        TRUNC,
    );
    add(
        "seq_cut_in_data.igs.mha",
        &whole[..head.len() + data.len() / 2],
        Sequence,
        TRUNC,
    );
    add("seq_cut_after_header.igs.mha", &head, Sequence, TRUNC);
    let lie = |k: &str, v: &str| [set_field(&head, k, v), data.clone()].concat();
    add(
        "seq_dimsize_more_frames.igs.mha",
        &lie("DimSize", "24 16 400000"),
        Sequence,
        SIZE,
    );
    add(
        "seq_dimsize_overflow.igs.mha",
        &lie("DimSize", "4294967295 4294967295 4294967295"),
        Sequence,
        &["size", "overflow", "large", "budget", "trunc"],
    );
    // Zero width reads as a tracking-only recording (PLUS writes those); extract must refuse it.
    add(
        "seq_dimsize_zero.igs.mha",
        &lie("DimSize", "0 16 4"),
        SequenceForExtract,
        &["image", "pixel", "tracking"],
    );
    add(
        "seq_dimsize_negative.igs.mha",
        &lie("DimSize", "24 -16 4"),
        Sequence,
        VALUE,
    );
    add(
        "seq_dimsize_nan.igs.mha",
        &lie("DimSize", "NaN 16 4"),
        Sequence,
        VALUE,
    );
    add(
        "seq_elementtype_wrong.igs.mha",
        &lie("ElementType", "MET_QUATERNION"),
        Sequence,
        VALUE,
    );
    add(
        "seq_ndims_seven.igs.mha",
        &lie("NDims", "7"),
        Sequence,
        VALUE,
    );
    let mut non_utf8 = head.clone();
    let at = non_utf8.len() / 3;
    non_utf8.splice(at..at, [0xffu8, 0xfe, 0x80, b'\n', 0xc3, b'=', 0xff, b'\n']);
    add(
        "seq_non_utf8_header.igs.mha",
        &[non_utf8, data.clone()].concat(),
        Sequence,
        &["utf", "text", "header", "line", "invalid"],
    );
    // More poses than frames: DimSize and the data say 3 frames, the header has fields for 4. (Fewer
    // poses than frames is not an error: a frame without a transform is skipped like an INVALID one.)
    add(
        "seq_more_poses_than_frames.igs.mha",
        &[
            set_field(&head, "DimSize", &format!("{SMALL_W} {SMALL_H} 3")),
            data[..SMALL_W * SMALL_H * 3].to_vec(),
        ]
        .concat(),
        Sequence,
        &["frames", "Seq_Frame0003"],
    );
    add(
        "seq_more_frames_than_data.igs.mha",
        &lie("DimSize", &format!("{SMALL_W} {SMALL_H} 5")),
        Sequence,
        SIZE,
    );
    // Pose problems the reader accepts and extract must refuse.
    let matrix_to = |needle: &'static str, value: &'static str| {
        map_lines(&head, needle, move |line| {
            if line.contains("Status") {
                Some(line.to_string())
            } else {
                let key = line.split('=').next().unwrap().trim_end();
                Some(format!("{key} = {value}\n"))
            }
        })
    };
    add(
        "seq_nan_matrices.igs.mha",
        &[
            matrix_to(
                "ProbeToTrackerTransform",
                "NaN 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1",
            ),
            data.clone(),
        ]
        .concat(),
        SequenceForExtract,
        &["nan", "finite", "valid", "pose", "transform", "frame"],
    );
    add(
        "seq_inf_matrices.igs.mha",
        &[
            matrix_to(
                "ReferenceToTrackerTransform",
                "inf 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1",
            ),
            data.clone(),
        ]
        .concat(),
        SequenceForExtract,
        &["inf", "finite", "valid", "pose", "transform", "frame"],
    );
    add(
        "seq_singular_reference.igs.mha",
        &[
            matrix_to(
                "ReferenceToTrackerTransform",
                "0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 1",
            ),
            data.clone(),
        ]
        .concat(),
        SequenceForExtract,
        &["singular", "invert", "valid", "pose", "transform", "frame"],
    );
    let invalid_only = map_lines(&head, "TransformStatus", |line| {
        let key = line.split('=').next().unwrap().trim_end();
        Some(format!("{key} = INVALID\n"))
    });
    add(
        "seq_invalid_only.igs.mha",
        &[invalid_only, data.clone()].concat(),
        SequenceForExtract,
        &["valid", "pose", "frame", "transform"],
    );

    // --- compressed MetaImage: lying sizes and zlib bombs ---
    let (zhead, zdata) = split_header(&seeds["seq_zlib.mha"], b"ElementDataFile = LOCAL\n");
    add(
        "seq_compressed_size_huge.igs.mha",
        &[
            set_field(&zhead, "CompressedDataSize", "99999999999"),
            zdata.clone(),
        ]
        .concat(),
        Sequence,
        SIZE,
    );
    add(
        "seq_compressed_size_zero.igs.mha",
        &[set_field(&zhead, "CompressedDataSize", "0"), zdata.clone()].concat(),
        Sequence,
        &["size", "trunc", "corrupt", "decode", "0"],
    );
    let mut flipped = zdata.clone();
    for i in (2..flipped.len()).step_by(7) {
        flipped[i] ^= 0x5a;
    }
    add(
        "seq_zlib_corrupt.igs.mha",
        &[zhead.clone(), flipped].concat(),
        Sequence,
        &["decode", "corrupt", "compress", "size"],
    );
    // A small real stream that inflates to 64 MiB where 1536 bytes were promised.
    let bomb = zlib(&vec![0u8; 64 << 20]);
    add(
        "seq_zlib_bomb_inflates_more.igs.mha",
        &[
            set_field(&zhead, "CompressedDataSize", &bomb.len().to_string()),
            bomb,
        ]
        .concat(),
        Sequence,
        &["more than"],
    );
    // A tiny stream under a header claiming 20000 x 20000 x 1000 pixels.
    let tiny = zlib(&[7u8; 100]);
    let claim = set_field(&zhead, "DimSize", "20000 20000 1000");
    add(
        "seq_zlib_tiny_claims_huge.igs.mha",
        &[
            set_field(&claim, "CompressedDataSize", &tiny.len().to_string()),
            tiny,
        ]
        .concat(),
        Sequence,
        &["cannot hold", "promises"],
    );
    // A 100 MB header line, streamed to disk.
    {
        let path = dir.join("seq_100mb_header_line.igs.mha");
        let mut f = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
        let cut = head.len() / 2;
        let line_start = head[..cut].iter().rposition(|&c| c == b'\n').unwrap() + 1;
        f.write_all(&head[..line_start]).unwrap();
        f.write_all(b"Comment = ").unwrap();
        let chunk = vec![b'A'; 1 << 20];
        for _ in 0..100 {
            f.write_all(&chunk).unwrap();
        }
        f.write_all(b"\n").unwrap();
        f.write_all(&head[line_start..]).unwrap();
        f.write_all(&data).unwrap();
        f.flush().unwrap();
        cases.push(Case {
            path,
            target: Sequence,
            problem_words: &["line", "long", "header"],
        });
    }
    let mut add =
        |name: &str, bytes: &[u8], target: Target, problem_words: &'static [&'static str]| {
            let path = dir.join(name);
            std::fs::write(&path, bytes).unwrap();
            cases.push(Case {
                path,
                target,
                problem_words,
            });
        };
    // Detached data: missing file, and a device that never ends.
    let mhd = |target: &str| [set_field(&head, "ElementDataFile", target)].concat();
    add(
        "seq_missing_raw.mhd",
        &mhd("nowhere.raw"),
        Sequence,
        &["exist", "missing", "nowhere"],
    );
    add(
        "seq_data_is_dev_zero.mhd",
        &mhd("/dev/zero"),
        Sequence,
        &["regular", "dev/zero"],
    );

    // --- NRRD ---
    let (nhead, ndata) = split_header(&seeds["seq_raw.nrrd"], b"\n\n");
    let nlie = |k: &str, v: &str| [set_field(&nhead, k, v), ndata.clone()].concat();
    add(
        "nrrd_cut_in_data.igs.nrrd",
        &[nhead.clone(), ndata[..ndata.len() / 3].to_vec()].concat(),
        Sequence,
        TRUNC,
    );
    add(
        "nrrd_cut_in_header.igs.nrrd",
        &nhead[..nhead.len() / 2],
        Sequence,
        TRUNC,
    );
    add(
        "nrrd_sizes_huge.igs.nrrd",
        &nlie("sizes", "4000000000 4000000000 4000000000"),
        Sequence,
        SIZE,
    );
    add(
        "nrrd_sizes_zero.igs.nrrd",
        &nlie("sizes", "24 0 4"),
        SequenceForExtract,
        &["image", "pixel", "tracking"],
    );
    add(
        "nrrd_type_wrong.igs.nrrd",
        &nlie("type", "quaternion"),
        Sequence,
        VALUE,
    );
    add(
        "nrrd_dimension_zero.igs.nrrd",
        &nlie("dimension", "0"),
        Sequence,
        VALUE,
    );
    let (ghead, _) = split_header(&seeds["seq_gz.nrrd"], b"\n\n");
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
    gz.write_all(&vec![0u8; 64 << 20]).unwrap();
    add(
        "nrrd_gzip_bomb.igs.nrrd",
        &[ghead, gz.finish().unwrap()].concat(),
        Sequence,
        &["more", "size", "long", "exceed", "trailing", "decode"],
    );

    // --- PLUS device-set XML ---
    let xml = String::from_utf8(seeds["config_nwire.xml"].clone()).unwrap();
    let no_probe: String = {
        let start = xml
            .find("<Transform From=\"Image\"")
            .expect("Image->Probe transform");
        let end = start + xml[start..].find("/>").unwrap() + 2;
        format!("{}{}", &xml[..start], &xml[end..])
    };
    add(
        "config_no_image_to_probe.xml",
        no_probe.as_bytes(),
        Config,
        &["image", "probe", "missing"],
    );
    add(
        "config_malformed.xml",
        &xml.as_bytes()[..xml.len() / 2],
        Config,
        &["xml", "parse", "unexpected", "end", "closed"],
    );
    let nan_matrix = {
        let start = xml.find("<Transform From=\"Image\"").unwrap();
        let m = start + xml[start..].find("Matrix=\"").unwrap() + "Matrix=\"".len();
        format!("{}NaN {}", &xml[..m], &xml[m..])
    };
    add(
        "config_nan_matrix.xml",
        nan_matrix.as_bytes(),
        Config,
        &["nan", "finite", "matrix", "16", "number"],
    );
    add(
        "config_not_xml.xml",
        &[0xff, 0xfe, 0x00, 0x3c, 0x00],
        Config,
        &["xml", "utf", "parse", "text", "invalid"],
    );

    // --- initial bands ---
    add(
        "init_two_vertices.json",
        br#"{"polygon": [[1, 2], [3, 4]]}"#,
        InitialBand,
        &["vertices", "3"],
    );
    add(
        "init_nan.json",
        br#"{"polygon": [[1, 2], [3, 4], [NaN, 5]]}"#,
        InitialBand,
        &["json", "expected", "finite"],
    );
    let png = super::small_png_mask();
    add(
        "init_truncated.png",
        &png[..png.len() / 2],
        InitialBand,
        &["png", "decode", "trunc", "eof", "corrupt"],
    );
    let mut wrong_size = png.clone();
    wrong_size[16..20].copy_from_slice(&1000u32.to_be_bytes()); // IHDR width (CRC now wrong too)
    add(
        "init_wrong_size.png",
        &wrong_size,
        InitialBand,
        &["png", "size", "crc", "decode", "corrupt", "1000"],
    );

    // --- point clouds and meshes ---
    let cloud = seeds["cloud.ply"].clone();
    let cloud_text = String::from_utf8_lossy(&cloud).into_owned();
    let lying_cloud = cloud_text.replacen("element vertex 30", "element vertex 4000000000", 1);
    assert_ne!(lying_cloud, cloud_text, "cloud header changed");
    add(
        "cloud_lying_vertex_count.ply",
        &lying_bytes(&cloud, "element vertex 30", "element vertex 4000000000"),
        PointCloud,
        SIZE,
    );
    add(
        "cloud_truncated.ply",
        &cloud[..cloud.len() - 37],
        PointCloud,
        TRUNC,
    );
    let mesh = seeds["mesh.ply"].clone();
    add(
        "mesh_lying_vertex_count.ply",
        &lying_bytes(&mesh, "element vertex 6", "element vertex 3000000000"),
        Mesh,
        SIZE,
    );
    add(
        "mesh_lying_face_count.ply",
        &lying_bytes(&mesh, "element face 8", "element face 3000000000"),
        Mesh,
        SIZE,
    );
    let stl = seeds["fcal_cut.stl"].clone();
    let mut lying_stl = stl.clone();
    lying_stl[80..84].copy_from_slice(&u32::MAX.to_le_bytes());
    add("mesh_stl_lying_count.stl", &lying_stl, Mesh, SIZE);
    add(
        "mesh_stl_truncated.stl",
        &stl[..84 + 50 * 20 + 17],
        Mesh,
        SIZE,
    );
    add(
        "mesh_stl_nan_vertex.stl",
        &nan_stl(&stl),
        Mesh,
        &["nan", "finite", "value"],
    );
    add(
        "mesh_obj_bad_index.obj",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99\n",
        Mesh,
        &["index", "vertex", "99", "range"],
    );
    add(
        "mesh_obj_zero_index.obj",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n",
        Mesh,
        &["index", "0", "range"],
    );
    add(
        "mesh_obj_garbage.obj",
        b"v 0 0 nope\nf 1 2 3\n",
        Mesh,
        &["number", "value", "parse", "nope", "invalid"],
    );

    // --- saved model ---
    let model = seeds["model.esrbf"].clone();
    add(
        "model_truncated.esrbf",
        &model[..model.len() / 2],
        Model,
        &["trunc", "size", "short", "ends", "length"],
    );
    let mut huge = model.clone();
    huge[12..20].copy_from_slice(&u64::MAX.to_le_bytes());
    add(
        "model_huge_count.esrbf",
        &huge,
        Model,
        &["size", "count", "centres", "trunc", "length", "large"],
    );
    add(
        "model_not_a_model.esrbf",
        b"this is not a model",
        Model,
        &["model", "magic", "esrbf", "not", "trunc", "short"],
    );

    // --- reconstructed volume ---
    let vol = seeds["volume.mha"].clone();
    add(
        "volume_truncated.mha",
        &vol[..vol.len() - 1000],
        Volume,
        &["trunc", "size", "short", "decode", "ends"],
    );
    cases
}

fn lying_bytes(bytes: &[u8], from: &str, to: &str) -> Vec<u8> {
    let pos = bytes
        .windows(from.len())
        .position(|w| w == from.as_bytes())
        .unwrap_or_else(|| panic!("{from:?} not in seed"));
    [&bytes[..pos], to.as_bytes(), &bytes[pos + from.len()..]].concat()
}

fn nan_stl(stl: &[u8]) -> Vec<u8> {
    let mut out = stl.to_vec();
    // First triangle's first vertex x (after the 84-byte header and 12-byte normal).
    out[84 + 12..84 + 16].copy_from_slice(&f32::NAN.to_le_bytes());
    out
}
