//! Reading every real PLUS file in `shared/data/real`, the spine geometry check against PLUS's own
//! reconstruction, the MetaImage/NRRD equivalence, the writer round trip, and one test per bad input.

use std::path::{Path, PathBuf};

use echosurf::io::{
    self, PixelData, ReferenceChoice, read_calibration, read_sequence, resolve_poses, split_sweeps,
    world_bounds, write_sequence,
};
use echosurf::{Error, FormatProblem};
use glam::DVec3;

use echosurf_testkit::real_data;
use real_data::real;

const SEQUENCES: &[(&str, usize, usize, usize)] = &[
    ("SpinePhantomFreehand.igs.mha", 820, 616, 21),
    ("NwirePhantomFreehand.igs.mha", 820, 616, 97),
    ("NwirePhantomFreehand.igs.nrrd", 820, 616, 97),
    ("NwirePhantomFreehandReconstructed.mha", 101, 104, 74),
    ("SpinePhantomFreehandReconstructed.mha", 147, 106, 104),
    (
        "vtkVolumeReconstructorTestNNMEANvolumeRef.mha",
        147,
        106,
        105,
    ),
    ("Prostate10_tracker.igs.mha", 1, 1, 10),
    ("Prostate10_video.igs.mhd", 640, 480, 10),
    ("WaterTankBottomTranslationCombined.igs.mha", 820, 616, 201),
];

const CONFIGS: &[&str] = &[
    "PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml",
    "PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml",
    "PlusDeviceSet_NwirePhantomFreehand_vtkVolumeReconstructorTest2.xml",
];

#[test]
fn every_real_sequence_reads() {
    for &(name, w, h, n) in SEQUENCES {
        let s = read_sequence(&real(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!((s.width, s.height, s.frames.len()), (w, h, n), "{name}");
        if name.starts_with("Prostate10_tracker") {
            assert!(s.is_tracking_only());
            assert!(
                s.frames
                    .iter()
                    .all(|f| f.transforms.contains_key("ToolToTracker"))
            );
        } else {
            assert_eq!(s.pixels.len(), w * h * n, "{name}");
            assert!(matches!(s.pixels, PixelData::U8(_)), "{name}");
        }
    }
}

#[test]
fn every_real_config_reads() {
    for name in CONFIGS {
        let c = read_calibration(&real(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
        let [sx, sy] = c.pixel_size_mm();
        assert!(
            (0.07..0.09).contains(&sx) && (0.07..0.09).contains(&sy),
            "{name}"
        );
        assert!(c.transforms.len() >= 2, "{name}");
        assert!(c.clip.is_some(), "{name}");
    }
    let nwire = read_calibration(&real(CONFIGS[2])).unwrap();
    let clip = nwire.clip.unwrap();
    assert_eq!((clip.origin_px, clip.size_px), ([167, 62], [495, 488]));
    assert_eq!(nwire.volume_reconstruction["Interpolation"], "LINEAR");
}

#[test]
fn old_and_detached_files_carry_their_fields() {
    let tracker = read_sequence(&real("Prostate10_tracker.igs.mha")).unwrap();
    assert_eq!(tracker.frames[3].fields["FrameNumber"].trim(), "4");
    assert_eq!(tracker.frames[0].timestamp_s, Some(1.0));
    assert!(tracker.header.contains_key("CustomFrameFieldNames"));
    let video = read_sequence(&real("Prostate10_video.igs.mhd")).unwrap();
    assert_eq!(video.header["ElementSpacing"], "0.3 0.3 1");
    assert_eq!(
        video.frames[9].transforms["ToolToTracker"].matrix,
        glam::DMat4::IDENTITY
    );
    let water = read_sequence(&real("WaterTankBottomTranslationCombined.igs.mha")).unwrap();
    assert_eq!(water.frames[0].fields["FrameNumber"], "1449");
    assert!(water.frames[0].fields.contains_key("UnfilteredTimestamp"));
    let volume = read_sequence(&real("vtkVolumeReconstructorTestNNMEANvolumeRef.mha")).unwrap();
    assert_eq!(volume.header["Offset"], "-74.5217 165.573 29.072");
    assert_eq!(volume.header["ElementSpacing"], "0.5 0.5 0.5");
    assert!(volume.frames.iter().all(|f| f.transforms.is_empty()));
}

/// PLUS's regression reference for the NN_MEAN config starts its volume at the minimum corner of all frame
/// corners; our pose chain must give the same box. The numbers in the reference header are rounded to
/// 6 significant digits, so 1e-3 mm is the tolerance the file itself supports.
#[test]
fn spine_frame_corners_span_the_plus_reference_volume() {
    let seq_path = real("SpinePhantomFreehand.igs.mha");
    let seq = read_sequence(&seq_path).unwrap();
    let cal = read_calibration(&real(
        "PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml",
    ))
    .unwrap();
    let poses = resolve_poses(&seq, Some(&cal), ReferenceChoice::Auto, &seq_path).unwrap();
    assert_eq!(poses.world_frame, "Reference");
    assert_eq!(poses.poses.len(), 21);
    let (lo, hi) = world_bounds(&seq, &poses.poses).unwrap();
    let expected_min = DVec3::new(-74.5217, 165.573, 29.072);
    assert!((lo - expected_min).abs().max_element() < 1e-3, "min {lo}");

    // The max corner is not on the voxel grid, so the volumes' sizes say how PLUS rounds the extent.
    // The NN_MEAN regression reference (147 x 106 x 105) has round((max - min) / 0.5) + 1 voxels per
    // axis: its last voxel centre is the grid point nearest the max corner (within 0.25 mm). The older
    // SpinePhantomFreehandReconstructed.mha of the same sweep (147 x 106 x 104, same origin) truncates
    // instead: floor((max - min) / 0.5) + 1, so the max corner lies within its last voxel's 0.5 mm step.
    let spacing = 0.5;
    let extent_voxels = (hi - lo) / spacing;
    for (name, rounding) in [
        ("vtkVolumeReconstructorTestNNMEANvolumeRef.mha", "round"),
        ("SpinePhantomFreehandReconstructed.mha", "floor"),
    ] {
        let volume = read_sequence(&real(name)).unwrap();
        assert_eq!(volume.header["Offset"], "-74.5217 165.573 29.072");
        let dims = DVec3::new(
            volume.width as f64,
            volume.height as f64,
            volume.frames.len() as f64,
        );
        let predicted = if rounding == "round" {
            extent_voxels.round() + 1.0
        } else {
            extent_voxels.floor() + 1.0
        };
        assert_eq!(predicted, dims, "{name}: max corner {hi}");
        let last_voxel = expected_min + (dims - 1.0) * spacing;
        if rounding == "round" {
            assert!(
                (hi - last_voxel).abs().max_element() <= 0.25,
                "{name}: {hi} vs {last_voxel}"
            );
        } else {
            assert!(hi.cmpge(last_voxel).all() && hi.cmplt(last_voxel + spacing).all());
        }
    }

    let sweeps = split_sweeps(&seq, &poses);
    assert_eq!(sweeps.len(), 1);
}

#[test]
fn nwire_mha_and_nrrd_decode_identically() {
    let mha = read_sequence(&real("NwirePhantomFreehand.igs.mha")).unwrap();
    let nrrd = read_sequence(&real("NwirePhantomFreehand.igs.nrrd")).unwrap();
    assert_eq!(mha.pixels, nrrd.pixels);
    assert_eq!(mha.frames, nrrd.frames);
    assert_eq!(mha.orientation, nrrd.orientation);
    let cal = read_calibration(&real(CONFIGS[2])).unwrap();
    let a = resolve_poses(&mha, Some(&cal), ReferenceChoice::Auto, Path::new("a")).unwrap();
    let b = resolve_poses(&nrrd, Some(&cal), ReferenceChoice::Auto, Path::new("b")).unwrap();
    assert_eq!(a, b);
    assert_eq!(a.poses.len(), 97);
}

#[test]
fn writer_round_trips_a_real_sweep() {
    let dir = tempfile::tempdir().unwrap();
    let seq = read_sequence(&real("NwirePhantomFreehand.igs.mha")).unwrap();
    for compress in [true, false] {
        let out = dir.path().join(format!("out{compress}.igs.mha"));
        write_sequence(&out, &seq, compress).unwrap();
        let back = read_sequence(&out).unwrap();
        assert_eq!(back.pixels, seq.pixels);
        assert_eq!(back.frames, seq.frames);
        assert_eq!((back.width, back.height, back.channels), (820, 616, 1));
        assert_eq!(back.orientation, "MF");
    }
    // Tracking-only sequences round-trip too.
    let tracker = read_sequence(&real("Prostate10_tracker.igs.mha")).unwrap();
    let out = dir.path().join("tracker.mha");
    write_sequence(&out, &tracker, true).unwrap();
    let back = read_sequence(&out).unwrap();
    assert_eq!(back.frames, tracker.frames);
    assert!(back.is_tracking_only());
}

// ---- bad input: one test per case; each must be an Err naming the file, never a panic ----

fn expect_problem(path: &Path, problem: FormatProblem) -> Error {
    let result = std::panic::catch_unwind(|| io::read_sequence(path));
    let err = result
        .expect("reader panicked")
        .expect_err("bad file was accepted");
    assert_eq!(err.problem(), Some(problem), "{err}");
    assert!(
        err.to_string()
            .contains(&*path.file_name().unwrap().to_string_lossy()),
        "error does not name the file: {err}"
    );
    err
}

/// Header and data of a real file, split at the end of the `ElementDataFile` line.
fn split_real(name: &str) -> (String, Vec<u8>) {
    let bytes = std::fs::read(real(name)).unwrap();
    let marker = b"ElementDataFile = LOCAL";
    let at = bytes
        .windows(marker.len())
        .position(|w| w == marker)
        .unwrap();
    let end = at + bytes[at..].iter().position(|&b| b == b'\n').unwrap() + 1;
    (
        String::from_utf8(bytes[..end].to_vec()).unwrap(),
        bytes[end..].to_vec(),
    )
}

fn write(dir: &Path, name: &str, header: &str, data: &[u8]) -> PathBuf {
    let p = dir.join(name);
    let mut bytes = header.as_bytes().to_vec();
    bytes.extend_from_slice(data);
    std::fs::write(&p, bytes).unwrap();
    p
}

#[test]
fn bad_truncated_file() {
    let dir = tempfile::tempdir().unwrap();
    let (header, data) = split_real("SpinePhantomFreehand.igs.mha");
    let p = write(dir.path(), "cut.mha", &header, &data[..data.len() / 2]);
    expect_problem(&p, FormatProblem::Truncated);
    // Cut inside the header.
    let p = write(
        dir.path(),
        "cut_header.mha",
        &header[..header.len() / 2],
        &[],
    );
    expect_problem(&p, FormatProblem::Truncated);
    let p = write(dir.path(), "cut_line_end.mha", &header[..1000], &[]);
    expect_problem(&p, FormatProblem::Truncated);
    let p = write(dir.path(), "empty.mha", "", &[]);
    expect_problem(&p, FormatProblem::Truncated);
    // Uncompressed: fewer bytes than DimSize promises.
    let (header, data) = split_real("vtkVolumeReconstructorTestNNMEANvolumeRef.mha");
    let p = write(dir.path(), "cut_raw.mha", &header, &data[..data.len() - 1]);
    expect_problem(&p, FormatProblem::Truncated);
}

#[test]
fn bad_dim_size_claims_more_than_the_stream_holds() {
    let dir = tempfile::tempdir().unwrap();
    let (header, data) = split_real("SpinePhantomFreehand.igs.mha");
    // One frame more than the zlib stream holds.
    let more = header.replace("DimSize = 820 616 21", "DimSize = 820 616 22");
    assert_ne!(more, header);
    let more = more.replace("Seq_Frame0000_Timestamp", "Seq_Frame0021_Timestamp");
    let p = write(dir.path(), "more.mha", &more, &data);
    expect_problem(&p, FormatProblem::Truncated);
    // Absurd size: must be refused before allocating (a terabyte would abort the test process).
    let huge = header.replace("DimSize = 820 616 21", "DimSize = 820000 616000 21");
    let p = write(dir.path(), "huge.mha", &huge, &data);
    expect_problem(&p, FormatProblem::SizeMismatch);
    let overflow = header.replace(
        "DimSize = 820 616 21",
        "DimSize = 18446744073709551615 18446744073709551615 21",
    );
    let p = write(dir.path(), "overflow.mha", &overflow, &data);
    expect_problem(&p, FormatProblem::SizeMismatch);
    // Uncompressed file claiming a huge image.
    let (header, data) = split_real("vtkVolumeReconstructorTestNNMEANvolumeRef.mha");
    let huge = header.replace(
        "DimSize = 147 106                    105",
        "DimSize = 147000 106000 105",
    );
    assert_ne!(huge, header);
    let p = write(dir.path(), "huge_raw.mha", &huge, &data);
    expect_problem(&p, FormatProblem::Truncated);
    // Fewer pixels than the stream holds is also a mismatch.
    let (header, data) = split_real("SpinePhantomFreehand.igs.mha");
    let less = header.replace("DimSize = 820 616 21", "DimSize = 820 616 20");
    let less = less.replace("Seq_Frame0020_", "Seq_Frame0019_");
    let p = write(dir.path(), "less.mha", &less, &data);
    expect_problem(&p, FormatProblem::SizeMismatch);
}

#[test]
fn bad_corrupt_zlib() {
    let dir = tempfile::tempdir().unwrap();
    let (header, mut data) = split_real("NwirePhantomFreehand.igs.mha");
    for b in &mut data[2..2000] {
        *b = b.wrapping_mul(31).wrapping_add(7);
    }
    let p = write(dir.path(), "corrupt.mha", &header, &data);
    expect_problem(&p, FormatProblem::Corrupt);
    // Gzip NRRD with a broken stream.
    let bytes = std::fs::read(real("NwirePhantomFreehand.igs.nrrd")).unwrap();
    let end = bytes.windows(2).position(|w| w == b"\n\n").unwrap() + 2;
    let mut broken = bytes.clone();
    for b in &mut broken[end + 20..end + 3000] {
        *b ^= 0x5a;
    }
    let p = dir.path().join("corrupt.nrrd");
    std::fs::write(&p, broken).unwrap();
    expect_problem(&p, FormatProblem::Corrupt);
}

#[test]
fn bad_missing_data_file() {
    let dir = tempfile::tempdir().unwrap();
    let header = std::fs::read_to_string(real("Prostate10_video.igs.mhd")).unwrap();
    let p = write(dir.path(), "video.mhd", &header, &[]);
    let err = expect_problem(&p, FormatProblem::MissingField);
    assert!(err.to_string().contains("Prostate10_video.raw"), "{err}");
    // A data file that is too short: the error names the data file.
    let raw = dir.path().join("Prostate10_video.raw");
    std::fs::write(&raw, vec![0u8; 1000]).unwrap();
    let err = io::read_sequence(&p).unwrap_err();
    assert_eq!(err.problem(), Some(FormatProblem::Truncated));
    assert!(err.to_string().contains("Prostate10_video.raw"), "{err}");
}

#[test]
fn bad_matrix_values() {
    let dir = tempfile::tempdir().unwrap();
    let (header, data) = split_real("SpinePhantomFreehand.igs.mha");
    let first = "Seq_Frame0003_ProbeToTrackerTransform = ";
    let at = header.find(first).unwrap() + first.len();
    let mut text = header.clone();
    text.replace_range(at..at + 3, "abc");
    let p = write(dir.path(), "text.mha", &text, &data);
    expect_problem(&p, FormatProblem::BadValue);
    let mut nan = header.clone();
    nan.replace_range(at..at + 3, "nan");
    let p = write(dir.path(), "nan.mha", &nan, &data);
    expect_problem(&p, FormatProblem::BadValue);
    let short = header.replace(
        "Seq_Frame0000_Timestamp = 215.102186",
        "Seq_Frame0000_Timestamp = soon",
    );
    let p = write(dir.path(), "time.mha", &short, &data);
    expect_problem(&p, FormatProblem::BadValue);
}

#[test]
fn bad_all_frames_invalid() {
    let dir = tempfile::tempdir().unwrap();
    let (header, data) = split_real("SpinePhantomFreehand.igs.mha");
    let invalid = header.replace("ImageStatus = OK", "ImageStatus = INVALID");
    let p = write(dir.path(), "invalid.mha", &invalid, &data);
    // Reading succeeds: a file of invalid frames is well-formed.
    let seq = read_sequence(&p).unwrap();
    assert!(seq.frames.iter().all(|f| !f.image_valid));
    let cal = read_calibration(&real(CONFIGS[1])).unwrap();
    let err = resolve_poses(&seq, Some(&cal), ReferenceChoice::Auto, &p).unwrap_err();
    assert_eq!(err.problem(), Some(FormatProblem::NoValidFrames));
    assert!(
        err.to_string().contains("invalid.mha") && err.to_string().contains("21 x image INVALID")
    );
    // The same through invalid tracking.
    let invalid = header.replace(
        "ProbeToTrackerTransformStatus = OK",
        "ProbeToTrackerTransformStatus = INVALID",
    );
    let p = write(dir.path(), "notrack.mha", &invalid, &data);
    let seq = read_sequence(&p).unwrap();
    let err = resolve_poses(&seq, Some(&cal), ReferenceChoice::Auto, &p).unwrap_err();
    assert_eq!(err.problem(), Some(FormatProblem::NoValidFrames));
}

#[test]
fn bad_calibration_without_image_to_probe() {
    let dir = tempfile::tempdir().unwrap();
    let xml = std::fs::read_to_string(real(CONFIGS[1])).unwrap();
    let no_image = xml.replace(
        "From=\"Image\" To=\"Probe\"",
        "From=\"Stylus\" To=\"Probe\"",
    );
    assert_ne!(no_image, xml);
    let p = dir.path().join("nocal.xml");
    std::fs::write(&p, no_image).unwrap();
    let err = read_calibration(&p).unwrap_err();
    assert_eq!(err.problem(), Some(FormatProblem::MissingTransform));
    assert!(err.to_string().contains("nocal.xml"));
    let nan = xml.replace("15.3978", "NaN");
    std::fs::write(&p, nan).unwrap();
    assert_eq!(
        read_calibration(&p).unwrap_err().problem(),
        Some(FormatProblem::BadValue)
    );
}

#[test]
fn bad_header_line_too_long() {
    let dir = tempfile::tempdir().unwrap();
    let mut header = String::from("ObjectType = Image\nNDims = 3\nDimSize = 1 1 1\nOffset = ");
    header.push_str(&"0 ".repeat(1 << 20));
    header.push_str("\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n");
    let p = write(dir.path(), "long.mha", &header, &[0]);
    expect_problem(&p, FormatProblem::SizeMismatch);
}

#[test]
fn bad_frame_fields_beyond_dim_size() {
    let dir = tempfile::tempdir().unwrap();
    let header = "ObjectType = Image\nNDims = 3\nDimSize = 0 0 2000000000\nElementType = MET_OTHER\n\
        Seq_Frame0000_Timestamp = 1\nElementDataFile = LOCAL\n";
    let p = write(dir.path(), "claims.mha", header, &[]);
    expect_problem(&p, FormatProblem::SizeMismatch);
    let header = "ObjectType = Image\nNDims = 3\nDimSize = 0 0 1\nElementType = MET_OTHER\n\
        Seq_Frame0005_Timestamp = 1\nElementDataFile = LOCAL\n";
    let p = write(dir.path(), "beyond.mha", header, &[]);
    expect_problem(&p, FormatProblem::SizeMismatch);
}

/// The N-wire reconstruction was made with a clip rectangle (167 62 / 495 488): its origin is the min of
/// the clip-rectangle corners of all frames (PLUS convention: origin .. min(origin + size, last pixel)),
/// and its size floor((max - min) / 0.5) + 1 voxels, as in the older spine reconstruction.
#[test]
fn nwire_clip_corners_span_the_plus_reconstruction() {
    let seq_path = real("NwirePhantomFreehand.igs.mha");
    let seq = read_sequence(&seq_path).unwrap();
    let cal = read_calibration(&real(CONFIGS[2])).unwrap();
    let poses = resolve_poses(&seq, Some(&cal), ReferenceChoice::Auto, &seq_path).unwrap();
    let (lo, hi) = io::clipped_world_bounds(&seq, &poses.poses, &cal.clip.unwrap()).unwrap();
    let volume = read_sequence(&real("NwirePhantomFreehandReconstructed.mha")).unwrap();
    assert_eq!(volume.header["Offset"], "-22.2573 -137.793 -58.5829");
    let origin = DVec3::new(-22.2573, -137.793, -58.5829);
    assert!((lo - origin).abs().max_element() < 1e-3, "min {lo}");
    let dims = DVec3::new(
        volume.width as f64,
        volume.height as f64,
        volume.frames.len() as f64,
    );
    assert_eq!(((hi - lo) / 0.5).floor() + 1.0, dims, "max {hi}");
}

/// Every truncation and many random byte corruptions of small valid files (MetaImage zlib and plain,
/// NRRD gz): the readers return Ok or Err, never panic. Seeded, so failures reproduce.
#[test]
fn mangled_files_never_panic() {
    use rand::{Rng, SeedableRng};
    let dir = tempfile::tempdir().unwrap();
    // A small 8 x 6 x 3 sweep with PLUS-like per-frame fields keeps the loop fast.
    let frames = (0..3)
        .map(|i| {
            let mut f = echosurf::io::TrackedFrame {
                timestamp_s: Some(345.6 + i as f64 * 0.08),
                image_valid: true,
                ..Default::default()
            };
            for (name, valid) in [("ProbeToTracker", true), ("ReferenceToTracker", i != 1)] {
                f.transforms.insert(
                    name.into(),
                    echosurf::io::FrameTransform {
                        matrix: glam::DMat4::from_rotation_z(0.1 * i as f64)
                            * glam::DMat4::from_translation(DVec3::new(-190.9, -98.1, -1949.1)),
                        valid,
                    },
                );
            }
            f
        })
        .collect();
    let seq = echosurf::io::TrackedSequence {
        width: 8,
        height: 6,
        channels: 1,
        orientation: "MF".into(),
        frames,
        pixels: PixelData::U8((0..144).map(|v| (v * 7 % 256) as u8).collect()),
        header: Default::default(),
    };
    let mut originals = Vec::new();
    for compress in [true, false] {
        let p = dir.path().join(format!("small{compress}.mha"));
        write_sequence(&p, &seq, compress).unwrap();
        originals.push(("mha", std::fs::read(&p).unwrap()));
    }
    let nrrd_header = "NRRD0004\ndimension: 3\ntype: uint8\nsizes: 4 2 2\nencoding: gz\n\
        ultrasound image orientation:=MN\nSeq_Frame0001_ProbeToTrackerTransform:=1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n\n";
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    std::io::Write::write_all(&mut gz, &[9u8; 16]).unwrap();
    let mut nrrd = nrrd_header.as_bytes().to_vec();
    nrrd.extend_from_slice(&gz.finish().unwrap());
    assert!(
        io::nrrd::read_sequence(&{
            let p = dir.path().join("ok.nrrd");
            std::fs::write(&p, &nrrd).unwrap();
            p
        })
        .is_ok()
    );
    originals.push(("nrrd", nrrd));

    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(20261125);
    for (ext, original) in &originals {
        // A fresh name per attempt: rewriting one file in place is ~10x slower on overlay file systems.
        let mut count = 0usize;
        let mut attempt = |bytes: &[u8]| {
            count += 1;
            let p = dir.path().join(format!("mangled{count}.{ext}"));
            std::fs::write(&p, bytes).unwrap();
            let result = std::panic::catch_unwind(|| read_sequence(&p));
            assert!(result.is_ok(), "panic on mangled {ext}");
        };
        // Every cut in the binary tail, a sample of cuts in the header (each read costs a file write).
        let tail = original.len().saturating_sub(160);
        for len in (0..tail).step_by(7).chain(tail..original.len()) {
            attempt(&original[..len]);
        }
        for _ in 0..400 {
            let mut bytes = original.clone();
            for _ in 0..rng.random_range(1..4) {
                let i = rng.random_range(0..bytes.len());
                bytes[i] = rng.random();
            }
            attempt(&bytes);
        }
    }
}

/// A missing recording fails its test with the path it looked for, not with a later read error.
#[test]
#[should_panic(expected = "real PLUS data missing: ")]
fn a_missing_recording_is_named() {
    real("no-such-recording.igs.mha");
}
