//! Synthetic checks of the reconstruction against hand-computed PLUS arithmetic.

use std::collections::BTreeMap;

use glam::{DMat4, DVec3};

use super::*;
use crate::io::{FramePose, PixelData, TrackedFrame};
use crate::progress::NoProgress;

/// A U8 sequence of `frames.len()` frames of w x h, each frame filled by `pixel(frame, u, v)`.
fn sequence(
    w: usize,
    h: usize,
    n: usize,
    pixel: impl Fn(usize, usize, usize) -> u8,
) -> TrackedSequence {
    let mut px = Vec::with_capacity(w * h * n);
    for f in 0..n {
        for v in 0..h {
            for u in 0..w {
                px.push(pixel(f, u, v));
            }
        }
    }
    TrackedSequence {
        width: w,
        height: h,
        channels: 1,
        orientation: "MF".into(),
        frames: vec![
            TrackedFrame {
                image_valid: true,
                ..Default::default()
            };
            n
        ],
        pixels: PixelData::U8(px),
        header: BTreeMap::new(),
    }
}

fn poses(mats: &[DMat4]) -> PoseResolution {
    PoseResolution {
        poses: mats
            .iter()
            .enumerate()
            .map(|(i, m)| FramePose {
                frame_index: i,
                image_to_world: *m,
            })
            .collect(),
        skipped: Vec::new(),
        world_frame: "Reference".into(),
    }
}

/// Image plane z = `z_mm`, pixel size `px_mm`, image x -> world x, image y -> world y.
fn plane(px_mm: f64, z_mm: f64) -> DMat4 {
    DMat4::from_translation(DVec3::new(0.0, 0.0, z_mm)) * DMat4::from_scale(DVec3::splat(px_mm))
}

fn nn_mean() -> VoxelOptions {
    VoxelOptions {
        spacing_mm: DVec3::splat(1.0),
        interpolation: Interpolation::NearestNeighbor,
        compounding: Compounding::Mean,
        ..Default::default()
    }
}

fn u8_values(v: &Volume) -> &[u8] {
    match &v.values {
        VoxelValues::U8(x) => x,
        VoxelValues::F32(_) => panic!("expected u8 volume"),
    }
}

#[test]
fn grid_is_fitted_to_clipped_frame_corners() {
    // Two 11x5 frames, 0.3 mm pixels: x spans 0..3.0 mm, y 0..1.2 mm; z at 0 and 2.2 mm.
    let seq = sequence(11, 5, 2, |_, _, _| 10);
    let p = poses(&[plane(0.3, 0.0), plane(0.3, 2.2)]);
    let opts = nn_mean();
    let g = grid_geometry(&seq, &p, &opts).unwrap();
    // dims = round(span / spacing) + 1: x 3.0 -> 4, y 1.2 -> 2, z 2.2 -> 3.
    assert_eq!(g.dims, [4, 2, 3]);
    let ceil = VoxelOptions {
        grid_rounding: GridRounding::Ceil,
        ..opts.clone()
    };
    assert_eq!(grid_geometry(&seq, &p, &ceil).unwrap().dims, [4, 3, 4]);
    let floor = VoxelOptions {
        grid_rounding: GridRounding::Floor,
        ..opts.clone()
    };
    assert_eq!(grid_geometry(&seq, &p, &floor).unwrap().dims, [4, 2, 3]);
    assert!((g.origin_mm - DVec3::ZERO).length() < 1e-12);
    // A clip rectangle 2..(2+3) x 1..(1+10): far edge included, clamped to the image.
    let clipped = VoxelOptions {
        clip: Some(ClipRect {
            origin_px: [2, 1],
            size_px: [3, 10],
        }),
        ..opts
    };
    let g = grid_geometry(&seq, &p, &clipped).unwrap();
    assert!((g.origin_mm - DVec3::new(0.6, 0.3, 0.0)).length() < 1e-12);
    // x: 0.6..1.5 mm -> round(0.9) + 1 = 2; y: 0.3..1.2 -> 2.
    assert_eq!(g.dims, [2, 2, 3]);
}

#[test]
fn explicit_output_extent_sets_grid() {
    let seq = sequence(4, 4, 1, |_, _, _| 1);
    let p = poses(&[plane(1.0, 0.0)]);
    let opts = VoxelOptions {
        output_origin_mm: Some(DVec3::new(10.0, 20.0, 30.0)),
        output_extent: Some([2, 5, 0, 3, -1, 1]),
        spacing_mm: DVec3::new(0.5, 1.0, 2.0),
        ..nn_mean()
    };
    let g = grid_geometry(&seq, &p, &opts).unwrap();
    assert_eq!(g.dims, [4, 4, 3]);
    assert!((g.origin_mm - DVec3::new(11.0, 20.0, 28.0)).length() < 1e-12);
}

#[test]
fn nearest_neighbour_mean_truncates_like_plus() {
    // 1 mm pixels on 1 mm voxels: each pixel hits one voxel. Frame values 100, 201, 50 at the same
    // plane. PLUS: out = (in*256 + out*acc) / (acc + 256), integer division.
    let vals = [100u8, 201, 50];
    let seq = sequence(3, 2, 3, |f, _, _| vals[f]);
    let p = poses(&[plane(1.0, 0.0), plane(1.0, 0.0), plane(1.0, 0.0)]);
    let v = reconstruct_volume(&seq, &p, &nn_mean(), &NoProgress).unwrap();
    // 100; (201*256 + 100*256)/512 = 150 (150.5 truncated); (50*256 + 150*512)/768 = 116 (116.67).
    assert_eq!(v.dims, [3, 2, 1]);
    assert!(u8_values(&v).iter().all(|&x| x == 116));
    assert!(v.accumulation.iter().all(|&a| a == 768));
    assert_eq!(v.stats.pixels_inserted, 18);
    assert_eq!(v.stats.voxels_hit, 6);
}

#[test]
fn maximum_and_latest_compounding() {
    let vals = [100u8, 201, 50];
    let seq = sequence(2, 2, 3, |f, _, _| vals[f]);
    let p = poses(&[plane(1.0, 0.0); 3]);
    for (mode, expect) in [(Compounding::Maximum, 201u8), (Compounding::Latest, 50)] {
        let opts = VoxelOptions {
            compounding: mode,
            ..nn_mean()
        };
        let v = reconstruct_volume(&seq, &p, &opts, &NoProgress).unwrap();
        assert!(u8_values(&v).iter().all(|&x| x == expect), "{mode:?}");
        assert!(v.accumulation.iter().all(|&a| a == 256));
    }
}

#[test]
fn several_pixels_per_voxel_round_to_nearest_voxel() {
    // 0.25 mm pixels into 1 mm voxels: pixel u lands at x = 0.25 u, rounded with floor(x + 0.5),
    // so voxel 0 gets u = 0, 1 (x < 0.5) and voxel 1 gets u = 2..5 (0.5 <= x < 1.5).
    let seq = sequence(8, 1, 1, |_, u, _| (u * 10) as u8);
    let p = poses(&[plane(0.25, 0.0)]);
    let v = reconstruct_volume(&seq, &p, &nn_mean(), &NoProgress).unwrap();
    assert_eq!(v.dims, [3, 1, 1]);
    // Running truncated means: voxel 0: 0, then (10*256 + 0)/512 = 5.
    // voxel 1: 20, (30*256+20*256)/512 = 25, (40*256+25*512)/768 = 30, (50*256+30*768)/1024 = 35.
    // voxel 2: u = 6, 7 -> 60, (70*256+60*256)/512 = 65.
    assert_eq!(u8_values(&v), &[5, 35, 65]);
    assert_eq!(v.accumulation, vec![512, 1024, 512]);
}

#[test]
fn trilinear_splat_weights_and_constant_image() {
    // One pixel at world (0.25, 0.5, 0): weights (1-fx)(1-fy) etc. over 4 voxels (z exact).
    let seq = sequence(1, 1, 1, |_, _, _| 200);
    let m = DMat4::from_translation(DVec3::new(0.25, 0.5, 0.0));
    let mut p = poses(&[m]);
    let opts = VoxelOptions {
        interpolation: Interpolation::Linear,
        output_origin_mm: Some(DVec3::ZERO),
        output_extent: Some([0, 1, 0, 1, 0, 0]),
        ..nn_mean()
    };
    let v = reconstruct_volume(&seq, &p, &opts, &NoProgress).unwrap();
    // weights: (0,0) .75*.5 = .375 -> 96; (1,0) .25*.5 = .125 -> 32; same for y = 1.
    assert_eq!(v.accumulation, vec![96, 32, 96, 32]);
    assert!(u8_values(&v).iter().all(|&x| x == 200));

    // A constant image on an oblique plane: every voxel reached keeps the constant (a weighted
    // mean of equal values), and the accumulation sums to 256 per inserted pixel up to rounding.
    let seq = sequence(40, 30, 1, |_, _, _| 77);
    let oblique = DMat4::from_rotation_y(0.4) * DMat4::from_rotation_x(0.3) * plane(0.11, 0.0);
    p = poses(&[oblique]);
    let opts = VoxelOptions {
        interpolation: Interpolation::Linear,
        spacing_mm: DVec3::splat(0.5),
        ..nn_mean()
    };
    let v = reconstruct_volume(&seq, &p, &opts, &NoProgress).unwrap();
    let hit: Vec<u8> = u8_values(&v)
        .iter()
        .zip(&v.accumulation)
        .filter(|&(_, &a)| a != 0)
        .map(|(&x, _)| x)
        .collect();
    assert!(!hit.is_empty());
    assert!(hit.iter().all(|&x| x == 77));
    let total: f64 = v.accumulation.iter().map(|&a| a as f64).sum();
    let expected = v.stats.pixels_inserted as f64 * 256.0;
    // Each voxel update rounds its accumulation by at most 0.5; 8 updates per pixel.
    assert!((total - expected).abs() <= 0.5 * 8.0 * v.stats.pixels_inserted as f64);
    assert!((total - expected).abs() / expected < 0.01);
}

#[test]
fn clip_rectangle_and_pixel_rejection_limit_inserted_pixels() {
    let seq = sequence(10, 10, 1, |_, u, _| if u < 5 { 5 } else { 100 });
    let p = poses(&[plane(1.0, 0.0)]);
    let clip = VoxelOptions {
        clip: Some(ClipRect {
            origin_px: [2, 3],
            size_px: [4, 4],
        }),
        ..nn_mean()
    };
    let v = reconstruct_volume(&seq, &p, &clip, &NoProgress).unwrap();
    // Columns 2..=6 and rows 3..=7: PLUS includes origin + size.
    assert_eq!(v.stats.pixels_inserted, 25);
    assert_eq!(v.dims, [5, 5, 1]);
    let reject = VoxelOptions {
        pixel_rejection_threshold: Some(10.0),
        ..nn_mean()
    };
    let v = reconstruct_volume(&seq, &p, &reject, &NoProgress).unwrap();
    assert_eq!(v.stats.pixels_inserted, 50);
}

#[test]
fn output_does_not_depend_on_thread_count() {
    let seq = sequence(64, 48, 6, |f, u, v| ((u * 7 + v * 13 + f * 31) % 251) as u8);
    let mats: Vec<DMat4> = (0..6)
        .map(|i| {
            DMat4::from_rotation_x(0.05 * i as f64)
                * DMat4::from_translation(DVec3::new(0.1 * i as f64, 0.0, 0.7 * i as f64))
                * plane(0.09, 0.0)
        })
        .collect();
    let p = poses(&mats);
    for (interpolation, position_arithmetic) in [
        (
            Interpolation::NearestNeighbor,
            PositionArithmetic::FixedPoint14,
        ),
        (Interpolation::Linear, PositionArithmetic::FixedPoint14),
        (Interpolation::NearestNeighbor, PositionArithmetic::Double),
        (Interpolation::Linear, PositionArithmetic::Double),
    ] {
        let opts = VoxelOptions {
            interpolation,
            position_arithmetic,
            spacing_mm: DVec3::splat(0.3),
            hole_filling: HoleFilling::stick(9, 1),
            ..nn_mean()
        };
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| reconstruct_volume(&seq, &p, &opts, &NoProgress).unwrap())
        };
        let one = run(1);
        let three = run(3);
        assert_eq!(one, three, "{interpolation:?}");
        assert!(one.stats.voxels_filled > 0);
    }
}

#[test]
fn memory_budget_refuses_with_a_spacing_that_fits() {
    let seq = sequence(100, 100, 2, |_, _, _| 9);
    let p = poses(&[plane(0.1, 0.0), plane(0.1, 10.0)]);
    // The budget counts what the process holds already (here the whole test harness, which other
    // tests change): the grid gets 4 MB on top of that.
    let grid_room = 4_000_000u64;
    let opts = VoxelOptions {
        spacing_mm: DVec3::splat(0.02),
        memory_budget_bytes: crate::budget::resident_bytes() + grid_room,
        hole_filling: HoleFilling::stick(9, 1),
        ..nn_mean()
    };
    let err = reconstruct_volume(&seq, &p, &opts, &NoProgress).unwrap_err();
    let Error::ResourceLimit(msg) = &err else {
        panic!("expected ResourceLimit, got {err:?}");
    };
    let suggested: f64 = msg
        .split("a spacing of ")
        .nth(1)
        .and_then(|s| s.split_whitespace().next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no spacing in '{msg}'"));
    assert!(suggested > 0.02);
    let fits = VoxelOptions {
        spacing_mm: DVec3::splat(suggested),
        memory_budget_bytes: u64::MAX,
        ..opts
    };
    let geometry = grid_geometry(&seq, &p, &fits).unwrap();
    let grid_bytes = estimated_memory_bytes(&geometry, seq.pixels.element_type(), &fits);
    assert!(grid_bytes <= grid_room as u128, "{grid_bytes}");
    let v = reconstruct_volume(&seq, &p, &fits, &NoProgress).unwrap();
    assert_eq!(v.dims, geometry.dims);
}

/// A 1-voxel-wide column: hit voxels at z = 0 (100) and z = 4 (200), holes between.
fn column() -> (Vec<u8>, Vec<u16>, [usize; 3]) {
    let dims = [1, 1, 5];
    let mut v = vec![0u8; 5];
    let mut a = vec![0u16; 5];
    v[0] = 100;
    a[0] = 256;
    v[4] = 200;
    a[4] = 256;
    (v, a, dims)
}

#[test]
fn stick_filling_uses_plus_weights() {
    let (v, a, dims) = column();
    let (out, filled) =
        fill::fill_holes(&v, &a, dims, &HoleFilling::stick(9, 1), true, &NoProgress);
    assert_eq!(filled, 3);
    // Hole at z = 2: fwd 2, rvs 2, total 5; PLUS weights fwd (rvs+1)/total = 0.6:
    // 0.4 * 100 + 0.6 * 200 = 160. z = 1: fwd 3, rvs 1 -> w_fwd = 2/5 -> 0.6*100 + 0.4*200 = 140.
    // z = 3: fwd 1, rvs 3 -> w_fwd = 4/5 -> 0.2*100 + 0.8*200 = 180.
    assert_eq!(out, vec![100, 140, 160, 180, 200]);
    // A stick longer than the limit finds nothing: holes stay 0.
    let (out, filled) =
        fill::fill_holes(&v, &a, dims, &HoleFilling::stick(4, 1), true, &NoProgress);
    assert_eq!(out, vec![100, 0, 0, 0, 200]);
    assert_eq!(filled, 0);
}

#[test]
fn gaussian_filling_and_min_ratio() {
    // 5x5x5 block, all hit with value 60 except the centre.
    let dims = [5, 5, 5];
    let mut v = vec![60u8; 125];
    let mut a = vec![256u16; 125];
    v[62] = 0;
    a[62] = 0;
    let (out, filled) = fill::fill_holes(
        &v,
        &a,
        dims,
        &HoleFilling::gaussian(3, 1.0, 0.5),
        true,
        &NoProgress,
    );
    assert_eq!(out[62], 60);
    assert_eq!(filled, 1);
    // 26 of 27 known = 0.963: a ratio of 0.97 is not met, the hole stays 0.
    let (out, filled) = fill::fill_holes(
        &v,
        &a,
        dims,
        &HoleFilling::gaussian(3, 1.0, 0.97),
        true,
        &NoProgress,
    );
    assert_eq!((out[62], filled), (0, 0));
    // Gaussian weights: a hole between 0 and 90 planes gets their weighted mean.
    let mut v = vec![0u8; 27];
    let mut a = vec![0u16; 27];
    for i in 0..9 {
        v[18 + i] = 90;
        a[i] = 256;
        a[18 + i] = 256;
    }
    let (out, _) = fill::fill_holes(
        &v,
        &a,
        [3, 3, 3],
        &HoleFilling::gaussian(3, 1.0, 0.1),
        true,
        &NoProgress,
    );
    assert_eq!(out[13], 45);
}

#[test]
fn mha_round_trip_plain_and_compressed() {
    let dir = tempfile::tempdir().unwrap();
    let seq = sequence(20, 10, 2, |f, u, v| (u + v * 3 + f * 40) as u8);
    let p = poses(&[plane(0.2, 0.0), plane(0.2, 1.5)]);
    let v = reconstruct_volume(&seq, &p, &nn_mean(), &NoProgress).unwrap();
    for compress in [false, true] {
        let path = dir.path().join(format!("v{compress}.mha"));
        write_volume_mha(&path, &v, compress).unwrap();
        let text = std::fs::read(&path).unwrap();
        let header = String::from_utf8_lossy(&text[..200.min(text.len())]).to_string();
        assert!(header.starts_with("ObjectType = Image\nNDims = 3\n"));
        let back = read_volume_mha(&path).unwrap();
        assert_eq!(back.dims, v.dims);
        assert_eq!(back.values, v.values);
        assert_eq!(back.origin_mm, v.origin_mm);
        assert_eq!(back.spacing_mm, v.spacing_mm);
        assert_eq!(back.element_type, ElementType::U8);
    }
    // Truncated data is an error naming the file, not a panic.
    let path = dir.path().join("vfalse.mha");
    let bytes = std::fs::read(&path).unwrap();
    let cut = dir.path().join("cut.mha");
    std::fs::write(&cut, &bytes[..bytes.len() - 5]).unwrap();
    let err = read_volume_mha(&cut).unwrap_err();
    assert_eq!(err.problem(), Some(crate::FormatProblem::Truncated));
    assert!(err.to_string().contains("cut.mha"));
}

const NN_MEAN_XML: &str = r#"<PlusConfiguration version="2.1">
  <VolumeReconstruction OutputSpacing="0.5 0.5 0.5"
    ClipRectangleOrigin="0 0" ClipRectangleSize="820 616"
    Interpolation="NEAREST_NEIGHBOR" Optimization="FULL"
    CompoundingMode="MEAN" FillHoles="ON" NumberOfThreads="1">
    <HoleFilling>
      <HoleFillingElement Type="STICK" StickLengthLimit="9" NumberOfSticksToUse="1" />
      <HoleFillingElement Type="GAUSSIAN" Size="5" Stdev="0.6667" MinimumKnownVoxelsRatio="0.5" />
    </HoleFilling>
  </VolumeReconstruction>
</PlusConfiguration>"#;

#[test]
fn options_from_plus_config() {
    let path = std::path::Path::new("cfg.xml");
    let o = options_from_config_xml(NN_MEAN_XML, path).unwrap();
    assert_eq!(o.spacing_mm, DVec3::splat(0.5));
    assert_eq!(o.interpolation, Interpolation::NearestNeighbor);
    assert_eq!(o.compounding, Compounding::Mean);
    assert_eq!(
        o.clip,
        Some(ClipRect {
            origin_px: [0, 0],
            size_px: [820, 616]
        })
    );
    assert_eq!(
        o.hole_filling.elements,
        vec![
            HoleFillingElement::Stick {
                length_limit: 9,
                sticks_to_use: 1
            },
            HoleFillingElement::Gaussian {
                size: 5,
                stdev: 0.6667,
                min_ratio: 0.5
            }
        ]
    );
    // The attribute map of a calibration gives the same settings (STICK assumed for FillHoles).
    let mut cal = crate::io::Calibration::from_image_to_probe(DMat4::IDENTITY);
    for (k, v) in [
        ("OutputSpacing", "0.5 0.5 0.5"),
        ("Interpolation", "NEAREST_NEIGHBOR"),
        ("CompoundingMode", "MEAN"),
        ("FillHoles", "ON"),
    ] {
        cal.volume_reconstruction.insert(k.into(), v.into());
    }
    let o = VoxelOptions::from_calibration(&cal).unwrap();
    assert_eq!(o.interpolation, Interpolation::NearestNeighbor);
    assert_eq!(o.hole_filling, HoleFilling::stick(9, 1));
    // PLUS defaults: LINEAR, MEAN; deprecated Compounding="OFF" means LATEST.
    cal.volume_reconstruction.clear();
    cal.volume_reconstruction
        .insert("Compounding".into(), "OFF".into());
    let o = VoxelOptions::from_calibration(&cal).unwrap();
    assert_eq!(o.interpolation, Interpolation::Linear);
    assert_eq!(o.compounding, Compounding::Latest);
    // Bad values are errors naming the attribute (and the file).
    let bad = NN_MEAN_XML.replace("OutputSpacing=\"0.5 0.5 0.5\"", "OutputSpacing=\"0.5 x\"");
    let err = options_from_config_xml(&bad, path).unwrap_err();
    assert!(err.to_string().contains("OutputSpacing") && err.to_string().contains("cfg.xml"));
    let bad = NN_MEAN_XML.replace("StickLengthLimit=\"9\"", "");
    assert!(options_from_config_xml(&bad, path).is_err());
}

#[test]
fn bad_inputs_are_errors() {
    let seq = sequence(4, 4, 1, |_, _, _| 1);
    let p = poses(&[plane(1.0, 0.0)]);
    let zero = VoxelOptions {
        spacing_mm: DVec3::new(0.5, 0.0, 0.5),
        ..nn_mean()
    };
    assert!(matches!(
        reconstruct_volume(&seq, &p, &zero, &NoProgress),
        Err(Error::InvalidInput(_))
    ));
    let none = poses(&[]);
    assert!(reconstruct_volume(&seq, &none, &nn_mean(), &NoProgress).is_err());
    let mut far = poses(&[plane(1.0, 0.0)]);
    far.poses[0].frame_index = 7;
    assert!(reconstruct_volume(&seq, &far, &nn_mean(), &NoProgress).is_err());
    let nan = poses(&[DMat4::from_scale(DVec3::splat(f64::NAN))]);
    assert!(reconstruct_volume(&seq, &nan, &nn_mean(), &NoProgress).is_err());
}
