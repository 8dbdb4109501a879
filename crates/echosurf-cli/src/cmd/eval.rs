//! `echosurf eval`: evaluate a fitted model (value and gradient) at the points of a PLY point cloud.

use std::path::PathBuf;

use echosurf::io::PointCloud;
use echosurf::rbf::RbfModel;

use super::outputs::{Holds, check_outputs, output};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Fitted model (.esrbf) from `echosurf fit`.
    pub model: PathBuf,
    /// Point cloud PLY (float x y z; other properties are kept).
    pub points: PathBuf,
    /// Output PLY: the input points with float `value`, `gx`, `gy`, `gz` added.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let inputs = [args.model.clone(), args.points.clone()];
    check_outputs(&inputs, &[output("--out", &args.out, Holds::PointCloud)])?;
    let model = RbfModel::load(&args.model)?;
    let cloud = echosurf::io::read_point_cloud(&args.points)?;
    let (values, gradients) = model.values_and_gradients(&cloud.positions);
    // Written as f32: a value or gradient past single precision (or NaN) would be written as inf/NaN.
    let representable = |v: f64| v.is_finite() && v.abs() <= f32::MAX as f64;
    let bad = values
        .iter()
        .zip(&gradients)
        .filter(|(v, g)| !(representable(**v) && g.to_array().into_iter().all(representable)))
        .count();
    if bad > 0 {
        anyhow::bail!(
            "{}: the model's value or gradient is infinite, NaN or beyond single precision at {bad} \
             of the {} points of {}: its coefficients are out of range",
            args.model.display(),
            values.len(),
            args.points.display()
        );
    }
    let mut scalars: Vec<(String, Vec<f32>)> = cloud
        .scalars
        .into_iter()
        .filter(|(name, _)| !matches!(name.as_str(), "value" | "gx" | "gy" | "gz"))
        .collect();
    scalars.push(("value".into(), values.iter().map(|&v| v as f32).collect()));
    scalars.push(("gx".into(), gradients.iter().map(|g| g.x as f32).collect()));
    scalars.push(("gy".into(), gradients.iter().map(|g| g.y as f32).collect()));
    scalars.push(("gz".into(), gradients.iter().map(|g| g.z as f32).collect()));
    let out = PointCloud {
        positions: cloud.positions,
        scalars,
    };
    echosurf::io::write_point_cloud(&args.out, &out)?;
    outln!(
        "evaluated {} points ({} centres) -> {}",
        values.len(),
        model.centres().len(),
        args.out.display()
    );
    Ok(())
}
