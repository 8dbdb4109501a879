//! Where a sweep's walls are lost, per band of angle between the wall and the beam (issue #26, item
//! 6): every frame's cut through the truth surface, sampled every half pixel inside the (clipped)
//! image, is a wall point; per angle band it prints the share of wall points whose frame shows an
//! echo (>= `ECHO`, default 40 grey, within 2 px), that `extract`'s default segmentation keeps in its
//! band, that have a kept sample at or above `LEVEL` (default 50) within 1 mm (all kept pixels, then
//! the thinned set handed to the fit), that have an echo crest of their own frame within 1 mm, and
//! that lie within 1 mm of a mesh when one is given. Trial overrides of the defaults (environment):
//! segmentation `REL` (min_edgel_relative_strength), `FRAC` (edgel_fraction), `BACK=1` (backward
//! pass), `WALL=1` (the wall-band preset); crests `PROM`, `RATIO`, `CHAIN`, `PEAK`, `CSMOOTH`.
//! `cargo run --release -p echosurf-bench --example wall_by_angle -- SEQ.mha CONFIG.xml TRUTH.stl
//! [TRUTH2.stl ...] [--mesh MESH.ply]`

use std::path::Path;

use echosurf::io::pose::FramePlane;
use echosurf::io::{self, clip_corners_px};
use echosurf::mesh::Mesh;
use echosurf::metrics::TriangleBvh;
use echosurf::pipeline::{self, ExtractOptions};
use echosurf::progress::NoProgress;
use echosurf::resources::StageMeter;
use echosurf::spatial::PointBuckets;
use glam::DVec3;
use std::collections::HashMap;

/// Upper edges of the angle bands (degrees between the wall's normal and the beam): the issue's
/// 37-46 / 46-53 / 53-60 bands, with everything steeper than 60 last.
const BAND_EDGES_DEG: [f64; 6] = [20.0, 37.0, 46.0, 53.0, 60.0, 90.0];

#[derive(Default, Clone, Copy)]
struct Tally {
    walls: usize,
    echoed: usize,
    in_band: usize,
    echoed_in_band: usize,
    near_kept_sample: usize,
    near_fit_sample: usize,
    near_crest: usize,
    near_mesh: usize,
}

fn env_f64(key: &str, default: f64) -> f64 {
    std::env::var(key)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let mesh_path = args.iter().position(|a| a == "--mesh").and_then(|i| {
        let p = args.get(i + 1).cloned();
        args.drain(i..(i + 2).min(args.len()));
        p
    });
    if args.len() < 3 {
        return Err(
            "usage: wall_by_angle SEQ.mha CONFIG.xml TRUTH.stl [TRUTH2.stl ...] [--mesh MESH]"
                .into(),
        );
    }
    let echo_grey = env_f64("ECHO", 40.0) as f32;
    let level = env_f64("LEVEL", 50.0) as f32;

    let sequence = io::read_sequence(Path::new(&args[0]))?;
    let calibration = io::read_calibration(Path::new(&args[1]))?;
    let truths = args[2..]
        .iter()
        .map(|p| io::read_mesh(Path::new(p)))
        .collect::<echosurf::Result<Vec<Mesh>>>()?;
    let truth = Mesh::merged(&truths);
    let mut options = ExtractOptions::default();
    if let Ok(v) = std::env::var("REL") {
        options.segment.min_edgel_relative_strength = v.parse()?;
    }
    if let Ok(v) = std::env::var("FRAC") {
        options.segment.edgel_fraction = v.parse()?;
    }
    let crest = &mut options.image_crests.crest;
    for (key, field) in [
        ("PROM", &mut crest.min_prominence_grey),
        ("RATIO", &mut crest.min_contrast_ratio),
        ("CHAIN", &mut crest.min_chain_mm),
        ("PEAK", &mut crest.min_local_peak_fraction),
        ("CSMOOTH", &mut crest.smoothing_mm),
    ] {
        if let Ok(v) = std::env::var(key) {
            *field = v.parse()?;
        }
    }
    if std::env::var("BACK").is_ok_and(|v| v == "1") {
        options.segment.backward_pass = true;
    }
    if std::env::var("WALL").is_ok_and(|v| v == "1") {
        options.segment = echosurf::segment::SegmentOptions::wall_band();
    }
    let mut meter = StageMeter::new(&NoProgress);
    let prepared = pipeline::prepare_samples(
        &sequence,
        Some(&calibration),
        &options,
        &mut meter,
        &NoProgress,
    )?;
    let above = |set: &echosurf::samples::SampleSet| -> Vec<DVec3> {
        set.positions
            .iter()
            .zip(&set.intensities)
            .filter(|(_, v)| **v >= level)
            .map(|(p, _)| *p)
            .collect()
    };
    let kept = PointBuckets::new(&above(&prepared.all), 1.0);
    let fitted = PointBuckets::new(&above(&prepared.samples), 1.0);
    let within_1mm =
        |points: &Option<PointBuckets>, x: DVec3| points.as_ref().is_some_and(|b| b.contains(x));
    let crests = echosurf::segment::crests::echo_crests(
        &sequence,
        &prepared.poses,
        calibration.clip,
        options.segment.detect_data_region,
        &options.image_crests.crest,
    )?;
    let crest_points: HashMap<usize, PointBuckets> = crests
        .iter()
        .filter_map(|f| {
            let points: Vec<DVec3> = f
                .crests
                .iter()
                .map(|c| io::sequence::pixel_to_world(&f.image_to_world, c.column, c.row))
                .collect();
            Some((f.frame_index, PointBuckets::new(&points, 1.0)?))
        })
        .collect();
    let mesh = mesh_path
        .map(|p| io::read_mesh(Path::new(&p)))
        .transpose()?;
    let mesh_bvh = mesh.as_ref().map(TriangleBvh::new);

    let (w, h) = (sequence.width, sequence.height);
    let [u_lo, v_lo, u_hi, v_hi] = calibration
        .clip
        .and_then(|c| clip_corners_px(w, h, &c))
        .unwrap_or([0.0, 0.0, (w - 1) as f64, (h - 1) as f64]);
    let mut tallies = [Tally::default(); BAND_EDGES_DEG.len()];
    for pose in &prepared.poses.poses {
        let Some(plane) = FramePlane::new(pose.image_to_world) else {
            continue;
        };
        let beam = plane.v.normalize();
        let mask = &prepared.masks.masks[pose.frame_index];
        let grey = |u: usize, v: usize| sequence.pixel_f32(pose.frame_index, u, v);
        for t in &truth.triangles {
            let p = t.map(|i| truth.vertices[i as usize]);
            let Some(normal) = (p[1] - p[0]).cross(p[2] - p[0]).try_normalize() else {
                continue;
            };
            let d = p.map(|x| (x - plane.origin).dot(plane.normal));
            let mut cut = Vec::with_capacity(2);
            for (a, b) in [(0, 1), (1, 2), (2, 0)] {
                if (d[a] < 0.0) != (d[b] < 0.0) {
                    let s = d[a] / (d[a] - d[b]);
                    cut.push(p[a] + (p[b] - p[a]) * s);
                }
            }
            let [a, b] = match cut[..] {
                [a, b] => [a, b],
                _ => continue,
            };
            let angle = normal.dot(beam).abs().min(1.0).acos().to_degrees();
            let band = BAND_EDGES_DEG
                .iter()
                .position(|&e| angle < e)
                .unwrap_or(BAND_EDGES_DEG.len() - 1);
            let [ua, va] = plane.pixel_of(a);
            let [ub, vb] = plane.pixel_of(b);
            let steps = ((ub - ua).hypot(vb - va) * 2.0).ceil().max(1.0) as usize;
            for k in 0..steps {
                let s = (k as f64 + 0.5) / steps as f64;
                let (u, v) = (ua + (ub - ua) * s, va + (vb - va) * s);
                if !(u >= u_lo && u <= u_hi && v >= v_lo && v <= v_hi) {
                    continue;
                }
                let (ui, vi) = (u.round() as usize, v.round() as usize);
                let tally = &mut tallies[band];
                tally.walls += 1;
                let echoed = (vi.saturating_sub(2)..=(vi + 2).min(h - 1))
                    .flat_map(|y| (ui.saturating_sub(2)..=(ui + 2).min(w - 1)).map(move |x| (x, y)))
                    .any(|(x, y)| grey(x, y) >= echo_grey);
                let in_band = mask[vi * w + ui] != 0;
                tally.echoed += echoed as usize;
                tally.in_band += in_band as usize;
                tally.echoed_in_band += (echoed && in_band) as usize;
                let x = plane.world_of([u, v]);
                tally.near_kept_sample += within_1mm(&kept, x) as usize;
                tally.near_fit_sample += within_1mm(&fitted, x) as usize;
                tally.near_crest += crest_points
                    .get(&pose.frame_index)
                    .is_some_and(|b| b.contains(x)) as usize;
                if let Some(bvh) = &mesh_bvh {
                    tally.near_mesh +=
                        bvh.nearest(x).is_some_and(|n| n.distance_mm <= 1.0) as usize;
                }
            }
        }
    }
    println!(
        "| angle to beam (deg) | wall points | echo >= {echo_grey} | in band | in band, of the echoed | kept sample >= {level} within 1 mm | fitted sample >= {level} within 1 mm | crest of the frame within 1 mm |{}",
        if mesh_bvh.is_some() {
            " mesh within 1 mm |"
        } else {
            ""
        }
    );
    println!(
        "|---|---|---|---|---|---|---|---|{}",
        if mesh_bvh.is_some() { "---|" } else { "" }
    );
    let share = |n: usize, of: usize| {
        if of == 0 {
            "-".to_string()
        } else {
            format!("{:.3}", n as f64 / of as f64)
        }
    };
    let mut lower = 0.0;
    for (t, upper) in tallies.iter().zip(BAND_EDGES_DEG) {
        println!(
            "| {lower:.0}-{upper:.0} | {} | {} | {} | {} | {} | {} | {} |{}",
            t.walls,
            share(t.echoed, t.walls),
            share(t.in_band, t.walls),
            share(t.echoed_in_band, t.echoed),
            share(t.near_kept_sample, t.walls),
            share(t.near_fit_sample, t.walls),
            share(t.near_crest, t.walls),
            if mesh_bvh.is_some() {
                format!(" {} |", share(t.near_mesh, t.walls))
            } else {
                String::new()
            }
        );
        lower = upper;
    }
    Ok(())
}
