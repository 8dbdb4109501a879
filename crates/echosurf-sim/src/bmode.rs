//! B-mode image formation, physically motivated and cheap.
//!
//! Per frame, on the pixel grid (plus a lateral and a bottom margin so the point-spread function sees
//! echoes beyond the image edge):
//! 1. Complex baseband scatterer field. Diffuse scatterers are tied to the object (a hash of the position
//!    on a 0.1 mm grid gives each cell an independent complex, nearly Gaussian amplitude), so revisiting a
//!    place shows the same speckle. The carrier of the modulated pulse is removed by I/Q demodulation, which
//!    leaves a real Gaussian envelope PSF acting on complex scatterers: exactly what envelope detection of
//!    RF lines convolved with a Gaussian-modulated pulse gives, without sampling the carrier.
//! 2. Specular boundary echoes at every zero crossing of the phantom's distance, with amplitude
//!    `R cos^n(theta)` (theta between the surface normal and the beam), times `1 + roughness * z` for the
//!    rough-surface speckle, plus a weak diffuse part `D cos(theta) z'`. The echo is placed analytically
//!    at the sub-pixel depth of the interface (the axial PSF evaluated at the along-beam distance), so it
//!    only needs the lateral convolution.
//! 3. Attenuation down each column (round trip, dB/cm/MHz of the material) and a transmission loss at
//!    each interface crossed: strong reflectors shadow what lies below them.
//! 4. Separable convolution (axial for the diffuse field, lateral for both), electronic noise (complex
//!    Gaussian, per-frame RNG), envelope, log compression to 8 bit.

use glam::{DMat4, DVec3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

use super::phantom::Phantom;

/// Echo-producing properties of a medium.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Material {
    /// RMS diffuse echo amplitude after the PSF, dB re the log compressor's reference (0 dB = white).
    pub scatter_db: f64,
    /// One-way attenuation in dB per cm per MHz.
    pub attenuation_db_per_cm_mhz: f64,
}

/// Acoustic parameters of the simulated scan.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Acoustics {
    /// Centre frequency (MHz): scales attenuation.
    pub frequency_mhz: f64,
    /// Full width at half maximum of the PSF envelope along the beam (mm).
    pub axial_fwhm_mm: f64,
    /// Full width at half maximum of the PSF across the beam, in the image plane (mm).
    pub lateral_fwhm_mm: f64,
    /// The medium around the object and in the duck's cavity: a water bath by default, soft tissue with
    /// [`Surround::Tissue`] (the name stays for the files already written).
    pub water: Material,
    /// The phantom's material (rubber for the duck, soft tissue for the hand).
    pub object: Material,
    /// Peak echo of a smooth interface at normal incidence (dB).
    pub reflection_db: f64,
    /// n in cos^n(theta): how fast specular echoes fall with the angle between normal and beam.
    pub specular_exponent: f64,
    /// Relative RMS of the rough-surface speckle multiplying the specular echo.
    pub roughness: f64,
    /// Share (0, 1] of the 0.1 mm scatterer cells that hold a diffuse scatterer: 1 gives fully developed
    /// (Rayleigh) speckle, small values sparse bright points; the RMS level stays the material's.
    #[serde(
        default = "full_scatterer_density",
        skip_serializing_if = "is_full_scatterer_density"
    )]
    pub scatterer_density: f64,
    /// Time-gain compensation: amplify each row by the round-trip attenuation of the surrounding medium
    /// down to its depth, as a scanner's TGC does, so tissue around the object keeps its brightness with
    /// depth (a water bath barely attenuates and needs none).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub depth_gain_compensation: bool,
    /// Diffuse (rough-surface) echo at normal incidence (dB); falls as cos(theta).
    pub diffuse_db: f64,
    /// Fraction of the round-trip amplitude lost at each interface crossed (shadowing).
    pub interface_loss: f64,
    /// RMS electronic noise (dB): the noise floor.
    pub noise_db: f64,
    /// Displayed dynamic range of the log compression (dB).
    pub dynamic_range_db: f64,
}

impl Default for Acoustics {
    /// Calibrated so that water shows ~15 and a normal-incidence boundary ~130 of 255 (the paper's levels).
    fn default() -> Self {
        Acoustics {
            frequency_mhz: 7.0,
            axial_fwhm_mm: 0.3,
            lateral_fwhm_mm: 0.8,
            water: Material {
                scatter_db: -55.5,
                attenuation_db_per_cm_mhz: 0.002,
            },
            object: Material {
                scatter_db: -50.0,
                attenuation_db_per_cm_mhz: 0.5,
            },
            reflection_db: -21.0,
            specular_exponent: 12.0,
            roughness: 1.0,
            scatterer_density: 1.0,
            depth_gain_compensation: false,
            diffuse_db: -48.0,
            interface_loss: 0.1,
            noise_db: -64.0,
            dynamic_range_db: 60.0,
        }
    }
}

fn full_scatterer_density() -> f64 {
    1.0
}

// serde's skip_serializing_if hands the field by reference.
#[allow(clippy::trivially_copy_pass_by_ref)]
fn is_full_scatterer_density(density: &f64) -> bool {
    *density == 1.0
}

impl Material {
    /// Soft tissue around the object (`--surround tissue`): speckle a little brighter than the phantom's
    /// material, so the background is texture, not dark water.
    pub const SURROUND_TISSUE: Material = Material {
        scatter_db: -47.0,
        attenuation_db_per_cm_mhz: 0.5,
    };
    /// Cortical bone: its interior scatters little and attenuates so strongly that nothing below its
    /// probe-side surface returns (2 mm of it cost over 50 dB round trip at 7 MHz).
    pub const BONE: Material = Material {
        scatter_db: -70.0,
        attenuation_db_per_cm_mhz: 20.0,
    };
}

/// What surrounds the phantom.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Surround {
    /// A water bath: dark, nearly echo-free.
    Water,
    /// Soft tissue: speckle everywhere around the object.
    Tissue,
}

impl Surround {
    pub fn parse(text: &str) -> Option<Surround> {
        match text.to_ascii_lowercase().as_str() {
            "water" => Some(Surround::Water),
            "tissue" => Some(Surround::Tissue),
            _ => None,
        }
    }
}

/// A named set of physics, the starting point the individual knobs then change.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PhysicsPreset {
    /// [`Acoustics::default`]: the water bath of the paper's phantoms.
    Default,
    /// The same object in soft tissue.
    Tissue,
    /// A bone surface in soft tissue: a strong echo and a full shadow below it.
    Bone,
}

impl PhysicsPreset {
    pub fn acoustics(self) -> Acoustics {
        match self {
            PhysicsPreset::Default => Acoustics::default(),
            PhysicsPreset::Tissue => Acoustics::default().with_surround(Surround::Tissue),
            PhysicsPreset::Bone => {
                let mut a = Acoustics::default().with_surround(Surround::Tissue);
                a.object = Material::BONE;
                // A bone surface reflects ~10 dB more than a rubber wall and passes little on.
                a.reflection_db = -11.0;
                a.interface_loss = 0.9;
                a
            }
        }
    }
}

impl Acoustics {
    /// The same scan with the object in water or in soft tissue (the duck's cavity takes the same
    /// medium); tissue turns the depth gain compensation on.
    pub fn with_surround(mut self, surround: Surround) -> Acoustics {
        (self.water, self.depth_gain_compensation) = match surround {
            Surround::Water => (Acoustics::default().water, false),
            Surround::Tissue => (Material::SURROUND_TISSUE, true),
        };
        self
    }

    /// Checks the parameters a user can set; returns a message naming the first bad one.
    pub fn validate(&self) -> Result<(), String> {
        let positive = [
            ("frequency_mhz", self.frequency_mhz),
            ("axial_fwhm_mm", self.axial_fwhm_mm),
            ("lateral_fwhm_mm", self.lateral_fwhm_mm),
            ("dynamic_range_db", self.dynamic_range_db),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{name} must be positive and finite (got {v})"));
            }
        }
        let finite = [
            ("water.scatter_db", self.water.scatter_db),
            ("object.scatter_db", self.object.scatter_db),
            ("reflection_db", self.reflection_db),
            ("diffuse_db", self.diffuse_db),
            ("noise_db", self.noise_db),
        ];
        for (name, v) in finite {
            if !v.is_finite() {
                return Err(format!("{name} must be finite (got {v})"));
            }
        }
        let non_negative = [
            ("specular_exponent", self.specular_exponent),
            ("roughness", self.roughness),
            (
                "water.attenuation_db_per_cm_mhz",
                self.water.attenuation_db_per_cm_mhz,
            ),
            (
                "object.attenuation_db_per_cm_mhz",
                self.object.attenuation_db_per_cm_mhz,
            ),
        ];
        for (name, v) in non_negative {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{name} must be >= 0 and finite (got {v})"));
            }
        }
        if !(self.scatterer_density > 0.0 && self.scatterer_density <= 1.0) {
            return Err(format!(
                "scatterer_density must be in (0, 1] (got {})",
                self.scatterer_density
            ));
        }
        if !(0.0..=1.0).contains(&self.interface_loss) {
            return Err(format!(
                "interface_loss must be in [0, 1] (got {})",
                self.interface_loss
            ));
        }
        if self.axial_fwhm_mm > 20.0 || self.lateral_fwhm_mm > 20.0 {
            return Err("PSF widths above 20 mm are not an ultrasound image".into());
        }
        Ok(())
    }
}

/// Grey-level statistics of one frame, split by what the truth says each pixel is.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LevelSums {
    /// Water at least 3 mm from any surface and not in a shadow.
    pub background_sum: f64,
    pub background_count: u64,
    /// The pixel row nearest a boundary facing the beam (cos theta > 0.9), not shadowed.
    pub boundary_sum: f64,
    pub boundary_count: u64,
}

impl LevelSums {
    pub fn add(&mut self, other: &LevelSums) {
        self.background_sum += other.background_sum;
        self.background_count += other.background_count;
        self.boundary_sum += other.boundary_sum;
        self.boundary_count += other.boundary_count;
    }
}

/// One simulated frame.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Log-compressed grey levels, row-major, `width * height`.
    pub grey: Vec<u8>,
    /// Envelope before log compression (same layout), when requested.
    pub envelope: Option<Vec<f32>>,
    pub levels: LevelSums,
}

/// Size of the image in pixels and the pixel pitch (mm) along columns (lateral) and rows (depth).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImageGrid {
    pub width: usize,
    pub height: usize,
}

const BLOCK: usize = 8;
const CLASS_NONE: u8 = 0;
const CLASS_BACKGROUND: u8 = 1;
const CLASS_BOUNDARY: u8 = 2;

fn db_to_amplitude(db: f64) -> f64 {
    10f64.powf(db / 20.0)
}

/// Gaussian kernel with the given FWHM in pixels, truncated at 3 sigma.
fn gaussian_kernel(fwhm_px: f64) -> Vec<f32> {
    let sigma = (fwhm_px / (2.0 * (2.0 * 2f64.ln()).sqrt())).max(1e-3);
    let half = (3.0 * sigma).ceil() as isize;
    (-half..=half)
        .map(|k| (-(k as f64).powi(2) / (2.0 * sigma * sigma)).exp() as f32)
        .collect()
}

/// SplitMix64 finaliser: a fast, well-mixed hash of one word.
#[inline]
fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Independent complex amplitude for the cell containing `p` (grid `inv_grain` cells per mm): each part is
/// a sum of four uniforms (Irwin-Hall), rescaled to unit variance. After the PSF sums ~15 cells the field
/// is Gaussian to well within the tolerance of the speckle statistics.
#[inline]
fn cell_gaussian(p: DVec3, inv_grain: f64, salt: u64) -> (f32, f32) {
    let h1 = mix64(cell_key(p, inv_grain, salt));
    let h2 = mix64(h1 ^ 0xd6e8_feb8_6659_fd93);
    // Sum of four 16-bit uniforms: mean 2, variance 4/12.
    let sum4 = |h: u64| {
        let s = (h & 0xffff) + ((h >> 16) & 0xffff) + ((h >> 32) & 0xffff) + (h >> 48);
        (s as f32 / 65535.0 - 2.0) * 1.732_050_8
    };
    (sum4(h1), sum4(h2))
}

/// Hash key of the scatterer cell containing `p`.
#[inline]
fn cell_key(p: DVec3, inv_grain: f64, salt: u64) -> u64 {
    let q = (p * inv_grain).floor();
    (q.x as i64 as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15)
        ^ (q.y as i64 as u64).wrapping_mul(0xc2b2_ae3d_27d4_eb4f)
        ^ (q.z as i64 as u64).wrapping_mul(0x1656_67b1_9e37_79f9)
        ^ salt
}

/// Whether the cell containing `p` holds a scatterer, with probability `density` (independent of the
/// cell's amplitude: another salt).
#[inline]
fn cell_occupied(p: DVec3, inv_grain: f64, salt: u64, density: f64) -> bool {
    let h = mix64(cell_key(p, inv_grain, salt));
    ((h >> 11) as f64) * (1.0 / (1u64 << 53) as f64) < density
}

/// Everything fixed across the frames of a simulation.
#[derive(Debug)]
pub struct FrameFormer<'a> {
    pub phantom: &'a dyn Phantom,
    pub acoustics: Acoustics,
    pub grid: ImageGrid,
    /// Salt of the object-fixed scatterer hash (from the seed).
    pub scatter_salt: u64,
}

impl FrameFormer<'_> {
    /// Forms the frame whose pixel (u, v) lies at `image_to_object * (u, v, 0, 1)` in the phantom's frame.
    /// `frame_seed` drives the electronic noise only.
    pub fn form(&self, image_to_object: &DMat4, frame_seed: u64, keep_envelope: bool) -> Frame {
        let ac = &self.acoustics;
        let (w, h) = (self.grid.width, self.grid.height);
        let ex = image_to_object.x_axis.truncate();
        let ey = image_to_object.y_axis.truncate();
        let origin = image_to_object.w_axis.truncate();
        let pitch_lateral = ex.length();
        let pitch_axial = ey.length();
        let beam = ey / pitch_axial;

        let kernel_axial = gaussian_kernel(ac.axial_fwhm_mm / pitch_axial);
        let kernel_lateral = gaussian_kernel(ac.lateral_fwhm_mm / pitch_lateral);
        let half_axial = kernel_axial.len() / 2;
        let half_lateral = kernel_lateral.len() / 2;
        let sum_lateral: f32 = kernel_lateral.iter().sum();
        let kernel_lateral: Vec<f32> = kernel_lateral.iter().map(|k| k / sum_lateral).collect();
        // Scale diffuse scatterers so the RMS after both kernels is the material's level.
        let energy: f64 = kernel_axial
            .iter()
            .map(|k| (*k as f64).powi(2))
            .sum::<f64>()
            * kernel_lateral
                .iter()
                .map(|k| (*k as f64).powi(2))
                .sum::<f64>();
        let scatter_norm = 1.0 / (2.0 * energy).sqrt(); // complex: two unit-variance parts
        let sigma_axial_mm = ac.axial_fwhm_mm / (2.0 * (2.0 * 2f64.ln()).sqrt());

        // Extended grid: lateral margin both sides, bottom margin; row 0 is the transducer face.
        let ew = w + 2 * half_lateral;
        let eh = h + half_axial;
        let n = ew * eh;
        let mut scat_re = vec![0f32; n];
        let mut scat_im = vec![0f32; n];
        let mut face_re = vec![0f32; n];
        let mut face_im = vec![0f32; n];
        let mut trans = vec![1f32; n];
        let mut class = vec![CLASS_NONE; n];

        let inv_grain = 10.0; // 0.1 mm scatterer cells
        let amp_water = (db_to_amplitude(ac.water.scatter_db) * scatter_norm) as f32;
        let amp_object = (db_to_amplitude(ac.object.scatter_db) * scatter_norm) as f32;
        let amp_reflect = db_to_amplitude(ac.reflection_db);
        let amp_diffuse = db_to_amplitude(ac.diffuse_db);
        let atten = |m: &Material| {
            // Round trip over one axial pitch, as an amplitude factor.
            10f64.powf(
                -2.0 * m.attenuation_db_per_cm_mhz * ac.frequency_mhz * pitch_axial / 10.0 / 20.0,
            ) as f32
        };
        let atten_water = atten(&ac.water);
        let atten_object = atten(&ac.object);
        let salt_rough = self.scatter_salt ^ 0x5851_f42d_4c95_7f2d;
        let salt_occupancy = self.scatter_salt ^ 0x8cb9_2ba7_2f3d_8dd7;
        let density = ac.scatterer_density;
        // Sparse scatterers carry 1 / sqrt(density) more amplitude, so the RMS level is unchanged.
        let sparse_gain = (1.0 / density.sqrt()) as f32;
        let scatterer = |p: DVec3| -> (f32, f32) {
            let (zr, zi) = cell_gaussian(p, inv_grain, self.scatter_salt);
            if density >= 1.0 {
                (zr, zi)
            } else if cell_occupied(p, inv_grain, salt_occupancy, density) {
                (zr * sparse_gain, zi * sparse_gain)
            } else {
                (0.0, 0.0)
            }
        };
        let salt_diffuse = self.scatter_salt ^ 0x2545_f491_4f6c_dd1d;

        let point = |u: isize, v: isize| origin + ex * u as f64 + ey * v as f64;
        // Near the surface the per-pixel work is needed within the axial PSF reach and the interface tent.
        let band_mm = 4.0 * sigma_axial_mm + 2.0 * pitch_axial;
        let block_radius_mm = 0.5
            * ((ex + ey) * BLOCK as f64)
                .length()
                .max(((ex - ey) * BLOCK as f64).length());
        // The ellipsoid estimate and blends can exceed slope 1 slightly: 1.5 is a safe Lipschitz bound.
        let safe = 1.5 * block_radius_mm + band_mm;

        let blocks_u = ew.div_ceil(BLOCK);
        let blocks_v = eh.div_ceil(BLOCK);
        let mut corner = vec![0f64; (blocks_u + 1) * (blocks_v + 1)];
        for bv in 0..=blocks_v {
            for bu in 0..=blocks_u {
                let u = (bu * BLOCK) as isize - half_lateral as isize;
                let v = (bv * BLOCK) as isize;
                corner[bv * (blocks_u + 1) + bu] = self.phantom.distance(point(u, v));
            }
        }

        for bv in 0..blocks_v {
            for bu in 0..blocks_u {
                let c = [
                    corner[bv * (blocks_u + 1) + bu],
                    corner[bv * (blocks_u + 1) + bu + 1],
                    corner[(bv + 1) * (blocks_u + 1) + bu],
                    corner[(bv + 1) * (blocks_u + 1) + bu + 1],
                ];
                let uniform_outside = c.iter().all(|&d| d > safe);
                let uniform_inside = c.iter().all(|&d| d < -safe);
                let far_background = c.iter().all(|&d| d > safe + 3.0);
                for v in bv * BLOCK..((bv + 1) * BLOCK).min(eh) {
                    for eu in bu * BLOCK..((bu + 1) * BLOCK).min(ew) {
                        let i = v * ew + eu;
                        let u = eu as isize - half_lateral as isize;
                        let p = point(u, v as isize);
                        if uniform_outside || uniform_inside {
                            let (amp, t) = if uniform_inside {
                                (amp_object, atten_object)
                            } else {
                                (amp_water, atten_water)
                            };
                            let (zr, zi) = scatterer(p);
                            scat_re[i] = amp * zr;
                            scat_im[i] = amp * zi;
                            trans[i] = t;
                            if far_background {
                                class[i] = CLASS_BACKGROUND;
                            }
                            continue;
                        }
                        let (d, g) = self.phantom.distance_and_gradient(p);
                        let inside = d < 0.0;
                        let (amp, mut t) = if inside {
                            (amp_object, atten_object)
                        } else {
                            (amp_water, atten_water)
                        };
                        let (zr, zi) = scatterer(p);
                        scat_re[i] = amp * zr;
                        scat_im[i] = amp * zi;
                        if d > 3.0 {
                            class[i] = CLASS_BACKGROUND;
                        }
                        let gn = g.length();
                        if gn > 1e-9 && d.abs() < band_mm {
                            let normal = g / gn;
                            let cos_theta = normal.dot(beam).abs();
                            let perpendicular = d / gn;
                            let along = perpendicular / cos_theta.max(0.02);
                            // The interface's loss is spread over the rows of one crossing (tent, sum 1).
                            let tent = (1.0 - along.abs() / pitch_axial).max(0.0);
                            t *= (1.0 - ac.interface_loss * tent) as f32;
                            if along.abs() < 4.0 * sigma_axial_mm {
                                let envelope = (-(along * along)
                                    / (2.0 * sigma_axial_mm * sigma_axial_mm))
                                    .exp();
                                let surface_point = p - normal * perpendicular;
                                let (rr, ri) = cell_gaussian(surface_point, inv_grain, salt_rough);
                                let (dr, di) =
                                    cell_gaussian(surface_point, inv_grain, salt_diffuse);
                                let specular = amp_reflect * cos_theta.powf(ac.specular_exponent);
                                let diffuse = amp_diffuse * cos_theta;
                                let re = specular * (1.0 + ac.roughness * rr as f64)
                                    + diffuse * dr as f64;
                                let im = specular * ac.roughness * ri as f64 + diffuse * di as f64;
                                face_re[i] = (envelope * re) as f32;
                                face_im[i] = (envelope * im) as f32;
                                if along.abs() <= 0.5 * pitch_axial && cos_theta > 0.9 {
                                    class[i] = CLASS_BOUNDARY;
                                }
                            }
                        }
                        trans[i] = t;
                    }
                }
            }
        }

        // Round-trip attenuation and shadowing, column by column (rows in order).
        let mut transmitted = vec![1f32; ew];
        for v in 0..eh {
            let row = v * ew;
            for (u, column) in transmitted.iter_mut().enumerate() {
                let i = row + u;
                let t = *column;
                scat_re[i] *= t;
                scat_im[i] *= t;
                face_re[i] *= t;
                face_im[i] *= t;
                if t < 0.8 {
                    class[i] = CLASS_NONE;
                }
                *column = t * trans[i];
            }
        }

        // Axial convolution of the diffuse field (rows v - half .. v + half, zero above the face),
        // plus the interface echoes, for the image rows only.
        let mut sum_re = vec![0f32; h * ew];
        let mut sum_im = vec![0f32; h * ew];
        for v in 0..h {
            let out = v * ew;
            for (k, &kv) in kernel_axial.iter().enumerate() {
                let src = v as isize + k as isize - half_axial as isize;
                if src < 0 || src >= eh as isize {
                    continue;
                }
                let src = src as usize * ew;
                for u in 0..ew {
                    sum_re[out + u] += kv * scat_re[src + u];
                    sum_im[out + u] += kv * scat_im[src + u];
                }
            }
            for u in 0..ew {
                sum_re[out + u] += face_re[v * ew + u];
                sum_im[out + u] += face_im[v * ew + u];
            }
        }

        // Lateral convolution, cropping the margins; noise; envelope; log compression.
        let mut rng = ChaCha8Rng::seed_from_u64(frame_seed);
        let noise = db_to_amplitude(ac.noise_db) as f32 / std::f32::consts::SQRT_2;
        let dr = ac.dynamic_range_db as f32;
        let mut grey = vec![0u8; w * h];
        let mut envelope_out = if keep_envelope {
            Some(vec![0f32; w * h])
        } else {
            None
        };
        let mut levels = LevelSums::default();
        for v in 0..h {
            let row = v * ew;
            // TGC: undo the surround's round-trip attenuation down to this row (on the echoes, before the
            // receiver noise, which stays at its floor).
            let gain = if ac.depth_gain_compensation {
                atten_water.powi(-(v as i32))
            } else {
                1.0
            };
            for u in 0..w {
                let mut re = 0f32;
                let mut im = 0f32;
                for (k, &kv) in kernel_lateral.iter().enumerate() {
                    re += kv * sum_re[row + u + k];
                    im += kv * sum_im[row + u + k];
                }
                if ac.depth_gain_compensation {
                    re *= gain;
                    im *= gain;
                }
                let nr: f32 = StandardNormal.sample(&mut rng);
                let ni: f32 = StandardNormal.sample(&mut rng);
                re += noise * nr;
                im += noise * ni;
                let env = (re * re + im * im).sqrt();
                let db = 20.0 * env.max(1e-12).log10();
                let g = (255.0 * ((db + dr) / dr).clamp(0.0, 1.0) + 0.5).floor() as u8;
                grey[v * w + u] = g;
                if let Some(e) = envelope_out.as_mut() {
                    e[v * w + u] = env;
                }
                match class[(v * ew) + u + half_lateral] {
                    CLASS_BACKGROUND => {
                        levels.background_sum += g as f64;
                        levels.background_count += 1;
                    }
                    CLASS_BOUNDARY => {
                        levels.boundary_sum += g as f64;
                        levels.boundary_count += 1;
                    }
                    _ => {}
                }
            }
        }
        Frame {
            grey,
            envelope: envelope_out,
            levels,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::phantom::{Sdf, SolidPhantom, SurfaceFn};
    use super::*;

    const W: usize = 128;
    const H: usize = 120;
    const PITCH: f64 = 0.2;

    /// Image -> object of a probe whose face centre is at `face`, array along x, beam straight down.
    fn probe_at(face: DVec3) -> DMat4 {
        let ex = DVec3::X * PITCH;
        let ey = -DVec3::Z * PITCH;
        let origin = face - ex * (0.5 * (W as f64 - 1.0));
        DMat4::from_cols(
            ex.extend(0.0),
            ey.extend(0.0),
            (ex.cross(ey).normalize() * PITCH).extend(0.0),
            origin.extend(1.0),
        )
    }

    fn form(phantom: &dyn Phantom, acoustics: Acoustics, m: &DMat4) -> Frame {
        FrameFormer {
            phantom,
            acoustics,
            grid: ImageGrid {
                width: W,
                height: H,
            },
            scatter_salt: 99,
        }
        .form(m, 5, true)
    }

    /// Material below the plane through `point` with unit `normal`.
    #[derive(Debug)]
    struct HalfSpace {
        point: DVec3,
        normal: DVec3,
    }

    impl Phantom for HalfSpace {
        fn distance_and_gradient(&self, p: DVec3) -> (f64, DVec3) {
            ((p - self.point).dot(self.normal), self.normal)
        }
        fn bounds(&self) -> (DVec3, DVec3) {
            (DVec3::splat(-1e3), DVec3::splat(1e3))
        }
        fn surfaces(&self) -> Vec<(String, &SurfaceFn)> {
            Vec::new()
        }
    }

    fn mean(values: impl Iterator<Item = f64>) -> f64 {
        let (s, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
        s / n as f64
    }

    /// A sphere far below the image: only the surrounding medium is in view.
    fn nothing_in_view() -> SolidPhantom {
        SolidPhantom::new(
            "far",
            Sdf::Sphere {
                center: DVec3::new(0.0, 0.0, -500.0),
                radius: 1.0,
            },
        )
    }

    #[test]
    fn default_preset_is_the_default_acoustics_and_writes_no_new_field() {
        assert_eq!(PhysicsPreset::Default.acoustics(), Acoustics::default());
        assert_eq!(
            Acoustics::default().with_surround(Surround::Water),
            Acoustics::default()
        );
        // phantom.json of a default run keeps its bytes: the density appears only when set.
        let json = serde_json::to_string(&Acoustics::default()).unwrap();
        assert!(!json.contains("scatterer_density"), "{json}");
        let sparse = Acoustics {
            scatterer_density: 0.1,
            ..Default::default()
        };
        let json = serde_json::to_string(&sparse).unwrap();
        assert!(json.contains("\"scatterer_density\":0.1"), "{json}");
        let back: Acoustics = serde_json::from_str(&json).unwrap();
        assert_eq!(back, sparse);
        for preset in [
            PhysicsPreset::Default,
            PhysicsPreset::Tissue,
            PhysicsPreset::Bone,
        ] {
            assert_eq!(preset.acoustics().validate(), Ok(()), "{preset:?}");
        }
    }

    #[test]
    fn lower_specular_exponent_brightens_a_wall_at_45_degrees() {
        // The wall's normal is 45 degrees from the beam; it crosses the image's centre 10 mm deep.
        let s = std::f64::consts::FRAC_1_SQRT_2;
        let wall = HalfSpace {
            point: DVec3::new(0.0, 0.0, 0.0),
            normal: DVec3::new(s, 0.0, s),
        };
        let m = probe_at(DVec3::new(0.0, 0.0, 10.0));
        let echo = |exponent: f64| {
            let a = Acoustics {
                specular_exponent: exponent,
                ..Default::default()
            };
            let frame = form(&wall, a, &m);
            // Pixels within 0.2 mm of the wall, away from the image's edges.
            mean(
                (10..H - 10)
                    .flat_map(|v| (10..W - 10).map(move |u| (u, v)))
                    .filter_map(|(u, v)| {
                        let p = m.transform_point3(DVec3::new(u as f64, v as f64, 0.0));
                        wall.distance(p)
                            .abs()
                            .lt(&0.2)
                            .then(|| frame.grey[v * W + u] as f64)
                    }),
            )
        };
        let (e4, e8, e12, e16) = (echo(4.0), echo(8.0), echo(12.0), echo(16.0));
        // cos^n at 45 degrees: 0.25, 0.063, 0.016, 0.004 of the normal-incidence echo.
        assert!(e4 > e8 + 10.0, "cos^4 {e4} vs cos^8 {e8}");
        assert!(e8 > e12 + 5.0, "cos^8 {e8} vs cos^12 {e12}");
        assert!(e12 >= e16, "cos^12 {e12} vs cos^16 {e16}");
    }

    #[test]
    fn tissue_surround_is_speckle_brighter_than_water() {
        let m = probe_at(DVec3::new(0.0, 0.0, 50.0));
        let far = nothing_in_view();
        let grey = |surround: Surround| {
            let frame = form(&far, Acoustics::default().with_surround(surround), &m);
            mean(
                (10..H - 10)
                    .flat_map(|v| (10..W - 10).map(move |u| v * W + u))
                    .map(|i| frame.grey[i] as f64),
            )
        };
        let (water, tissue) = (grey(Surround::Water), grey(Surround::Tissue));
        // 8.5 dB more scatter: ~36 grey levels more on a 60 dB display.
        assert!(tissue > water + 25.0, "tissue {tissue} vs water {water}");
    }

    #[test]
    fn sparse_scatterers_keep_the_level_but_lose_rayleigh_statistics() {
        let m = probe_at(DVec3::new(0.0, 0.0, 50.0));
        let far = nothing_in_view();
        let stats = |density: f64| {
            let mut a = Acoustics::default().with_surround(Surround::Tissue);
            a.scatterer_density = density;
            let frame = form(&far, a, &m);
            let env = frame.envelope.unwrap();
            let values: Vec<f64> = (10..H - 10)
                .flat_map(|v| (10..W - 10).map(move |u| v * W + u))
                .map(|i| env[i] as f64)
                .collect();
            let mu = mean(values.iter().copied());
            let power = mean(values.iter().map(|x| x * x));
            let sd = (power - mu * mu).sqrt();
            (power, mu / sd)
        };
        let (power_full, snr_full) = stats(1.0);
        let (power_sparse, snr_sparse) = stats(0.02);
        let rayleigh = (std::f64::consts::PI / (4.0 - std::f64::consts::PI)).sqrt();
        assert!((snr_full / rayleigh - 1.0).abs() < 0.15, "full {snr_full}");
        // About half a scatterer per resolution cell: far below Rayleigh's signal-to-noise ratio.
        assert!(snr_sparse < 0.8 * rayleigh, "sparse {snr_sparse}");
        let ratio = power_sparse / power_full;
        assert!((0.6..=1.6).contains(&ratio), "mean power ratio {ratio}");
        let bad = Acoustics {
            scatterer_density: 0.0,
            ..Default::default()
        };
        assert!(bad.validate().unwrap_err().contains("scatterer_density"));
    }

    #[test]
    fn bone_echo_is_bright_and_dark_below() {
        // A 6 mm bone ball 12 mm below the face, in tissue.
        let ball = SolidPhantom::new(
            "ball",
            Sdf::Sphere {
                center: DVec3::ZERO,
                radius: 6.0,
            },
        );
        let m = probe_at(DVec3::new(0.0, 0.0, 12.0));
        let frame = form(&ball, PhysicsPreset::Bone.acoustics(), &m);
        let grey = |v: usize, u: usize| frame.grey[v * W + u] as f64;
        let centre = W / 2;
        // The top of the ball is 6 mm deep: rows 28-32.
        let echo = (27..=33)
            .map(|v| mean((centre - 3..centre + 3).map(|u| grey(v, u))))
            .fold(0.0, f64::max);
        // Inside and under the ball (rows 40-110), within 3 mm of the axis (the ball's radius is 6 mm), against tissue beside it.
        let under = mean(
            (40..110)
                .flat_map(|v| (centre - 15..centre + 15).map(move |u| (v, u)))
                .map(|(v, u)| grey(v, u)),
        );
        let beside = mean(
            (40..110)
                .flat_map(|v| (0..20).chain(W - 20..W).map(move |u| (v, u)))
                .map(|(v, u)| grey(v, u)),
        );
        assert!(echo > 170.0, "bone echo {echo}");
        // What remains under the bone is the (depth-compensated) electronic noise, far below tissue.
        assert!(
            under + 20.0 < beside,
            "under the bone {under}, tissue beside {beside}"
        );
    }
}
