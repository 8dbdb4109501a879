//! The option set of [`extract`](super::extract) in two tiers: [`UserOptions`], the few a user sets,
//! and [`Tuning`], every other knob. Each knob lives here once, with one default; [`ExtractConfig`]
//! (de)serialises the whole set (the CLI's `--config` TOML), [`ExtractConfig::validate`] checks every
//! range and names the field, and [`ExtractConfig::to_extract_options`] builds what the pipeline runs.
//! docs/guide/options.md lists the knobs with their recommended ranges.

use serde::{Deserialize, Serialize};

use super::{
    DEFAULT_BRIDGE_GAP_MM, DEFAULT_ECHO_MARGIN_MM, DEFAULT_MAX_ECHO_DISTANCE_MM,
    DEFAULT_MIN_ECHO_FRAMES, DEFAULT_SMOOTHING_MM, ExtractOptions, ImageCrests, IsoLevels, Method,
    Sheet, VoxelRouteOptions, WeakEchoes,
};
use crate::io::ReferenceChoice;
use crate::rbf::FitOptions;
use crate::segment::{InitialBand, SegmentOptions};
use crate::surface::{SheetOptions, SurfaceOptions};

/// An option out of range: which one (its path in the TOML, e.g. `tuning.segment.threshold`) and why.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field} {problem}")]
pub struct OptionError {
    /// The option's path in [`ExtractConfig`], as the TOML spells it.
    pub field: String,
    /// What a valid value is, and the value given.
    pub problem: String,
}

/// Which route turns the frames into a surface (its settings are in [`Tuning::voxel`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MethodChoice {
    /// Segment, fit one RBF to the kept pixels, surface it (the paper's route).
    #[default]
    Rbf,
    /// The PLUS-like volume of all clipped pixels, a Gaussian, marching cubes.
    Voxel,
}

/// Both tiers: what `--print-config` writes and `--config` reads.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ExtractConfig {
    pub user: UserOptions,
    pub tuning: Tuning,
}

/// The user tier: what most runs set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct UserOptions {
    /// Iso-level(s) of the boundary echo (one surface each), or `"auto"`: between the background and
    /// boundary echo levels of the kept pixels.
    #[serde(with = "iso_serde")]
    pub iso: IsoLevels,
    /// Smoothing weight w of the RBF fit (mm; larger is smoother, 0 interpolates the speckle).
    pub smoothing_mm: f64,
    /// Output surface: the iso-surface, one sheet on each echo's ridge, or `auto` (see [`Sheet`]).
    #[serde(with = "sheet_serde")]
    pub sheet: Sheet,
    /// Lattice spacing of the surfacer (mm); the voxel route's grid spacing unless set there.
    pub resolution_mm: f64,
    /// Random decimation target for the samples handed to the fit.
    pub max_samples: usize,
    /// Remove what no echo backs (flaps, small and unechoed pieces) and join near pieces, as set in
    /// [`CleanupTuning`]; `false` keeps the surface as drawn.
    pub cleanup: bool,
    pub method: MethodChoice,
    /// Seed of the random decimation and of everything else random.
    pub seed: u64,
}

impl Default for UserOptions {
    fn default() -> Self {
        UserOptions {
            iso: IsoLevels::Auto,
            smoothing_mm: DEFAULT_SMOOTHING_MM,
            sheet: Sheet::Auto,
            resolution_mm: SurfaceOptions::default().resolution_mm,
            max_samples: 100_000,
            cleanup: true,
            method: MethodChoice::Rbf,
            seed: 1,
        }
    }
}

/// The expert tier: every other knob, grouped by stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
#[non_exhaustive]
pub struct Tuning {
    /// World frame the frames are placed in: `auto`, `tracker` or `reference`.
    #[serde(with = "world_serde")]
    pub world: ReferenceChoice,
    /// Refuse up front when the run would need more than this many MB (10^6 bytes); `None` (`"auto"`
    /// in the TOML): half the machine's memory.
    #[serde(with = "auto_f64")]
    pub memory_budget_mb: Option<f64>,
    /// Region of trust: no surface farther than this (mm) from any sample; `None` (`"auto"`): from
    /// the frame spacing ([`super::trust_distance_for`]).
    #[serde(with = "auto_f64")]
    pub trust_distance_mm: Option<f64>,
    pub segment: SegmentOptions,
    pub sampling: SamplingTuning,
    /// The RBF fit; its smoothing and seed are the user tier's.
    pub fit: FitOptions,
    /// The surfacer; its resolution is the user tier's, its trust distance `trust_distance_mm`.
    pub surface: SurfaceOptions,
    /// The echo-ridge sheet ([`Sheet::EchoRidge`], and `auto` where it picks it).
    pub ridge: SheetOptions,
    /// Weaker echoes extending the ridge sheet.
    pub weak_echoes: WeakEchoes,
    /// The frames' echo crests extending the ridge sheet.
    pub image_crests: ImageCrests,
    pub cleanup: CleanupTuning,
    /// The voxel route ([`MethodChoice::Voxel`]); its memory budget is `memory_budget_mb`.
    pub voxel: VoxelRouteOptions,
}

impl Default for Tuning {
    fn default() -> Self {
        Tuning {
            world: ReferenceChoice::Auto,
            memory_budget_mb: None,
            trust_distance_mm: None,
            segment: SegmentOptions::default(),
            sampling: SamplingTuning::default(),
            fit: FitOptions::default(),
            surface: SurfaceOptions::default(),
            ridge: SheetOptions::default(),
            weak_echoes: WeakEchoes::default(),
            image_crests: ImageCrests::default(),
            cleanup: CleanupTuning::default(),
            voxel: VoxelRouteOptions::default(),
        }
    }
}

/// From kept pixels to the samples of the fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
#[non_exhaustive]
pub struct SamplingTuning {
    /// Kept pixels are averaged over blocks of about this size (mm) first; 0 = single pixels.
    pub bin_mm: f64,
    /// Echo-priority thinning: samples within this distance (mm) of an echo are kept first (up to half
    /// the budget), the rest at random; 0 = the paper's uniform random decimation.
    pub echo_margin_mm: f64,
}

impl Default for SamplingTuning {
    fn default() -> Self {
        SamplingTuning {
            bin_mm: 0.4,
            echo_margin_mm: DEFAULT_ECHO_MARGIN_MM,
        }
    }
}

/// What [`UserOptions::cleanup`] removes and joins, in this order.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
#[non_exhaustive]
pub struct CleanupTuning {
    /// Ridge sheet: triangles farther than this (mm) from every echo are removed; 0 keeps them.
    pub max_echo_distance_mm: f64,
    /// Pieces smaller than this (mm^2) are removed; `None` (`"auto"`): 5 for the iso sheet, 2 for the
    /// ridge sheet, and at the end any piece under [`super::MIN_PIECE_SHARE_OF_LARGEST`] of the largest.
    #[serde(with = "auto_f64")]
    pub min_component_area_mm2: Option<f64>,
    /// Pieces that echoes from fewer than this many frames back are removed; 0 keeps every piece.
    pub min_echo_frames: usize,
    /// Pieces whose boundaries pass within this distance (mm), continuing one another, are joined.
    pub bridge_gap_mm: f64,
    /// Rings of triangles peeled off each piece's rim; 0 keeps the rims.
    pub trim_rim_rings: usize,
}

impl Default for CleanupTuning {
    fn default() -> Self {
        CleanupTuning {
            max_echo_distance_mm: DEFAULT_MAX_ECHO_DISTANCE_MM,
            min_component_area_mm2: None,
            min_echo_frames: DEFAULT_MIN_ECHO_FRAMES,
            bridge_gap_mm: DEFAULT_BRIDGE_GAP_MM,
            trim_rim_rings: 0,
        }
    }
}

/// `Err` naming `field` unless `ok`.
fn check(ok: bool, field: &str, problem: impl FnOnce() -> String) -> Result<(), OptionError> {
    if ok {
        Ok(())
    } else {
        Err(OptionError {
            field: field.to_string(),
            problem: problem(),
        })
    }
}

fn positive_mm(field: &str, mm: f64) -> Result<(), OptionError> {
    check(mm.is_finite() && mm > 0.0, field, || {
        format!("must be a positive number of mm, got {mm}")
    })
}

fn non_negative(field: &str, x: f64, unit: &str) -> Result<(), OptionError> {
    check(x.is_finite() && x >= 0.0, field, || {
        format!("must be 0 or a positive number{unit}, got {x}")
    })
}

impl ExtractConfig {
    /// Checks every range; the error names the first field out of range (its TOML path).
    pub fn validate(&self) -> Result<(), OptionError> {
        let (u, t) = (&self.user, &self.tuning);
        if let IsoLevels::Levels(levels) = &u.iso {
            check(!levels.is_empty(), "user.iso", || {
                "must be \"auto\" or at least one level".into()
            })?;
            for (k, &level) in levels.iter().enumerate() {
                check(level.is_finite(), "user.iso", || {
                    format!("must hold finite levels, got {level}")
                })?;
                // Each level's mesh is named after it: a level listed twice would be written twice.
                check(!levels[..k].contains(&level), "user.iso", || {
                    format!("lists the level {level} twice")
                })?;
            }
        }
        non_negative("user.smoothing_mm", u.smoothing_mm, " of mm")?;
        positive_mm("user.resolution_mm", u.resolution_mm)?;
        check(u.max_samples > 0, "user.max_samples", || {
            "must be at least 1, got 0".into()
        })?;
        if let Some(mb) = t.memory_budget_mb {
            check(
                mb.is_finite() && mb > 0.0,
                "tuning.memory_budget_mb",
                || format!("must be \"auto\" or a positive number of MB, got {mb}"),
            )?;
        }
        if let Some(mm) = t.trust_distance_mm {
            positive_mm("tuning.trust_distance_mm", mm)?;
        }
        let s = &t.segment;
        check(
            s.threshold.is_finite() && s.threshold > 0.0 && s.threshold <= 1.0,
            "tuning.segment.threshold",
            || format!("must be in (0, 1], got {}", s.threshold),
        )?;
        s.validate().map_err(|e| OptionError {
            field: "tuning.segment".into(),
            problem: format!("is invalid: {e}"),
        })?;
        non_negative("tuning.sampling.bin_mm", t.sampling.bin_mm, " of mm")?;
        non_negative(
            "tuning.sampling.echo_margin_mm",
            t.sampling.echo_margin_mm,
            " of mm",
        )?;
        let f = &t.fit;
        check(
            f.accuracy.is_finite() && f.accuracy > 0.0,
            "tuning.fit.accuracy_grey",
            || {
                format!(
                    "must be a positive number of grey levels, got {}",
                    f.accuracy
                )
            },
        )?;
        check(
            f.eval_accuracy.is_finite() && f.eval_accuracy > 0.0 && f.eval_accuracy < 1.0,
            "tuning.fit.eval_accuracy",
            || format!("must be in (0, 1), got {}", f.eval_accuracy),
        )?;
        non_negative(
            "tuning.fit.merge_distance_mm",
            f.merge_distance_mm,
            " of mm",
        )?;
        check(f.pu_leaf_points > 0, "tuning.fit.pu_leaf_points", || {
            "must be at least 1, got 0".into()
        })?;
        non_negative("tuning.fit.pu_overlap", f.pu_overlap, "")?;
        non_negative(
            "tuning.fit.pu_min_overlap_mm",
            f.pu_min_overlap_mm,
            " of mm",
        )?;
        check(
            t.surface.cluster_cell_factor.is_finite() && t.surface.cluster_cell_factor > 0.0,
            "tuning.surface.cluster_cell_factor",
            || {
                format!(
                    "must be a positive number, got {}",
                    t.surface.cluster_cell_factor
                )
            },
        )?;
        positive_mm(
            "tuning.surface.surface_tolerance_mm",
            t.surface.surface_tolerance_mm,
        )?;
        let r = &t.ridge;
        positive_mm("tuning.ridge.smoothing_mm", r.smoothing_mm)?;
        positive_mm("tuning.ridge.reach_mm", r.reach_mm)?;
        let w = &t.weak_echoes;
        positive_mm("tuning.weak_echoes.reach_mm", w.reach_mm)?;
        non_negative("tuning.ridge.bridge_mm", r.bridge_mm, " of mm")?;
        non_negative(
            "tuning.ridge.max_hole_perimeter_mm",
            r.max_hole_perimeter_mm,
            " of mm",
        )?;
        check(
            w.level_fraction.is_finite() && (0.0..1.0).contains(&w.level_fraction),
            "tuning.weak_echoes.level_fraction",
            || {
                format!(
                    "must be a fraction in [0, 1) of the way from the iso-level to the background, got {}",
                    w.level_fraction
                )
            },
        )?;
        let ic = &t.image_crests;
        positive_mm("tuning.image_crests.link_mm", ic.link_mm)?;
        positive_mm("tuning.image_crests.seed_mm", ic.seed_mm)?;
        positive_mm("tuning.image_crests.normal_radius_mm", ic.normal_radius_mm)?;
        ic.crest.validate().map_err(|e| OptionError {
            field: "tuning.image_crests.crest".into(),
            problem: e.to_string(),
        })?;
        let c = &t.cleanup;
        non_negative(
            "tuning.cleanup.max_echo_distance_mm",
            c.max_echo_distance_mm,
            " of mm",
        )?;
        if let Some(a) = c.min_component_area_mm2 {
            non_negative("tuning.cleanup.min_component_area_mm2", a, " of mm^2")?;
        }
        non_negative("tuning.cleanup.bridge_gap_mm", c.bridge_gap_mm, " of mm")?;
        if let Some(mm) = t.voxel.spacing_mm {
            positive_mm("tuning.voxel.spacing_mm", mm)?;
        }
        non_negative(
            "tuning.voxel.smoothing_sigma_mm",
            t.voxel.smoothing_sigma_mm,
            " of mm",
        )?;
        Ok(())
    }

    /// What the pipeline runs, with the first band `init` (a band is data, not an option). The memory
    /// budget `"auto"` becomes half the machine's memory here. Does not validate: call
    /// [`Self::validate`] first.
    pub fn to_extract_options(&self, init: InitialBand) -> ExtractOptions {
        let (u, t) = (&self.user, &self.tuning);
        let (c, keep_all) = (&t.cleanup, !u.cleanup);
        ExtractOptions {
            method: match u.method {
                MethodChoice::Rbf => Method::Rbf,
                MethodChoice::Voxel => Method::Voxel(t.voxel.clone()),
            },
            iso: u.iso.clone(),
            init,
            segment: t.segment.clone(),
            reference: t.world,
            max_samples: u.max_samples,
            seed: u.seed,
            fit: FitOptions {
                smoothing: u.smoothing_mm,
                seed: u.seed,
                ..t.fit.clone()
            },
            surface: SurfaceOptions {
                resolution_mm: u.resolution_mm,
                ..t.surface.clone()
            },
            trust_distance_mm: t.trust_distance_mm,
            sample_bin_mm: t.sampling.bin_mm,
            echo_margin_mm: (t.sampling.echo_margin_mm > 0.0).then_some(t.sampling.echo_margin_mm),
            max_echo_distance_mm: if keep_all {
                0.0
            } else {
                c.max_echo_distance_mm
            },
            min_component_area_mm2: if keep_all {
                Some(0.0)
            } else {
                c.min_component_area_mm2
            },
            min_echo_frames: if keep_all { 0 } else { c.min_echo_frames },
            bridge_gap_mm: if keep_all { 0.0 } else { c.bridge_gap_mm },
            trim_rim_rings: if keep_all { 0 } else { c.trim_rim_rings },
            sheet: u.sheet,
            echo_sheet: t.ridge.clone(),
            weak_echoes: t.weak_echoes.clone(),
            image_crests: t.image_crests.clone(),
            memory_budget_bytes: Some(match t.memory_budget_mb {
                Some(mb) => (mb * 1e6) as u64,
                None => crate::resources::default_memory_budget_bytes(),
            }),
        }
    }
}

/// [`IsoLevels`] as `"auto"`, one number or a list of numbers.
mod iso_serde {
    use serde::{Deserialize, Deserializer, Serialize, Serializer, de::Error};

    use super::IsoLevels;

    #[derive(Serialize, Deserialize)]
    #[serde(untagged)]
    enum Iso {
        Levels(Vec<f64>),
        Level(f64),
        Word(String),
    }

    pub fn serialize<S: Serializer>(value: &IsoLevels, s: S) -> Result<S::Ok, S::Error> {
        match value {
            IsoLevels::Auto => Iso::Word("auto".into()),
            IsoLevels::Levels(l) => Iso::Levels(l.clone()),
        }
        .serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<IsoLevels, D::Error> {
        match Iso::deserialize(d)? {
            Iso::Levels(l) => Ok(IsoLevels::Levels(l)),
            Iso::Level(l) => Ok(IsoLevels::Levels(vec![l])),
            Iso::Word(w) if w.eq_ignore_ascii_case("auto") => Ok(IsoLevels::Auto),
            Iso::Word(w) => Err(D::Error::custom(format!(
                "expected \"auto\", a level or a list of levels, got \"{w}\""
            ))),
        }
    }
}

use crate::serde_forms::{auto_f64, word_serde};

word_serde!(sheet_serde, Sheet, ["auto" => Sheet::Auto, "iso" => Sheet::Iso, "ridge" => Sheet::EchoRidge]);
word_serde!(world_serde, ReferenceChoice, [
    "auto" => ReferenceChoice::Auto,
    "tracker" => ReferenceChoice::Tracker,
    "reference" => ReferenceChoice::Reference,
]);

#[cfg(test)]
mod tests;
