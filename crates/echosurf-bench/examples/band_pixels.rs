//! Writes issue-27 band pixels (see `echosurf_bench::band_pixels`) as a PLY point cloud with a float
//! `intensity` property, for `echosurf fit`:
//! `cargo run --release --example band_pixels -- OUT.ply COUNT [SEQUENCE.mha CONFIG.xml]`
//! (without a sequence: our own duck simulator, two sweeps of 60 frames, true poses). `SEED` (default 1).

use std::path::Path;

use echosurf::io::{self, PointCloud};
use echosurf_bench::{random_subset, simulated_band_pixels, sweep_band_pixels};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (Some(out), Some(count)) = (args.first(), args.get(1)) else {
        return Err("usage: band_pixels OUT.ply COUNT [SEQUENCE CONFIG]".into());
    };
    let count: usize = count.parse()?;
    let seed: u64 = std::env::var("SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1);
    let (points, values) = match (args.get(2), args.get(3)) {
        (Some(seq), Some(config)) => {
            let (points, values) = sweep_band_pixels(Path::new(seq), Path::new(config))?;
            random_subset(&points, &values, count, seed)
        }
        _ => simulated_band_pixels(count, 60, seed)?,
    };
    let cloud = PointCloud {
        positions: points,
        scalars: vec![(
            "intensity".into(),
            values.iter().map(|&v| v as f32).collect(),
        )],
    };
    io::write_point_cloud(Path::new(out), &cloud)?;
    eprintln!("{} band pixels -> {out}", cloud.positions.len());
    Ok(())
}
