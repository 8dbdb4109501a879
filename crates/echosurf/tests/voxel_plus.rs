//! Against PLUS itself: the spine sweep reconstructed with PLUS's NN_MEAN test configuration must
//! reproduce PLUS's regression reference volume (vtkVolumeReconstructorTestNNMEANvolumeRef.mha).

use echosurf::io::{ReferenceChoice, read_calibration, read_sequence, resolve_poses};
use echosurf::progress::NoProgress;
use echosurf::voxel::{
    GridRounding, Interpolation, Volume, grid_geometry, options_from_config_xml, read_volume_mha,
    reconstruct_volume,
};

use echosurf_testkit::real_data;
use real_data::real;

struct Agreement {
    total: usize,
    within_one: usize,
    exact: usize,
    hit_total: usize,
    hit_within_one: usize,
    hole_total: usize,
    hole_within_one: usize,
}

fn compare(ours: &Volume, reference: &Volume) -> Agreement {
    let a = ours.values_f32();
    let b = reference.values_f32();
    let hit = ours.hit_mask();
    let mut r = Agreement {
        total: a.len(),
        within_one: 0,
        exact: 0,
        hit_total: 0,
        hit_within_one: 0,
        hole_total: 0,
        hole_within_one: 0,
    };
    for i in 0..a.len() {
        let d = (a[i] - b[i]).abs();
        let ok = d <= 1.0;
        r.within_one += usize::from(ok);
        r.exact += usize::from(d == 0.0);
        if hit[i] {
            r.hit_total += 1;
            r.hit_within_one += usize::from(ok);
        } else {
            r.hole_total += 1;
            r.hole_within_one += usize::from(ok);
        }
    }
    r
}

#[test]
fn spine_nn_mean_matches_plus_reference() {
    let seq_path = real("SpinePhantomFreehand.igs.mha");
    let cfg_path = real("PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml");
    let sequence = read_sequence(&seq_path).unwrap();
    let calibration = read_calibration(&cfg_path).unwrap();
    let poses = resolve_poses(
        &sequence,
        Some(&calibration),
        ReferenceChoice::Auto,
        &seq_path,
    )
    .unwrap();
    let xml = std::fs::read_to_string(&cfg_path).unwrap();
    let options = options_from_config_xml(&xml, &cfg_path).unwrap();
    let ours = reconstruct_volume(&sequence, &poses, &options, &NoProgress).unwrap();
    let reference =
        read_volume_mha(&real("vtkVolumeReconstructorTestNNMEANvolumeRef.mha")).unwrap();

    assert_eq!(ours.dims, reference.dims);
    assert_eq!(ours.dims, [147, 106, 105]);
    assert!((ours.spacing_mm - reference.spacing_mm).abs().max_element() < 1e-12);
    // The reference header prints the origin to 6 significant digits.
    assert!(
        (ours.origin_mm - reference.origin_mm).abs().max_element() < 1e-3,
        "origin {:?} vs {:?}",
        ours.origin_mm,
        reference.origin_mm
    );

    let r = compare(&ours, &reference);
    let pct = |a: usize, b: usize| 100.0 * a as f64 / b.max(1) as f64;
    eprintln!(
        "all voxels: {} / {} within +/-1 ({:.3}%), exact {:.3}%; hit: {:.3}% of {}; holes: {:.3}% of {}; stats {:?}",
        r.within_one,
        r.total,
        pct(r.within_one, r.total),
        pct(r.exact, r.total),
        pct(r.hit_within_one, r.hit_total),
        r.hit_total,
        pct(r.hole_within_one, r.hole_total),
        r.hole_total,
        ours.stats
    );
    // Same pose chain, same 14-bit fixed-point pixel mapping, same integer running mean and the
    // same STICK rule: PLUS's reference is reproduced byte for byte, hit voxels and filled holes.
    assert_eq!(r.exact, r.total);
    assert_eq!(ours.values, reference.values);
    assert!(r.hit_total > 300_000 && r.hole_total > 1_000_000);
    assert_eq!(ours.stats.frames_inserted, 21);
    assert_eq!(ours.stats.accumulation_overflows, 0);
}

/// The older PLUS reconstruction of the same sweep (`SpinePhantomFreehandReconstructed.mha`, made
/// with the LINEAR / MEAN / STICK configuration) truncated the voxel count: with the `Floor` grid
/// rule the trilinear route reproduces its grid and every grey level.
#[test]
fn spine_linear_mean_matches_older_plus_reconstruction() {
    let seq_path = real("SpinePhantomFreehand.igs.mha");
    let cfg_path = real("PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml");
    let sequence = read_sequence(&seq_path).unwrap();
    let calibration = read_calibration(&cfg_path).unwrap();
    let poses = resolve_poses(
        &sequence,
        Some(&calibration),
        ReferenceChoice::Auto,
        &seq_path,
    )
    .unwrap();
    let xml = std::fs::read_to_string(&cfg_path).unwrap();
    let mut options = options_from_config_xml(&xml, &cfg_path).unwrap();
    assert_eq!(options.interpolation, Interpolation::Linear);
    let old = read_volume_mha(&real("SpinePhantomFreehandReconstructed.mha")).unwrap();
    options.grid_rounding = GridRounding::Ceil;
    assert_eq!(
        grid_geometry(&sequence, &poses, &options).unwrap().dims,
        [148, 107, 105]
    );
    options.grid_rounding = GridRounding::Floor;
    let ours = reconstruct_volume(&sequence, &poses, &options, &NoProgress).unwrap();
    assert_eq!(ours.dims, old.dims);
    assert_eq!(ours.dims, [147, 106, 104]);
    assert!((ours.origin_mm - old.origin_mm).abs().max_element() < 1e-3);
    let r = compare(&ours, &old);
    let pct = |a: usize, b: usize| 100.0 * a as f64 / b.max(1) as f64;
    eprintln!(
        "LINEAR vs older PLUS: {:.3}% within +/-1, {:.3}% exact; hit {:.3}%, holes {:.3}%",
        pct(r.within_one, r.total),
        pct(r.exact, r.total),
        pct(r.hit_within_one, r.hit_total),
        pct(r.hole_within_one, r.hole_total)
    );
    // With PLUS's fixed-point trilinear weights and running mean, every voxel is reproduced.
    assert_eq!(r.exact, r.total);
    assert_eq!(ours.values, old.values);
}
