//! `echosurf inspect` end to end on the real PLUS data.

use std::process::Output;

use echosurf_testkit::png_pixels;
use echosurf_testkit::real_data;
use png_pixels::read_grey_png;
use real_data::real;

const NN_MEAN: &str = "PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml";

mod common;

fn inspect(args: &[&str]) -> Output {
    let mut all = vec!["inspect"];
    all.extend_from_slice(args);
    common::echosurf(&all)
}

/// `echosurf inspect ARGS`, which must succeed.
fn inspect_ok(args: &[&str]) -> Output {
    let mut all = vec!["inspect"];
    all.extend_from_slice(args);
    common::echosurf_ok(&all)
}

fn path_arg(name: &str) -> String {
    real(name).to_string_lossy().into_owned()
}

#[test]
fn json_has_the_documented_keys_and_the_spine_box() {
    let out = inspect_ok(&[
        &path_arg("SpinePhantomFreehand.igs.mha"),
        "--calibration",
        &path_arg(NN_MEAN),
        "--json",
    ]);
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("one JSON object");
    assert_eq!(v["frames"], 21);
    assert_eq!(v["valid_frames"], 21);
    assert_eq!(v["width"], 820);
    assert_eq!(v["height"], 616);
    assert_eq!(v["world_frame"], "Reference");
    let sweeps = v["sweeps"].as_array().unwrap();
    assert_eq!(sweeps.len(), 1);
    assert_eq!(sweeps[0]["frames"], 21);
    let path_mm = sweeps[0]["path_length_mm"].as_f64().unwrap();
    assert!(
        (25.0..45.0).contains(&path_mm),
        "README: a sweep of about 33 mm, got {path_mm}"
    );
    let min: Vec<f64> = v["bounds_mm"]["min"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect();
    for (got, want) in min.iter().zip([-74.5217, 165.573, 29.072]) {
        assert!((got - want).abs() < 1e-3, "{min:?}");
    }
    assert_eq!(v["bounds_mm"]["max"].as_array().unwrap().len(), 3);
    let px = v["pixel_size_mm"].as_array().unwrap();
    assert!((px[0].as_f64().unwrap() - 0.085).abs() < 0.001);
    // The frames' corners reach 32.9 mm off the first frame's plane (measured; the sweep is ~33 mm).
    let span_mm = v["sweep_span_mm"].as_f64().unwrap();
    assert!((span_mm - 32.9).abs() < 0.05, "{span_mm}");
}

#[test]
fn without_calibration_it_says_so_and_still_summarises() {
    let out = inspect(&[&path_arg("SpinePhantomFreehand.igs.mha")]);
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(text.contains("21 (21 valid, 0 skipped)"), "{text}");
    assert!(text.contains("calibration"), "{text}");
    assert!(
        text.contains("ProbeToTracker, ReferenceToTracker, StylusToTracker"),
        "{text}"
    );
    let out = inspect(&[&path_arg("SpinePhantomFreehand.igs.mha"), "--json"]);
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(v["bounds_mm"].is_null());
    assert_eq!(v["sweeps"].as_array().unwrap().len(), 1);
}

#[test]
fn every_real_sequence_is_summarised() {
    for name in [
        "NwirePhantomFreehand.igs.mha",
        "NwirePhantomFreehand.igs.nrrd",
        "NwirePhantomFreehandReconstructed.mha",
        "SpinePhantomFreehandReconstructed.mha",
        "vtkVolumeReconstructorTestNNMEANvolumeRef.mha",
        "Prostate10_tracker.igs.mha",
        "Prostate10_video.igs.mhd",
        "WaterTankBottomTranslationCombined.igs.mha",
    ] {
        let out = inspect(&[&path_arg(name), "--json"]);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{name}: {stderr}");
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert!(v["frames"].as_u64().unwrap() >= 10, "{name}");
        // Reconstructed volumes carry no tracking: described, but no frame is placed.
        let volume = name.contains("Reconstructed") || name.starts_with("vtkVolume");
        assert_eq!(v["valid_frames"] == 0, volume, "{name}");
        assert_eq!(v["sweeps"].as_array().unwrap().is_empty(), volume, "{name}");
        let text = inspect(&[&path_arg(name)]);
        assert!(text.status.success(), "{name}");
    }
}

#[test]
fn a_clip_rectangle_beyond_the_frames_is_pointed_out() {
    let nwire_config =
        path_arg("PlusDeviceSet_NwirePhantomFreehand_vtkVolumeReconstructorTest2.xml");
    let clip_line = |sequence: &str| {
        let out = inspect_ok(&[&path_arg(sequence), "--calibration", &nwire_config]);
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        text.lines()
            .find(|l| l.trim_start().starts_with("clip "))
            .unwrap()
            .to_string()
    };
    // The N-wire calibration's clip (167 62, 495 x 488) fits its own 820 x 616 frames, not the
    // Prostate video's 640 x 480.
    let own = clip_line("NwirePhantomFreehand.igs.mha");
    assert!(!own.contains("beyond"), "{own}");
    let other = clip_line("Prostate10_video.igs.mhd");
    assert!(
        other.contains("reaches beyond the 640 x 480 px frames"),
        "{other}"
    );
}

#[test]
fn bad_inputs_exit_non_zero_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    // All frames INVALID.
    let bytes = std::fs::read(real("SpinePhantomFreehand.igs.mha")).unwrap();
    let marker = b"ImageStatus = OK";
    let mut edited = Vec::with_capacity(bytes.len());
    let mut i = 0;
    let header_end = bytes
        .windows(b"ElementDataFile".len())
        .position(|w| w == b"ElementDataFile")
        .unwrap();
    while i < bytes.len() {
        if i < header_end && bytes[i..].starts_with(marker) {
            edited.extend_from_slice(b"ImageStatus = INVALID");
            i += marker.len();
        } else {
            edited.push(bytes[i]);
            i += 1;
        }
    }
    let seq = dir.path().join("all_invalid.igs.mha");
    std::fs::write(&seq, edited).unwrap();
    let out = inspect(&[seq.to_str().unwrap(), "--calibration", &path_arg(NN_MEAN)]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("all_invalid.igs.mha") && err.contains("INVALID"),
        "{err}"
    );

    // Calibration without Image->Probe.
    let xml = std::fs::read_to_string(real(NN_MEAN))
        .unwrap()
        .replace("From=\"Image\"", "From=\"Camera\"");
    let cal = dir.path().join("no_image_to_probe.xml");
    std::fs::write(&cal, xml).unwrap();
    let out = inspect(&[
        &path_arg("SpinePhantomFreehand.igs.mha"),
        "--calibration",
        cal.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("no_image_to_probe.xml") && err.contains("Image"),
        "{err}"
    );

    // Reference frame forced on a recording without a reference sensor.
    let out = inspect(&[
        &path_arg("Prostate10_tracker.igs.mha"),
        "--reference",
        "reference",
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("Reference"));

    // A file that does not exist: named, with the system's reason said once.
    let nothing = dir.path().join("nothing.mha");
    let out = inspect(&[nothing.to_str().unwrap()]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    let reason = std::fs::File::open(&nothing).unwrap_err().to_string();
    assert!(err.contains("nothing.mha"), "{err}");
    assert_eq!(err.matches(reason.as_str()).count(), 1, "{err}");
}

#[test]
fn frames_in_one_plane_are_pointed_out() {
    // The Prostate video's frames share one pose: whatever the calibration, they hold no volume.
    let nwire_config =
        path_arg("PlusDeviceSet_NwirePhantomFreehand_vtkVolumeReconstructorTest2.xml");
    let out = inspect_ok(&[
        &path_arg("Prostate10_video.igs.mhd"),
        "--calibration",
        &nwire_config,
    ]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("span mm     0.0 off the first frame's plane"),
        "{text}"
    );
    assert!(
        text.contains("they hold no volume, and extract refuses them"),
        "{text}"
    );
}

#[test]
fn a_frame_is_written_to_draw_the_first_band_on() {
    let dir = tempfile::tempdir().unwrap();
    let spine = path_arg("SpinePhantomFreehand.igs.mha");
    let sequence = echosurf::io::read_sequence(&real("SpinePhantomFreehand.igs.mha")).unwrap();
    let echosurf::io::PixelData::U8(pixels) = &sequence.pixels else {
        panic!("the spine sweep is 8-bit")
    };
    let frame_len = 820 * 616;

    // By default the first frame of the first sweep, where --init's band is used; pixel for pixel.
    let first = dir.path().join("first.png");
    let out = inspect_ok(&[
        &spine,
        "--calibration",
        &path_arg(NN_MEAN),
        "--frame-png",
        first.to_str().unwrap(),
    ]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("frames      21") && text.contains("frame 0 written"),
        "{text}"
    );
    let (w, h, grey) = read_grey_png(&first);
    assert_eq!((w, h), (820, 616));
    assert_eq!(grey, pixels[..frame_len]);

    // Another frame; with --json the summary alone is on stdout.
    let last = dir.path().join("last.png");
    let out = inspect_ok(&[
        &spine,
        "--json",
        "--frame",
        "20",
        "--frame-png",
        last.to_str().unwrap(),
    ]);
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(json["frames"], 21);
    assert!(String::from_utf8_lossy(&out.stderr).contains("frame 20 written"));
    assert_eq!(
        read_grey_png(&last).2,
        pixels[20 * frame_len..21 * frame_len]
    );

    // A frame that is not there: refused before anything is printed or written.
    let none = dir.path().join("none.png");
    let out = inspect(&[
        &spine,
        "--frame",
        "21",
        "--frame-png",
        none.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    assert!(out.stdout.is_empty());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("frame 21") && err.contains("21 frames"),
        "{err}"
    );
    assert!(!none.exists());

    // Never over the recording itself.
    let copy = dir.path().join("spine.mha");
    std::fs::copy(real("SpinePhantomFreehand.igs.mha"), &copy).unwrap();
    let before = std::fs::read(&copy).unwrap();
    let out = inspect(&[
        copy.to_str().unwrap(),
        "--frame-png",
        copy.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("an input of this run"));
    assert_eq!(std::fs::read(&copy).unwrap(), before);
}
