//! Near-duplicate merging: frames of a freehand sweep cross, so samples can (almost) coincide; two such
//! samples with different values make the interpolation system (nearly) singular.

use std::collections::HashMap;

use glam::DVec3;

/// Merges samples closer than `tolerance_mm` to an earlier kept sample into it (position of the first,
/// mean of the values). Input order decides, so the result is deterministic. `tolerance_mm = 0` merges
/// exact duplicates only.
pub fn merge_near_duplicates(
    points: &[DVec3],
    values: &[f64],
    tolerance_mm: f64,
) -> (Vec<DVec3>, Vec<f64>) {
    let cell = if tolerance_mm > 0.0 {
        tolerance_mm
    } else {
        1.0
    };
    let key = |p: DVec3| {
        let q = (p / cell).floor();
        (q.x as i64, q.y as i64, q.z as i64)
    };
    let mut grid: HashMap<(i64, i64, i64), Vec<u32>> = HashMap::new();
    let mut kept: Vec<DVec3> = Vec::new();
    let mut sums: Vec<f64> = Vec::new();
    let mut counts: Vec<u32> = Vec::new();
    let tol_sq = tolerance_mm * tolerance_mm;
    for (p, &v) in points.iter().zip(values) {
        let (kx, ky, kz) = key(*p);
        let mut found = None;
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    if let Some(list) = grid.get(&(kx + dx, ky + dy, kz + dz)) {
                        for &k in list {
                            let d = (kept[k as usize] - *p).length_squared();
                            if d <= tol_sq && found.is_none_or(|(bk, bd)| (d, k) < (bd, bk)) {
                                found = Some((k, d));
                            }
                        }
                    }
                }
            }
        }
        match found {
            Some((k, _)) => {
                sums[k as usize] += v;
                counts[k as usize] += 1;
            }
            None => {
                grid.entry((kx, ky, kz))
                    .or_default()
                    .push(kept.len() as u32);
                kept.push(*p);
                sums.push(v);
                counts.push(1);
            }
        }
    }
    let means = sums
        .iter()
        .zip(&counts)
        .map(|(s, &c)| s / c as f64)
        .collect();
    (kept, means)
}
