//! The fitted model evaluated from its definition, apart from the model's own evaluator: the independent
//! reference that the accuracy-contract tests and the band-pixel benchmark check a fit against.

use glam::DVec3;

/// `s(x)` from the definition of the fitted model, written apart from the model's evaluator (no BVH, no
/// treecode, a sum over every centre): for a global spline the trend plus the sum over all centres; for
/// partition of unity the Wendland-weighted blend over *all* patches of their local sums.
pub fn definition_value(model: &super::RbfModel, x: DVec3) -> f64 {
    match model.partition_of_unity() {
        None => {
            let (c0, c, origin) = model.trend();
            c0 + c.dot(x - origin)
                + model
                    .centres()
                    .iter()
                    .zip(model.coefficients())
                    .map(|(p, l)| l * (x - *p).length())
                    .sum::<f64>()
        }
        Some(pu) => {
            let xc = x.clamp(pu.root_lo, pu.root_hi);
            let (mut sum_w, mut sum_ws) = (0.0, 0.0);
            for j in 0..pu.patches() {
                let t = (xc - pu.support_centre[j]).abs() / pu.support_half[j];
                if t.max_element() >= 1.0 {
                    continue;
                }
                let phi = |t: f64| (1.0 - t).powi(4) * (4.0 * t + 1.0);
                let w = phi(t.x) * phi(t.y) * phi(t.z);
                let rel = x - pu.support_centre[j];
                let mut s = pu.constant[j] + pu.linear[j].dot(rel);
                for k in pu.offsets[j]..pu.offsets[j + 1] {
                    let d = rel - DVec3::new(pu.xs[k], pu.ys[k], pu.zs[k]);
                    s += pu.coefficients[k] * d.length();
                }
                sum_w += w;
                sum_ws += w * s;
            }
            sum_ws / sum_w
        }
    }
}

/// Largest |f_i - s(x_i)| over the merged samples, by [`definition_value`] (w = 0): the contract check
/// of the tests and the band-pixel benchmark, independent of the model's own evaluator.
pub fn definition_max_misfit(
    model: &super::RbfModel,
    pts: &[DVec3],
    vals: &[f64],
    merge_mm: f64,
) -> f64 {
    let (pts, vals) = super::merge_near_duplicates(pts, vals, merge_mm);
    use rayon::prelude::*;
    pts.par_iter()
        .zip(&vals)
        .map(|(p, f)| (f - definition_value(model, *p)).abs())
        .reduce(|| 0.0, f64::max)
}
