//! `echosurf sample`.

use std::path::PathBuf;

use echosurf::io;
use echosurf::samples::{collect_samples, estimate_levels, random_decimate};

use super::segment::SegmentArgs;

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub segment: SegmentArgs,
    /// Keep at most this many samples, chosen uniformly at random (the paper: ~10k large features,
    /// ~100k detail).
    #[arg(long)]
    pub max_samples: Option<usize>,
    /// Seed of the random thinning.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output point cloud (binary PLY, x y z in mm + float intensity).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let (sequence, poses, masks) = args.segment.run()?;
    let all = collect_samples(&sequence, &poses, &masks);
    let set = match args.max_samples {
        Some(n) => random_decimate(&all, n, args.seed),
        None => all.clone(),
    };
    io::write_point_cloud(&args.out, &set.to_point_cloud())?;
    print!(
        "wrote {} of {} samples ({} world frame)",
        set.len(),
        all.len(),
        poses.world_frame
    );
    match estimate_levels(&set.intensities) {
        Some(l) => println!(
            "; levels: background {:.1}, boundary {:.1}, suggested iso {:.1}",
            l.background, l.boundary, l.iso
        ),
        None => println!(),
    }
    Ok(())
}
