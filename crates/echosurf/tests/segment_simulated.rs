//! Band segmentation on simulated sweeps (crate::simulate) against the phantom's exact distance field.

use echosurf::io::{FramePose, PoseResolution};
use echosurf::progress::NoProgress;
use echosurf::segment::{BandMasks, InitialBand, SegmentOptions, segment_sequence};
use echosurf::simulate::{
    PhantomKind, Simulation, SimulationOptions, build_phantom, simulate_sweeps,
};
use glam::DVec3;

fn simulated(kind: PhantomKind) -> Simulation {
    let options = SimulationOptions {
        phantom: kind,
        frames_per_sweep: 12,
        sweeps: Some(1),
        width_px: 200,
        height_px: 160,
        pixel_size_mm: 0.2,
        ..Default::default()
    }
    .without_errors();
    simulate_sweeps(&options, &NoProgress).unwrap()
}

/// Poses where the pixels really were (the test judges the segmentation, not the tracking), for the
/// frames whose beam meets the object in at least a quarter of the columns: the sweep's run-in and
/// run-out frames image only water and speckle, where the band has nothing to follow.
fn true_poses(sim: &Simulation, kind: &PhantomKind) -> PoseResolution {
    let phantom = build_phantom(kind).unwrap();
    let (w, h) = (sim.sequence.width, sim.sequence.height);
    PoseResolution {
        poses: sim
            .true_image_to_world
            .iter()
            .enumerate()
            .filter(|(_, m)| {
                let hit = (0..w)
                    .filter(|&u| {
                        (0..h).any(|v| {
                            phantom
                                .distance_and_gradient(
                                    m.transform_point3(DVec3::new(u as f64, v as f64, 0.0)),
                                )
                                .0
                                < 0.0
                        })
                    })
                    .count();
                4 * hit >= w
            })
            .map(|(frame_index, &image_to_world)| FramePose {
                frame_index,
                image_to_world,
            })
            .collect(),
        skipped: Vec::new(),
        world_frame: "Reference".into(),
    }
}

/// (share of the visible-surface pixels within 1 mm that are kept, share of all pixels kept).
/// Visible surface: the first boundary each column's beam meets (below it the object shadows everything),
/// where the surface faces the beam within 60 degrees (steeper walls return no echo, as in the paper's
/// Fig. 5, so no band method can see them).
fn coverage(sim: &Simulation, kind: &PhantomKind, masks: &BandMasks) -> (f64, f64) {
    let phantom = build_phantom(kind).unwrap();
    let (w, h) = (sim.sequence.width, sim.sequence.height);
    let (mut near, mut near_kept, mut kept) = (0usize, 0usize, 0usize);
    let segmented: Vec<usize> = (0..masks.masks.len())
        .filter(|&f| masks.masks[f].contains(&255))
        .collect();
    for &f in &segmented {
        let m = &sim.true_image_to_world[f];
        let mask = &masks.masks[f];
        kept += mask.iter().filter(|&&x| x != 0).count();
        let beam = m.y_axis.truncate().normalize();
        for u in 0..w {
            let world = |v: usize| m.transform_point3(DVec3::new(u as f64, v as f64, 0.0));
            let Some(first_inside) =
                (0..h).find(|&v| phantom.distance_and_gradient(world(v)).0 < 0.0)
            else {
                continue;
            };
            for v in 0..h.min(first_inside + 10) {
                let (d, g) = phantom.distance_and_gradient(world(v));
                if d.abs() <= 1.0 && g.normalize().dot(beam).abs() >= 0.5 {
                    near += 1;
                    near_kept += (mask[v * w + u] != 0) as usize;
                }
            }
        }
    }
    let all = w * h * segmented.len();
    eprintln!(
        "{} frames segmented; visible-surface pixels kept {near_kept}/{near}, kept {kept}/{all}",
        segmented.len()
    );
    assert!(
        near > 1000,
        "the sweep must image the surface ({near} pixels)"
    );
    (near_kept as f64 / near as f64, kept as f64 / all as f64)
}

/// Known weakness, kept as an executable target: on the simulated sphere the band follows the arc in the
/// frames where its echo is strong, but in frames where the faint arc sits at the image top or at the
/// steep sides the M edgels are mostly speckle, the band percolates over the frame (kept ~50 %) and
/// ~4 % of the visible-surface pixels are lost (defaults: 95.9 % kept near the surface, 50.8 % of all
/// pixels). Stricter edgels trade one for the other (relative floor 0.5 / M 0.4 x columns: 89.6 % / 28.9 %;
/// 0.6 / 0.3: 83.6 % / 18.5 %). Run with `cargo test -- --ignored`.
#[test]
#[ignore = "known weakness: band percolates through speckle where the simulated echo is faint"]
fn simulated_sphere_auto_init() {
    let kind = PhantomKind::Sphere;
    let sim = simulated(kind.clone());
    let masks = segment_sequence(
        &sim.sequence,
        &true_poses(&sim, &kind),
        None,
        &InitialBand::Auto,
        &SegmentOptions::default(),
        &NoProgress,
    )
    .unwrap();
    if let Ok(path) = std::env::var("SEGMENT_PREVIEW") {
        let frames = echosurf::segment::default_preview_frames(&masks, 9);
        echosurf::segment::write_band_preview(
            std::path::Path::new(&path),
            &sim.sequence,
            &masks,
            &frames,
        )
        .unwrap();
    }
    let (kept_near, kept_all) = coverage(&sim, &kind, &masks);
    assert!(
        kept_near >= 0.99,
        "kept {kept_near} of the pixels within 1 mm"
    );
    assert!(kept_all <= 0.30, "kept {kept_all} of all pixels");
}
