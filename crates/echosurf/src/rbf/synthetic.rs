//! Ultrasound-like test samples: ~100 tilted, irregularly spaced planar frames through an ellipsoid,
//! with an echo-like intensity of the distance to its surface and multiplicative speckle. Not a physical
//! simulator (that is the `echosurf-sim` crate); the fixture of the fit's tests and benchmarks.

use glam::{DQuat, DVec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

/// Semi-axes (mm) of the benchmark ellipsoid, centred at the origin.
pub const BENCH_ELLIPSOID_MM: DVec3 = DVec3::new(30.0, 20.0, 15.0);

/// `n` samples (positions in mm, grey levels 0..255) on 100 frames; same `n` and `seed` give the same data.
pub fn ultrasound_like_samples(n: usize, seed: u64) -> (Vec<DVec3>, Vec<f64>) {
    let frames = 100.min(n.max(1));
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let speckle = Normal::new(1.0, 0.25).expect("valid normal");
    let mut points = Vec::with_capacity(n);
    let mut values = Vec::with_capacity(n);
    // Irregular sweep: frame positions along z with jittered steps, small random tilts.
    let mut z = -22.0;
    let mean_step = 44.0 / frames as f64;
    for f in 0..frames {
        let count = n / frames + usize::from(f < n % frames);
        let tilt = DQuat::from_rotation_x(rng.random_range(-0.05..0.05))
            * DQuat::from_rotation_y(rng.random_range(-0.05..0.05));
        let centre = DVec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), z);
        z += mean_step * rng.random_range(0.4..1.6);
        // A rectangular image of 80 x 60 mm sampled on a regular pixel grid with ~count pixels.
        let cols = ((count as f64 * 4.0 / 3.0).sqrt().ceil() as usize).max(1);
        let rows = count.div_ceil(cols).max(1);
        for k in 0..count {
            let (r, c) = (k / cols, k % cols);
            let u = -40.0 + 80.0 * (c as f64 + 0.5) / cols as f64;
            let v = -30.0 + 60.0 * (r as f64 + 0.5) / rows as f64;
            let p = centre + tilt * DVec3::new(u, v, 0.0);
            let q = p / BENCH_ELLIPSOID_MM;
            let distance_mm = (q.length() - 1.0) * BENCH_ELLIPSOID_MM.min_element();
            let echo = 15.0
                + 115.0 * (-(distance_mm / 1.5).powi(2)).exp()
                + if distance_mm < 0.0 { 25.0 } else { 0.0 };
            let value = (echo * speckle.sample(&mut rng)).clamp(0.0, 255.0);
            points.push(p);
            values.push(value);
        }
    }
    (points, values)
}
