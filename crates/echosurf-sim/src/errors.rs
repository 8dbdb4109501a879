//! The errors a real tracked system has: tracker noise on every pose and a calibration that differs from
//! the true Image->Probe transform.

use glam::{DMat4, DQuat, DVec3};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal, UnitSphere};

/// Magnitudes of the tracking errors.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrackingErrors {
    /// Standard deviation per axis of the tracked position (mm).
    pub tracker_noise_mm: f64,
    /// Standard deviation per axis of the tracked rotation (degrees).
    pub tracker_noise_deg: f64,
    /// Translation of the written calibration away from the true one (mm, exact magnitude).
    pub calibration_error_mm: f64,
    /// Rotation of the written calibration away from the true one (degrees, exact magnitude).
    pub calibration_error_deg: f64,
}

impl Default for TrackingErrors {
    fn default() -> Self {
        TrackingErrors {
            tracker_noise_mm: 0.1,
            tracker_noise_deg: 0.05,
            calibration_error_mm: 0.3,
            calibration_error_deg: 0.4,
        }
    }
}

impl TrackingErrors {
    /// A perfect system.
    pub fn none() -> Self {
        TrackingErrors {
            tracker_noise_mm: 0.0,
            tracker_noise_deg: 0.0,
            calibration_error_mm: 0.0,
            calibration_error_deg: 0.0,
        }
    }

    pub fn validate(&self) -> Result<(), String> {
        for (name, v, max) in [
            ("tracker noise (mm)", self.tracker_noise_mm, 50.0),
            ("tracker noise (deg)", self.tracker_noise_deg, 30.0),
            ("calibration error (mm)", self.calibration_error_mm, 50.0),
            ("calibration error (deg)", self.calibration_error_deg, 30.0),
        ] {
            if !(v.is_finite() && (0.0..=max).contains(&v)) {
                return Err(format!("{name} must be in [0, {max}] (got {v})"));
            }
        }
        Ok(())
    }

    /// The calibration error as a rigid transform applied in the probe frame (written = error * true):
    /// a rotation of exactly `calibration_error_deg` about a random axis and a translation of exactly
    /// `calibration_error_mm` in a random direction.
    pub fn calibration_error<R: Rng>(&self, rng: &mut R) -> DMat4 {
        let axis = DVec3::from_array(UnitSphere.sample(rng));
        let direction = DVec3::from_array(UnitSphere.sample(rng));
        DMat4::from_rotation_translation(
            DQuat::from_axis_angle(axis, self.calibration_error_deg.to_radians()),
            direction * self.calibration_error_mm,
        )
    }

    /// One pose's tracker noise as a rigid perturbation in the marker frame (written = true * noise).
    pub fn tracker_noise<R: Rng>(&self, rng: &mut R) -> DMat4 {
        let mut gauss = || -> f64 { StandardNormal.sample(rng) };
        let rotation_vector =
            DVec3::new(gauss(), gauss(), gauss()) * self.tracker_noise_deg.to_radians();
        let translation = DVec3::new(gauss(), gauss(), gauss()) * self.tracker_noise_mm;
        let angle = rotation_vector.length();
        let rotation = if angle > 0.0 {
            DQuat::from_axis_angle(rotation_vector / angle, angle)
        } else {
            DQuat::IDENTITY
        };
        DMat4::from_rotation_translation(rotation, translation)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn calibration_error_has_the_requested_magnitudes() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let e = TrackingErrors::default().calibration_error(&mut rng);
        let (_, rotation, translation) = e.to_scale_rotation_translation();
        assert!((translation.length() - 0.3).abs() < 1e-12);
        assert!((rotation.to_axis_angle().1.to_degrees() - 0.4).abs() < 1e-9);
        let none = TrackingErrors::none().calibration_error(&mut rng);
        assert!(none.abs_diff_eq(DMat4::IDENTITY, 1e-15));
    }

    #[test]
    fn tracker_noise_has_the_requested_spread() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let errors = TrackingErrors::default();
        let n = 4000;
        let mut sum_sq = 0.0;
        for _ in 0..n {
            sum_sq += errors
                .tracker_noise(&mut rng)
                .w_axis
                .truncate()
                .length_squared();
        }
        // E|t|^2 = 3 sigma^2; 4000 draws give the RMS to ~1.2 % (1 sigma), so allow 5 %.
        let rms_per_axis = (sum_sq / (3.0 * n as f64)).sqrt();
        assert!((rms_per_axis - 0.1).abs() < 0.005, "{rms_per_axis}");
    }
}
