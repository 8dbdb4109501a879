//! `echosurf reconstruct` end to end on the real spine sweep.

use std::path::Path;

mod common;

use echosurf_testkit::real_data;
use real_data::real;

/// `echosurf reconstruct SEQ --calibration CONFIG --out OUT EXTRA...`.
fn reconstruct_args(seq: &Path, config: &Path, out: &Path, extra: &[&str]) -> Vec<String> {
    let path = |p: &Path| p.display().to_string();
    let mut args = vec![
        "reconstruct".to_string(),
        path(seq),
        "--calibration".into(),
        path(config),
        "--out".into(),
        path(out),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    args
}

#[test]
fn reconstructs_plus_reference_and_refuses_oversized_grids() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("spine.mha");
    let seq = real("SpinePhantomFreehand.igs.mha");
    let cfg = real("PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml");
    let run = common::echosurf_ok(&reconstruct_args(&seq, &cfg, &out, &[]));
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(stdout.contains("147x106x105"), "{stdout}");
    // Defaults from the configuration (NN, MEAN, STICK) give PLUS's reference volume exactly.
    let ours = echosurf::voxel::read_volume_mha(&out).unwrap();
    let reference =
        echosurf::voxel::read_volume_mha(&real("vtkVolumeReconstructorTestNNMEANvolumeRef.mha"))
            .unwrap();
    assert_eq!(ours.dims, reference.dims);
    assert_eq!(ours.values, reference.values);
    assert!((ours.origin_mm - reference.origin_mm).abs().max_element() < 1e-3);
    let header = std::fs::read(&out).unwrap();
    let header = String::from_utf8_lossy(&header[..600]);
    assert!(header.contains("CompressedData = True"), "{header}");
    assert!(header.contains("ElementType = MET_UCHAR"), "{header}");

    // 0.01 mm spacing would need gigabytes: refused with a spacing that fits, nothing written.
    let big = dir.path().join("big.mha");
    let run = common::echosurf(&reconstruct_args(
        &seq,
        &cfg,
        &big,
        &["--spacing", "0.01", "--memory-budget", "50"],
    ));
    assert!(!run.status.success());
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(
        stderr.contains("memory budget") && stderr.contains("a spacing of"),
        "{stderr}"
    );
    assert!(!big.exists());
}
