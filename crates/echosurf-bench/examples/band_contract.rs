//! Issue 27's accuracy contract and PU-vs-global comparison on band pixels (a PLY from the
//! `band_pixels` example):
//! `cargo run --release --example band_contract -- POINTS.ply LEVEL [SOLVERS]`
//! fits every solver (default `pu,auto,direct,fast`) at w = 0, accuracy 1 grey, checks the largest
//! |f_i - s(x_i)| at every merged sample with `rbf::definition_max_misfit` (a sum over every centre, not
//! the model's evaluator) or prints the refusal; then surfaces the PU model at LEVEL, takes 20,000 points
//! within 2 mm of that surface and prints how far the PU field is from the global (`fast`) spline there.

use std::path::Path;
use std::time::Instant;

use echosurf::io;
use echosurf::progress::NoProgress;
use echosurf::rbf::{FitOptions, RbfModel, SolverChoice, definition_max_misfit, fit};
use echosurf::surface::{SurfaceDomain, SurfaceOptions, extract_surfaces_with_stats};
use glam::DVec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (Some(path), Some(level)) = (args.first(), args.get(1)) else {
        return Err("usage: band_contract POINTS.ply LEVEL [pu,auto,direct,fast]".into());
    };
    let level: f64 = level.parse()?;
    let solvers = args.get(2).map_or("pu,auto,direct,fast", String::as_str);
    let cloud = io::read_point_cloud(Path::new(path))?;
    let values: Vec<f64> = cloud
        .scalars
        .iter()
        .find(|(name, _)| name == "intensity")
        .ok_or("no intensity property")?
        .1
        .iter()
        .map(|&v| f64::from(v))
        .collect();
    let points = cloud.positions;
    println!("{} band pixels from {path}", points.len());
    println!(
        "| solver | outcome | fit s | report max residual | independent max residual | iterations |"
    );
    println!("|---|---|---|---|---|---|");
    let mut models: Vec<(SolverChoice, RbfModel)> = Vec::new();
    for name in solvers.split(',') {
        let solver = match name {
            "pu" => SolverChoice::PartitionOfUnity,
            "auto" => SolverChoice::Auto,
            "direct" => SolverChoice::Direct,
            "fast" => SolverChoice::Fast,
            other => return Err(format!("unknown solver {other}").into()),
        };
        let options = FitOptions {
            smoothing: 0.0,
            accuracy: 1.0,
            solver,
            ..FitOptions::default()
        };
        let start = Instant::now();
        match fit(&points, &values, &options, &NoProgress) {
            Ok((model, report)) => {
                let seconds = start.elapsed().as_secs_f64();
                let check = Instant::now();
                let independent =
                    definition_max_misfit(&model, &points, &values, options.merge_distance_mm);
                eprintln!(
                    "{name}: independent check {:.1} s",
                    check.elapsed().as_secs_f64()
                );
                println!(
                    "| {name} | {} | {seconds:.2} | {:.3e} | {independent:.3e} | {} |",
                    if independent <= 1.0 { "met" } else { "MISSED" },
                    report.max_residual,
                    report.iterations
                );
                models.push((report.solver, model));
            }
            Err(e) => println!(
                "| {name} | refused: {e} | {:.2} | | | |",
                start.elapsed().as_secs_f64()
            ),
        }
    }
    let pu = models
        .iter()
        .find(|(s, _)| *s == SolverChoice::PartitionOfUnity);
    let global = models.iter().find(|(s, _)| *s == SolverChoice::Fast);
    if let (Some((_, pu)), Some((_, global))) = (pu, global) {
        let lo = points
            .iter()
            .fold(DVec3::splat(f64::INFINITY), |a, p| a.min(*p));
        let hi = points
            .iter()
            .fold(DVec3::splat(f64::NEG_INFINITY), |a, p| a.max(*p));
        let domain = SurfaceDomain {
            bounds_min_mm: lo,
            bounds_max_mm: hi,
            seeds: points.clone(),
            trust_points: points.clone(),
        };
        let (meshes, _) =
            extract_surfaces_with_stats(pu, &[level], &domain, &SurfaceOptions::default())?;
        let vertices = &meshes[0].vertices;
        if vertices.is_empty() {
            return Err(format!("PU model has no surface at {level}").into());
        }
        let mut rng = ChaCha8Rng::seed_from_u64(27);
        let probes: Vec<DVec3> = (0..20_000)
            .map(|_| {
                let v = vertices[rng.random_range(0..vertices.len())];
                let d = loop {
                    let d = DVec3::new(
                        rng.random_range(-1.0..1.0),
                        rng.random_range(-1.0..1.0),
                        rng.random_range(-1.0..1.0),
                    );
                    if d.length_squared() <= 1.0 {
                        break d;
                    }
                };
                v + d * 2.0
            })
            .collect();
        let (a, b) = (pu.values(&probes), global.values(&probes));
        let diffs: Vec<f64> = a.iter().zip(&b).map(|(x, y)| (x - y).abs()).collect();
        let max = diffs.iter().copied().fold(0.0, f64::max);
        let rms = (diffs.iter().map(|d| d * d).sum::<f64>() / diffs.len() as f64).sqrt();
        println!(
            "PU vs global spline at {} points within 2 mm of the PU surface at iso {level} ({} \
             vertices): max |difference| {max:.3} grey, rms {rms:.3} grey",
            probes.len(),
            vertices.len()
        );
    }
    Ok(())
}
