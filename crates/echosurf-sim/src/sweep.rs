//! Freehand sweeps: where a sonographer would put a linear probe to cover an object in a water bath, and
//! how a hand actually moves it.
//!
//! The plan: parallel passes over the top (beam straight down) until the image width covers the object
//! across, then one pass from each side with the beam tilted toward the object (flanks are steep from
//! above and would return no echo). Every pass runs along the object's x axis, back and forth.
//! The motion: gamma-distributed steps between frames (a hand does not move at constant speed), a slow
//! random tilt / roll / yaw and lateral drift, the probe kept a few mm above the nearest surface under it
//! (smoothed, never touching), and hand tremor on top.

use glam::{DMat3, DMat4, DVec3};
use rand::Rng;
use rand_distr::{Distribution, Gamma, StandardNormal};

use super::phantom::Phantom;

/// How the hand moves the probe (and, optionally, the object moves).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct HandMotion {
    /// Amplitude of the slow random tilt, roll and yaw (degrees).
    pub wobble_deg: f64,
    /// Amplitude of the slow lateral drift across the sweep (mm).
    pub drift_mm: f64,
    /// Shape of the gamma distribution of the steps between frames (larger = more regular).
    pub step_shape: f64,
    /// Hand tremor amplitude (mm per axis) and rotation (degrees per axis), ~8-12 Hz.
    pub tremor_mm: f64,
    pub tremor_deg: f64,
    /// Gap kept between the probe face and the nearest surface under it (mm).
    pub standoff_mm: f64,
    /// Tilt of the side sweeps' beam from vertical (degrees).
    pub side_tilt_deg: f64,
    /// Frame rate (Hz) for timestamps and tremor.
    pub frame_rate_hz: f64,
    /// Amplitude of untracked object motion (mm): a slow sway plus a drift. 0 = the object stays put.
    pub object_motion_mm: f64,
}

impl Default for HandMotion {
    fn default() -> Self {
        HandMotion {
            wobble_deg: 3.0,
            drift_mm: 1.5,
            step_shape: 4.0,
            tremor_mm: 0.1,
            tremor_deg: 0.1,
            standoff_mm: 4.0,
            side_tilt_deg: 40.0,
            frame_rate_hz: 20.0,
            object_motion_mm: 0.0,
        }
    }
}

impl HandMotion {
    pub fn validate(&self) -> Result<(), String> {
        for (name, v, max) in [
            ("wobble_deg", self.wobble_deg, 30.0),
            ("drift_mm", self.drift_mm, 100.0),
            ("tremor_mm", self.tremor_mm, 10.0),
            ("tremor_deg", self.tremor_deg, 10.0),
            ("standoff_mm", self.standoff_mm, 100.0),
            ("side_tilt_deg", self.side_tilt_deg, 80.0),
            ("object_motion_mm", self.object_motion_mm, 100.0),
        ] {
            if !(v.is_finite() && (0.0..=max).contains(&v)) {
                return Err(format!("{name} must be in [0, {max}] (got {v})"));
            }
        }
        if !(self.step_shape.is_finite() && self.step_shape > 0.0) {
            return Err(format!(
                "step_shape must be positive (got {})",
                self.step_shape
            ));
        }
        if !(self.frame_rate_hz.is_finite() && self.frame_rate_hz > 0.0) {
            return Err(format!(
                "frame_rate_hz must be positive (got {})",
                self.frame_rate_hz
            ));
        }
        Ok(())
    }
}

/// One planned pass.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct SweepSpec {
    /// Beam tilt from straight down, toward -y for positive values (probe on the +y side).
    pub tilt_deg: f64,
    /// Offset of the pass across the object (world y, mm).
    pub lateral_mm: f64,
    /// Runs toward -x.
    pub reverse: bool,
}

/// Passes covering an object with bounds `(lo, hi)` with an image `image_width_mm` wide: top passes
/// first, then the two sides. `count` truncates or extends (repeating the plan in the opposite direction).
pub fn plan_sweeps(
    bounds: (DVec3, DVec3),
    image_width_mm: f64,
    side_tilt_deg: f64,
    count: Option<usize>,
) -> Vec<SweepSpec> {
    let (lo, hi) = bounds;
    let across = hi.y - lo.y;
    // Top passes side by side until the images span the object (the side sweeps see the flanks).
    let passes = ((across / (0.95 * image_width_mm)).ceil() as usize).max(1);
    let centre_y = 0.5 * (lo.y + hi.y);
    let mut plan = Vec::new();
    for k in 0..passes {
        let offset = (k as f64 - 0.5 * (passes - 1) as f64) * (across / passes as f64);
        plan.push(SweepSpec {
            tilt_deg: 0.0,
            lateral_mm: centre_y + offset,
            reverse: k % 2 == 1,
        });
    }
    for side in [1.0, -1.0] {
        let reverse = plan.len() % 2 == 1;
        plan.push(SweepSpec {
            tilt_deg: side * side_tilt_deg,
            lateral_mm: centre_y,
            reverse,
        });
    }
    match count {
        None => plan,
        Some(n) => (0..n)
            .map(|i| {
                let mut s = plan[i % plan.len()];
                if (i / plan.len()) % 2 == 1 {
                    s.reverse = !s.reverse;
                }
                s
            })
            .collect(),
    }
}

/// A smooth random process on [0, 1]: three sinusoids of random frequency (0.3-1.5 cycles per sweep)
/// and phase, with peak amplitude at most `amplitude`.
#[derive(Debug, Clone)]
pub struct SlowWobble {
    terms: [(f64, f64, f64); 3],
}

impl SlowWobble {
    pub fn new<R: Rng>(rng: &mut R, amplitude: f64) -> Self {
        let mut terms = [(0.0, 0.0, 0.0); 3];
        let mut weight_sum = 0.0;
        for t in &mut terms {
            let weight = rng.random_range(0.5..1.0);
            weight_sum += weight;
            *t = (
                weight,
                rng.random_range(0.3..1.5),
                rng.random_range(0.0..std::f64::consts::TAU),
            );
        }
        for t in &mut terms {
            t.0 *= amplitude / weight_sum;
        }
        SlowWobble { terms }
    }

    pub fn at(&self, progress: f64) -> f64 {
        self.terms
            .iter()
            .map(|(a, f, phase)| a * (std::f64::consts::TAU * f * progress + phase).sin())
            .sum()
    }
}

/// The true pose of each frame of one sweep: the image axes in the world (columns: lateral, beam,
/// elevation) and the position of the face centre, plus the timestamp.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbePlacement {
    pub image_rotation: DMat3,
    pub face_centre: DVec3,
    pub time_s: f64,
}

/// Geometry of the probe's image needed to place it.
#[derive(Debug, Clone, Copy)]
pub struct ProbeGeometry {
    pub width_mm: f64,
    pub depth_mm: f64,
}

/// Plans one sweep's frames.
#[allow(clippy::too_many_arguments)]
pub fn sweep_placements<R: Rng>(
    rng: &mut R,
    phantom: &dyn Phantom,
    spec: &SweepSpec,
    frames: usize,
    probe: ProbeGeometry,
    motion: &HandMotion,
    start_time_s: f64,
) -> Vec<ProbePlacement> {
    let (lo, hi) = phantom.bounds();
    let centre = 0.5 * (lo + hi);
    let radius = 0.5 * (hi - lo).length();
    let margin = 5.0;
    let (x0, x1) = if spec.reverse {
        (hi.x + margin, lo.x - margin)
    } else {
        (lo.x - margin, hi.x + margin)
    };

    // Irregular spacing: gamma steps, rescaled so the sweep spans the object.
    let gamma = Gamma::new(motion.step_shape, 1.0).expect("validated shape");
    let mut positions = Vec::with_capacity(frames);
    let mut acc = 0.0;
    for i in 0..frames {
        if i > 0 {
            acc += gamma.sample(rng);
        }
        positions.push(acc);
    }
    let total = if acc > 0.0 { acc } else { 1.0 };
    let xs: Vec<f64> = positions
        .iter()
        .map(|s| x0 + (x1 - x0) * s / total)
        .collect();

    let tilt = SlowWobble::new(rng, motion.wobble_deg);
    let roll = SlowWobble::new(rng, motion.wobble_deg);
    let yaw = SlowWobble::new(rng, motion.wobble_deg);
    let drift = SlowWobble::new(rng, motion.drift_mm);
    let tremor_hz = rng.random_range(8.0..12.0);
    let tremor_phase: [f64; 6] =
        std::array::from_fn(|_| rng.random_range(0.0..std::f64::consts::TAU));

    // Nominal image axes: lateral (array), beam, elevation.
    let t = spec.tilt_deg.to_radians();
    let beam0 = DVec3::new(0.0, -t.sin(), -t.cos());
    let lateral0 = DVec3::new(0.0, t.cos(), -t.sin());
    let nominal = DMat3::from_cols(lateral0, beam0, lateral0.cross(beam0));

    let mut rotations = Vec::with_capacity(frames);
    let mut anchors = Vec::with_capacity(frames);
    let mut target = Vec::with_capacity(frames);
    let mut clear = Vec::with_capacity(frames);
    let back = radius + 20.0;
    for (i, &x) in xs.iter().enumerate() {
        let progress = if frames > 1 {
            i as f64 / (frames - 1) as f64
        } else {
            0.5
        };
        // Tilt about the array axis, roll about the elevation axis, yaw about the beam (image axes).
        let wobble = DMat3::from_rotation_x(tilt.at(progress).to_radians())
            * DMat3::from_rotation_z(roll.at(progress).to_radians())
            * DMat3::from_rotation_y(yaw.at(progress).to_radians());
        let rotation = nominal * wobble;
        let anchor = DVec3::new(x, spec.lateral_mm, centre.z) + lateral0 * drift.at(progress);
        let (beam, lateral) = (rotation.y_axis, rotation.x_axis);
        // Nearest surface under the face: march 9 beams from far back.
        let start = anchor - beam * back;
        let mut nearest: Option<f64> = None;
        for k in 0..9 {
            let offset = (k as f64 / 8.0 - 0.5) * probe.width_mm;
            let origin = start + lateral * offset;
            if let Some(hit) = march(phantom, origin, beam, 2.0 * back + probe.depth_mm) {
                nearest = Some(nearest.map_or(hit, |n: f64| n.min(hit)));
            }
        }
        // Distance back from the anchor of a face `standoff` in front of that surface.
        target.push(nearest.map(|hit| back - hit + motion.standoff_mm));
        // Minimum distance back so that the whole face stays 1 mm off the object.
        let mut needed = f64::NEG_INFINITY;
        for k in 0..=32 {
            let offset = (k as f64 / 32.0 - 0.5) * probe.width_mm;
            let along_face = anchor + lateral * offset;
            if let Some(hit) = march(phantom, along_face - beam * back, beam, 2.0 * back) {
                needed = needed.max(back - hit + 1.0);
            }
        }
        clear.push(needed);
        rotations.push(rotation);
        anchors.push(anchor);
    }
    // Frames with nothing under them keep the nearest frame's distance (the hand does not dive).
    let fallback = target.iter().flatten().copied().fold(f64::NAN, f64::max);
    let fallback = if fallback.is_nan() { radius } else { fallback };
    let mut filled: Vec<f64> = Vec::with_capacity(frames);
    for i in 0..frames {
        let value = target[i].or_else(|| {
            (1..frames).find_map(|d| {
                let before = i.checked_sub(d).and_then(|j| target[j]);
                let after = target.get(i + d).copied().flatten();
                before.or(after)
            })
        });
        filled.push(value.unwrap_or(fallback));
    }
    // The hand follows the surface slowly: moving average over +-6 frames, never closer than allowed.
    let window = 6usize;
    let mut placements = Vec::with_capacity(frames);
    let mut gauss = || -> f64 { StandardNormal.sample(rng) };
    for i in 0..frames {
        let a = i.saturating_sub(window);
        let b = (i + window + 1).min(frames);
        let smooth = filled[a..b].iter().sum::<f64>() / (b - a) as f64;
        let distance = smooth.max(clear[i]);
        let time_s = start_time_s + i as f64 / motion.frame_rate_hz;
        let phase = std::f64::consts::TAU * tremor_hz * time_s;
        // Tremor: a sinusoid per axis (aliased by the frame rate, as on a real scanner) plus 30 % jitter.
        let shake = |k: usize, g: f64| (phase + tremor_phase[k]).sin() + 0.3 * g;
        let tremor_t =
            DVec3::new(shake(0, gauss()), shake(1, gauss()), shake(2, gauss())) * motion.tremor_mm;
        let tremor_r = DVec3::new(shake(3, gauss()), shake(4, gauss()), shake(5, gauss()))
            * motion.tremor_deg.to_radians();
        let rotation = DMat3::from_euler(glam::EulerRot::XYZ, tremor_r.x, tremor_r.y, tremor_r.z)
            * rotations[i];
        placements.push(ProbePlacement {
            image_rotation: rotation,
            face_centre: anchors[i] - rotations[i].y_axis * distance + tremor_t,
            time_s,
        });
    }
    placements
}

/// Sphere-traces from `origin` along unit `dir`; distance to the first surface within `max_mm`.
fn march(phantom: &dyn Phantom, origin: DVec3, dir: DVec3, max_mm: f64) -> Option<f64> {
    let mut t = 0.0;
    for _ in 0..512 {
        let d = phantom.distance(origin + dir * t);
        if d < 0.02 {
            return Some(t);
        }
        // Blends and the ellipsoid estimate may overestimate slightly: step 90 %.
        t += (0.9 * d).max(0.01);
        if t > max_mm {
            return None;
        }
    }
    None
}

/// Untracked object motion: a slow sway (0.2-0.3 Hz) plus a linear drift, zero at t = 0.
#[derive(Debug, Clone, Copy)]
pub struct ObjectMotion {
    amplitude_mm: f64,
    sway_dir: DVec3,
    sway_hz: f64,
    drift_mm_per_s: DVec3,
}

impl ObjectMotion {
    pub fn new<R: Rng>(rng: &mut R, amplitude_mm: f64, duration_s: f64) -> Self {
        let a: f64 = rng.random_range(0.0..std::f64::consts::TAU);
        let b: f64 = rng.random_range(0.0..std::f64::consts::TAU);
        ObjectMotion {
            amplitude_mm,
            sway_dir: DVec3::new(0.3 * a.cos(), 0.3 * a.sin(), 1.0).normalize(),
            sway_hz: rng.random_range(0.2..0.3),
            // Drifts by `amplitude` over the whole recording.
            drift_mm_per_s: DVec3::new(b.cos(), b.sin(), 0.0) * amplitude_mm / duration_s.max(1e-9),
        }
    }

    /// Object -> world at time `t` (the truth is the object at t = 0).
    pub fn object_to_world(&self, t: f64) -> DMat4 {
        let sway = (std::f64::consts::TAU * self.sway_hz * t).sin() * self.amplitude_mm;
        DMat4::from_translation(self.sway_dir * sway + self.drift_mm_per_s * t)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::phantom::{PhantomKind, build_phantom};
    use rand::SeedableRng;

    #[test]
    fn duck_plan_is_one_top_pass_and_two_sides() {
        let duck = build_phantom(&PhantomKind::Duck).unwrap();
        let plan = plan_sweeps(duck.bounds(), 51.2, 40.0, None);
        assert_eq!(plan.len(), 3, "{plan:?}");
        assert_eq!(plan[0].tilt_deg, 0.0);
        assert!(plan[1].tilt_deg > 0.0 && plan[2].tilt_deg < 0.0);
        let hand = build_phantom(&PhantomKind::Hand).unwrap();
        assert!(plan_sweeps(hand.bounds(), 51.2, 40.0, None).len() >= 5);
        assert_eq!(plan_sweeps(duck.bounds(), 51.2, 40.0, Some(1)).len(), 1);
    }

    #[test]
    fn probe_stays_outside_and_near_the_object() {
        let duck = build_phantom(&PhantomKind::Duck).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let probe = ProbeGeometry {
            width_mm: 51.2,
            depth_mm: 40.0,
        };
        for spec in plan_sweeps(duck.bounds(), probe.width_mm, 40.0, None) {
            let placements = sweep_placements(
                &mut rng,
                duck.as_ref(),
                &spec,
                60,
                probe,
                &HandMotion::default(),
                0.0,
            );
            let mut steps = Vec::new();
            for pair in placements.windows(2) {
                steps.push((pair[1].face_centre - pair[0].face_centre).length());
            }
            for p in &placements {
                // The face (centre line) is outside the object.
                for k in 0..=8 {
                    let q = p.face_centre
                        + p.image_rotation.x_axis * ((k as f64 / 8.0 - 0.5) * probe.width_mm);
                    assert!(duck.distance(q) > 0.5, "face inside the duck at {q}");
                }
            }
            // Irregular spacing: the steps vary (gamma shape 4 has a coefficient of variation of 0.5).
            let mean = steps.iter().sum::<f64>() / steps.len() as f64;
            let sd =
                (steps.iter().map(|s| (s - mean).powi(2)).sum::<f64>() / steps.len() as f64).sqrt();
            assert!(sd / mean > 0.2, "steps too regular: {mean} +- {sd}");
        }
    }
}
