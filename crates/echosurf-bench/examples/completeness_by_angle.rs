//! Where an extracted surface is complete: simulates a phantom (duck or hand, seed 1), extracts with the
//! defaults, and prints the completeness (share of truth within 1 mm of the mesh) per wall, per band of
//! angle between the truth's normal and the nearest sweeping frame's beam, and per facing sign (outward
//! normal against the beam: the side facing the probe). Environment overrides: `MAXS` (sample budget),
//! `W` (smoothing), `BIN` (sample block mm), `ECHO` (echo margin mm, 0 = uniform thinning), `ISO`, `SHEET=iso|ridge` (default: auto, as `extract`),
//! `MINCOMP` (smallest piece kept, mm^2), `MINFRAMES` (least frames echoing a piece), `BRIDGE` (largest gap between pieces joined, mm, 0 = off), `CHAIN=1` (chained edgels), `BACK=1` (backward band pass), `SEED`, and for the ridge sheet
//! `SHEET_H` (smoothing mm), `SHEET_REACH` (mm), `SHEET_BRIDGE` (mm, 0 = off), `HOLE` (largest hole closed,
//! perimeter mm).
//! `cargo run --release --example completeness_by_angle -- duck [mesh.ply]`
use echosurf::metrics::{CompareOptions, compare_meshes, triangle_mask};
use echosurf::pipeline::{self, ExtractOptions};
use echosurf::progress::NoProgress;
use echosurf_sim::{PhantomKind, SimulationOptions, simulate};
use glam::DVec3;

fn main() -> echosurf::Result<()> {
    let kind = match std::env::args().nth(1).as_deref() {
        Some("hand") => PhantomKind::Hand,
        _ => PhantomKind::Duck,
    };
    let sim_options = SimulationOptions {
        phantom: kind,
        seed: std::env::var("SEED")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(1),
        ..SimulationOptions::default()
    };
    let sim = simulate(&sim_options, &NoProgress)?;
    let mut options = ExtractOptions {
        seed: 1,
        ..ExtractOptions::default()
    };
    let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse::<f64>().ok());
    if let Some(v) = env("MAXS") {
        options.max_samples = v as usize;
    }
    if let Some(v) = env("W") {
        options.fit.smoothing = v;
    }
    if let Some(v) = env("ECHO") {
        options.echo_margin_mm = if v > 0.0 { Some(v) } else { None };
    }
    if let Some(v) = env("SHEET_H") {
        options.echo_sheet.smoothing_mm = v;
    }
    if let Some(v) = env("SHEET_BRIDGE") {
        options.echo_sheet.bridge_mm = v;
    }
    if let Some(v) = env("SHEET_REACH") {
        options.echo_sheet.reach_mm = v;
    }
    if let Some(v) = env("WEAK") {
        options.weak_echoes.level_fraction = v;
    }
    if let Some(v) = env("WEAK_REACH") {
        options.weak_echoes.reach_mm = v;
    }
    if let Some(v) = env("HOLE") {
        options.echo_sheet.max_hole_perimeter_mm = v;
    }
    match std::env::var("SHEET").as_deref() {
        Ok("iso") => options.sheet = echosurf::pipeline::Sheet::Iso,
        Ok("ridge") => options.sheet = echosurf::pipeline::Sheet::EchoRidge,
        _ => {}
    }
    if let Some(v) = env("MINFRAMES") {
        options.min_echo_frames = v as usize;
    }
    if let Some(v) = env("MINCOMP") {
        options.min_component_area_mm2 = Some(v);
    }
    if env("CHAIN") == Some(1.0) {
        options.segment = echosurf::segment::SegmentOptions::chained();
    }
    if let Some(v) = env("BRIDGE") {
        options.bridge_gap_mm = v;
    }
    if env("BACK") == Some(1.0) {
        options.segment.backward_pass = true;
    }
    if let Some(v) = env("BIN") {
        options.sample_bin_mm = v;
    }
    if let Some(v) = env("ISO") {
        options.iso = echosurf::pipeline::IsoLevels::Levels(vec![v]);
    }
    let t = std::time::Instant::now();
    let out = pipeline::extract(
        &sim.sequence,
        // TRUECAL=1: the calibration without the simulated calibration error.
        Some(if env("TRUECAL") == Some(1.0) {
            &sim.calibration_true
        } else {
            &sim.calibration_written
        }),
        &options,
        &NoProgress,
    )?;
    let mesh = &out.surfaces[0].mesh;
    if let Some(p) = std::env::args().nth(2) {
        echosurf::io::write_mesh(std::path::Path::new(&p), mesh)?;
    }
    println!(
        "samples {} kept px {} binned {}",
        out.report.counts.samples, out.report.counts.kept_pixels, out.report.counts.binned_samples
    );
    println!(
        "extract {:.2}s, {} triangles",
        t.elapsed().as_secs_f64(),
        mesh.triangles.len()
    );
    let (w, h) = (sim.sequence.width as f64, sim.sequence.height as f64);
    let frames: Vec<_> = sim
        .true_image_to_world
        .iter()
        .map(|m| {
            let beam = m.transform_vector3(DVec3::Y).normalize();
            let normal = m
                .transform_vector3(DVec3::X)
                .cross(m.transform_vector3(DVec3::Y))
                .normalize();
            (m.inverse(), *m, beam, normal)
        })
        .collect();
    // Best |cos| and its sign over frames that sweep the centroid.
    let classify = |c: DVec3, n: DVec3| -> Option<f64> {
        let mut best: Option<f64> = None;
        for (inv, m, beam, pn) in &frames {
            let p = inv.transform_point3(c);
            if !(p.x >= 0.0 && p.x <= w - 1.0 && p.y >= 0.0 && p.y <= h - 1.0) {
                continue;
            }
            let foot = m.transform_point3(DVec3::new(p.x, p.y, 0.0));
            if (c - foot).dot(*pn).abs() > 1.5 {
                continue;
            }
            let d = n.dot(*beam);
            if best.is_none_or(|b| d.abs() > b.abs()) {
                best = Some(d);
            }
        }
        best
    };
    for (name, truth) in &sim.truth {
        for (lo, hi) in [(0.0, 20.0), (20.0, 30.0), (30.0, 40.0), (40.0, 60.0)] {
            for sign in [-1.0, 1.0] {
                let mask = triangle_mask(truth, |c, n| match classify(c, n) {
                    Some(d) => {
                        let a = d.abs().acos().to_degrees();
                        a >= lo && a < hi && d * sign > 0.0
                    }
                    None => false,
                });
                if mask.iter().filter(|&&m| m).count() < 20 {
                    continue;
                }
                let c = compare_meshes(
                    mesh,
                    truth,
                    &CompareOptions {
                        truth_mask: Some(mask),
                        ..CompareOptions::default()
                    },
                )?;
                println!(
                    "{name} {lo:>2}-{hi:>2} deg n.beam {}: area {:>5.0} mm2, complete {:.3}, reverse p50 {:.2} p95 {:.2}",
                    if sign < 0.0 { "<0" } else { ">0" },
                    c.truth_compared_area_mm2,
                    c.completeness_1mm,
                    c.reverse.median_mm,
                    c.reverse.p95_mm
                );
            }
        }
    }
    let whole = compare_meshes(
        mesh,
        &sim.truth
            .iter()
            .fold(echosurf::mesh::Mesh::default(), |mut a, (_, m)| {
                let b = a.vertices.len() as u32;
                a.vertices.extend(&m.vertices);
                a.triangles
                    .extend(m.triangles.iter().map(|t| t.map(|i| i + b)));
                a
            }),
        &CompareOptions::default(),
    )?;
    println!(
        "accuracy mean {:.3} p95 {:.3} components {}",
        whole.accuracy.mean_mm, whole.accuracy.p95_mm, whole.mesh_topology.components
    );
    Ok(())
}
