//! What echosurf's tests and benches share: where the real PLUS data is ([`real_data`]), decoding the PNGs
//! echosurf writes ([`png_pixels`]), and seed files for the mutation harness and the hostile corpus
//! ([`corpus`]), generated at test time from the real PLUS data in `../shared/data/real/` (cut down so
//! thousands of parses stay fast) and from our own writers.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::OnceLock;

use echosurf::io::{self, PixelData, TrackedSequence};
use echosurf::mesh::Mesh;
use glam::DVec3;

pub mod corpus;
pub mod png_pixels;

pub mod real_data;
pub use real_data::real;

/// Width and height of the cropped frames of [`small_sequence`].
pub const SMALL_W: usize = 24;
pub const SMALL_H: usize = 16;

/// The first 4 frames of the real N-wire sweep (all its transforms and fields), each cropped to
/// 24 x 16 pixels: a real PLUS header in a file of a few kB.
pub fn small_sequence() -> &'static TrackedSequence {
    static SEQ: OnceLock<TrackedSequence> = OnceLock::new();
    SEQ.get_or_init(|| {
        let full =
            io::read_sequence(&real("NwirePhantomFreehand.igs.mha")).expect("real N-wire data");
        let frames = 4.min(full.frames.len());
        let mut pixels = Vec::with_capacity(SMALL_W * SMALL_H * frames);
        for f in 0..frames {
            for v in 0..SMALL_H {
                for u in 0..SMALL_W {
                    pixels.push(full.pixel_f32(f, u + 300, v + 200).clamp(0.0, 255.0) as u8);
                }
            }
        }
        TrackedSequence {
            width: SMALL_W,
            height: SMALL_H,
            channels: 1,
            orientation: full.orientation.clone(),
            frames: full.frames[..frames].to_vec(),
            pixels: PixelData::U8(pixels),
            header: full.header.clone(),
        }
    })
}

/// A small NRRD sequence in the PLUS layout: the real N-wire NRRD header (first 4 frames' fields) with
/// 24 x 16 x 4 pixels, raw or gzip-encoded.
pub fn small_nrrd(gzip: bool) -> Vec<u8> {
    let real_bytes = std::fs::read(real("NwirePhantomFreehand.igs.nrrd")).expect("real NRRD");
    let header_end = real_bytes
        .windows(2)
        .position(|w| w == b"\n\n")
        .expect("NRRD header end");
    let header = String::from_utf8_lossy(&real_bytes[..header_end]).into_owned();
    let mut out = String::new();
    for line in header.lines() {
        if let Some(rest) = line.strip_prefix("Seq_Frame") {
            let index: usize = rest[..4].parse().unwrap_or(usize::MAX);
            if index >= 4 {
                continue;
            }
        }
        if line.starts_with("sizes:") {
            out.push_str(&format!("sizes: {SMALL_W} {SMALL_H} 4\n"));
        } else if line.starts_with("encoding:") {
            out.push_str(if gzip {
                "encoding: gz\n"
            } else {
                "encoding: raw\n"
            });
        } else {
            out.push_str(line);
            out.push('\n');
        }
    }
    out.push('\n');
    let data: Vec<u8> = (0..SMALL_W * SMALL_H * 4)
        .map(|i| (i * 7 % 251) as u8)
        .collect();
    let mut bytes = out.into_bytes();
    if gzip {
        use std::io::Write;
        let mut enc = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        enc.write_all(&data).unwrap();
        bytes.extend(enc.finish().unwrap());
    } else {
        bytes.extend(data);
    }
    bytes
}

/// A small closed mesh (octahedron) with normals.
pub fn small_mesh() -> Mesh {
    let vertices = vec![
        DVec3::X,
        -DVec3::X,
        DVec3::Y,
        -DVec3::Y,
        DVec3::Z,
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
    Mesh {
        normals: vertices.clone(),
        vertices,
        triangles,
    }
}

/// A point cloud of 30 points with an intensity scalar.
pub fn small_cloud() -> io::PointCloud {
    let positions: Vec<DVec3> = (0..30)
        .map(|i| {
            let t = i as f64;
            DVec3::new(t.sin() * 10.0, t.cos() * 10.0, t * 0.5)
        })
        .collect();
    let intensity: Vec<f32> = (0..30).map(|i| (i * 8) as f32).collect();
    io::PointCloud {
        positions,
        scalars: vec![("intensity".to_string(), intensity)],
    }
}

/// A 24 x 16 greyscale PNG mask with a filled rectangle.
pub fn small_png_mask() -> Vec<u8> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, SMALL_W as u32, SMALL_H as u32);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header().unwrap();
        let data: Vec<u8> = (0..SMALL_W * SMALL_H)
            .map(|i| {
                if (i % SMALL_W) > 5 && (i / SMALL_W) > 4 {
                    255
                } else {
                    0
                }
            })
            .collect();
        w.write_image_data(&data).unwrap();
    }
    out
}

/// A small fitted RBF model (.esrbf bytes), fitted to 40 samples of a linear-plus-bump field.
pub fn small_model_bytes(dir: &Path) -> Vec<u8> {
    let points: Vec<DVec3> = (0..40)
        .map(|i| {
            let t = i as f64;
            DVec3::new(
                (t * 0.7).sin() * 5.0,
                (t * 1.3).cos() * 5.0,
                (t * 0.37).sin() * 5.0,
            )
        })
        .collect();
    let values: Vec<f64> = points.iter().map(|p| p.x * 3.0 + p.length()).collect();
    let (model, _) = echosurf::rbf::fit(
        &points,
        &values,
        &echosurf::rbf::FitOptions::default(),
        &echosurf::progress::NoProgress,
    )
    .expect("small fit");
    let path = dir.join("seed_model.esrbf");
    model.save(&path).unwrap();
    std::fs::read(&path).unwrap()
}

/// Every seed: (file name with the extension its reader dispatches on, bytes).
pub fn seeds(dir: &Path) -> BTreeMap<&'static str, Vec<u8>> {
    let mut out = BTreeMap::new();
    let seq = small_sequence();
    let p = dir.join("seed.mha");
    io::write_sequence(&p, seq, false).unwrap();
    out.insert("seq_raw.mha", std::fs::read(&p).unwrap());
    io::write_sequence(&p, seq, true).unwrap();
    out.insert("seq_zlib.mha", std::fs::read(&p).unwrap());
    out.insert("seq_raw.nrrd", small_nrrd(false));
    out.insert("seq_gz.nrrd", small_nrrd(true));
    out.insert(
        "tracker.mha",
        std::fs::read(real("Prostate10_tracker.igs.mha")).unwrap(),
    );
    out.insert(
        "config_nwire.xml",
        std::fs::read(real(
            "PlusDeviceSet_NwirePhantomFreehand_vtkVolumeReconstructorTest2.xml",
        ))
        .unwrap(),
    );
    out.insert(
        "config_spine.xml",
        std::fs::read(real(
            "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml",
        ))
        .unwrap(),
    );
    out.insert(
        "polygon.json",
        br#"{"polygon": [[2.0, 3.0], [20.5, 3.0], [20.0, 14.0], [3.0, 12.0]]}"#.to_vec(),
    );
    out.insert("mask.png", small_png_mask());
    let mesh = small_mesh();
    for (key, ext) in [
        ("mesh.ply", "ply"),
        ("mesh.stl", "stl"),
        ("mesh.obj", "obj"),
    ] {
        let p = dir.join(format!("seed_mesh.{ext}"));
        io::write_mesh(&p, &mesh).unwrap();
        out.insert(key, std::fs::read(&p).unwrap());
    }
    // A real STL cut down: the 84-byte header and the first 40 triangles, count patched.
    let stl = std::fs::read(real("fCal_1.0.stl")).unwrap();
    let mut cut = stl[..84 + 40 * 50].to_vec();
    cut[80..84].copy_from_slice(&40u32.to_le_bytes());
    out.insert("fcal_cut.stl", cut);
    let p = dir.join("seed_cloud.ply");
    io::write_point_cloud(&p, &small_cloud()).unwrap();
    out.insert("cloud.ply", std::fs::read(&p).unwrap());
    out.insert("model.esrbf", small_model_bytes(dir));
    out.insert(
        "volume.mha",
        std::fs::read(real("NwirePhantomFreehandReconstructed.mha")).unwrap(),
    );
    out
}

/// Runs the reader that a user's file of this name would go through (the CLI's dispatch), returning the
/// error's Display on failure. Readers whose Ok value can feed further user-facing code also run that code
/// (summary of a sequence), so a reader that accepts nonsense that then panics downstream is caught too.
pub fn parse(key: &str, path: &Path) -> Result<(), String> {
    use echosurf::segment::InitialBand;
    let r: echosurf::Result<()> = match key {
        // An accepted sequence also goes through what `inspect` does with it (poses, sweeps, bounds):
        // its errors are fine, a panic on data the reader let through is not.
        k if k.starts_with("seq") || k == "tracker.mha" => io::read_sequence(path).map(|s| {
            let _ = io::summarise(&s, None, io::ReferenceChoice::Auto, path);
        }),
        k if k.starts_with("config") => io::read_calibration(path).map(|_| ()).and_then(|_| {
            let text = std::fs::read_to_string(path).map_err(|e| echosurf::Error::io(path, e))?;
            echosurf::voxel::options_from_config_xml(&text, path).map(|_| ())
        }),
        "polygon.json" => InitialBand::load(path, SMALL_W, SMALL_H).map(|_| ()),
        "mask.png" => InitialBand::load(path, SMALL_W, SMALL_H).map(|_| ()),
        "cloud.ply" => io::read_point_cloud(path).map(|_| ()),
        k if k.starts_with("mesh") || k.starts_with("fcal") => io::read_mesh(path).map(|_| ()),
        "model.esrbf" => echosurf::rbf::RbfModel::load(path).map(|_| ()),
        "volume.mha" => echosurf::voxel::read_volume_mha(path).map(|_| ()),
        other => panic!("no reader for seed {other}"),
    };
    r.map_err(|e| e.to_string())
}

/// The extension of a seed key (the part after the first dot).
pub fn ext_of(key: &str) -> &str {
    key.split_once('.').map(|(_, e)| e).unwrap_or("bin")
}
