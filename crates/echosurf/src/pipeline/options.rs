//! The option set of [`extract`](super::extract) in two tiers: [`UserOptions`], the few a user sets,
//! and [`Tuning`], every other knob. Each knob lives here once, with one default; [`ExtractConfig`]
//! (de)serialises the whole set (the CLI's `--config` TOML), [`ExtractConfig::validate`] checks every
//! range and names the field, and [`ExtractConfig::to_extract_options`] builds what the pipeline runs.
//! docs/guide/options.md lists the knobs with their recommended ranges.

use serde::{Deserialize, Serialize};

use super::{
    DEFAULT_BRIDGE_GAP_MM, DEFAULT_ECHO_MARGIN_MM, DEFAULT_MAX_ECHO_DISTANCE_MM,
    DEFAULT_MIN_ECHO_FRAMES, DEFAULT_SMOOTHING_MM, ExtractOptions, IsoLevels, Method, Sheet,
    VoxelRouteOptions, WeakEchoes,
};
use crate::io::ReferenceChoice;
use crate::rbf::{FitOptions, SolverChoice};
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

/// Which route turns the frames into a surface (its settings are in [`VoxelTuning`]).
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
    pub fit: FitTuning,
    pub surface: SurfaceTuning,
    pub ridge: RidgeTuning,
    pub cleanup: CleanupTuning,
    pub voxel: VoxelTuning,
}

impl Default for Tuning {
    fn default() -> Self {
        Tuning {
            world: ReferenceChoice::Auto,
            memory_budget_mb: None,
            trust_distance_mm: None,
            segment: SegmentOptions::default(),
            sampling: SamplingTuning::default(),
            fit: FitTuning::default(),
            surface: SurfaceTuning::default(),
            ridge: RidgeTuning::default(),
            cleanup: CleanupTuning::default(),
            voxel: VoxelTuning::default(),
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

/// The RBF fit, besides the smoothing (user tier) and the seed (user tier).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
#[non_exhaustive]
pub struct FitTuning {
    /// `auto` (dense up to `direct_max_points`, partition of unity above), `direct`, `pu` or `fast`.
    #[serde(with = "solver_serde")]
    pub solver: SolverChoice,
    /// Largest allowed |s(x_i) - f_i - w l_i| (grey levels).
    pub accuracy_grey: f64,
    /// Relative accuracy of the fast evaluator.
    pub eval_accuracy: f64,
    /// Samples closer than this (mm) are merged into one.
    pub merge_distance_mm: f64,
    /// Largest problem the `auto` solver solves densely.
    pub direct_max_points: usize,
    /// Krylov iteration budget of the `fast` solver.
    pub max_iterations: usize,
    /// Partition of unity: samples per leaf cell, support expansion per side (relative to the leaf's
    /// half-size) and its minimum (mm).
    pub pu_leaf_points: usize,
    pub pu_overlap: f64,
    pub pu_min_overlap_mm: f64,
}

impl Default for FitTuning {
    fn default() -> Self {
        let f = FitOptions::default();
        FitTuning {
            solver: f.solver,
            accuracy_grey: f.accuracy,
            eval_accuracy: f.eval_accuracy,
            merge_distance_mm: f.merge_distance_mm,
            direct_max_points: f.direct_max_points,
            max_iterations: f.max_iterations,
            pu_leaf_points: f.pu_leaf_points,
            pu_overlap: f.pu_overlap,
            pu_min_overlap_mm: f.pu_min_overlap_mm,
        }
    }
}

/// The surfacer, besides its resolution (user tier) and the trust distance ([`Tuning`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
#[non_exhaustive]
pub struct SurfaceTuning {
    /// How far (cells) a seed whose own cell is not crossed looks for the surface.
    pub seed_search_radius_cells: u32,
    /// Size of the clustering cells relative to the lattice (larger: coarser mesh).
    pub cluster_cell_factor: f64,
    /// Newton steps at most per vertex when putting vertices back on the surface.
    pub max_newton_steps: u32,
    /// A vertex is on the surface when its first-order distance is below this (mm).
    pub surface_tolerance_mm: f64,
}

impl Default for SurfaceTuning {
    fn default() -> Self {
        let s = SurfaceOptions::default();
        SurfaceTuning {
            seed_search_radius_cells: s.seed_search_radius_cells,
            cluster_cell_factor: s.cluster_cell_factor,
            max_newton_steps: s.max_newton_steps,
            surface_tolerance_mm: s.surface_tolerance_mm,
        }
    }
}

/// The echo-ridge sheet ([`Sheet::EchoRidge`], and `auto` where it picks it).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
#[non_exhaustive]
pub struct RidgeTuning {
    /// Distance (mm) over which the sheet averages the ridge points.
    pub smoothing_mm: f64,
    /// How far (mm) the sheet may reach from the nearest ridge point.
    pub reach_mm: f64,
    /// Also bridge gaps up to this wide (mm) where points surround them on a common plane; 0 = off.
    pub bridge_mm: f64,
    /// Holes whose boundary is at most this long (mm) are closed; 0 keeps them all.
    pub max_hole_perimeter_mm: f64,
    /// Weaker echoes whose peak passes a level this fraction of the way from the iso-level down to
    /// the background extend the sheet where they continue a strong echo's ridge; 0 = off.
    pub weak_level_fraction: f64,
    /// How far (mm) a weak echo's ridge may continue from a strong one.
    pub weak_reach_mm: f64,
}

impl Default for RidgeTuning {
    fn default() -> Self {
        let (sheet, weak) = (SheetOptions::default(), WeakEchoes::default());
        RidgeTuning {
            smoothing_mm: sheet.smoothing_mm,
            reach_mm: sheet.reach_mm,
            bridge_mm: sheet.bridge_mm,
            max_hole_perimeter_mm: sheet.max_hole_perimeter_mm,
            weak_level_fraction: weak.level_fraction,
            weak_reach_mm: weak.reach_mm,
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
    /// ridge sheet.
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

/// The voxel route ([`MethodChoice::Voxel`]); its memory budget is [`Tuning::memory_budget_mb`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
#[non_exhaustive]
pub struct VoxelTuning {
    /// Grid spacing (mm); `None` (`"auto"`): the calibration's OutputSpacing, else the resolution.
    #[serde(with = "auto_f64")]
    pub spacing_mm: Option<f64>,
    /// Sigma of the Gaussian pre-smoothing (mm); 0 = none.
    pub smoothing_sigma_mm: f64,
}

impl Default for VoxelTuning {
    fn default() -> Self {
        let v = VoxelRouteOptions::default();
        VoxelTuning {
            spacing_mm: v.spacing_mm,
            smoothing_sigma_mm: v.smoothing_sigma_mm,
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
            f.accuracy_grey.is_finite() && f.accuracy_grey > 0.0,
            "tuning.fit.accuracy_grey",
            || {
                format!(
                    "must be a positive number of grey levels, got {}",
                    f.accuracy_grey
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
        positive_mm("tuning.ridge.weak_reach_mm", r.weak_reach_mm)?;
        non_negative("tuning.ridge.bridge_mm", r.bridge_mm, " of mm")?;
        non_negative(
            "tuning.ridge.max_hole_perimeter_mm",
            r.max_hole_perimeter_mm,
            " of mm",
        )?;
        check(
            r.weak_level_fraction.is_finite() && (0.0..1.0).contains(&r.weak_level_fraction),
            "tuning.ridge.weak_level_fraction",
            || {
                format!(
                    "must be a fraction in [0, 1) of the way from the iso-level to the background, got {}",
                    r.weak_level_fraction
                )
            },
        )?;
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
        let fit_defaults = FitOptions::default();
        let (c, keep_all) = (&t.cleanup, !u.cleanup);
        ExtractOptions {
            method: match u.method {
                MethodChoice::Rbf => Method::Rbf,
                MethodChoice::Voxel => Method::Voxel(VoxelRouteOptions {
                    spacing_mm: t.voxel.spacing_mm,
                    smoothing_sigma_mm: t.voxel.smoothing_sigma_mm,
                }),
            },
            iso: u.iso.clone(),
            init,
            segment: t.segment.clone(),
            reference: t.world,
            max_samples: u.max_samples,
            seed: u.seed,
            fit: FitOptions {
                smoothing: u.smoothing_mm,
                accuracy: t.fit.accuracy_grey,
                eval_accuracy: t.fit.eval_accuracy,
                seed: u.seed,
                merge_distance_mm: t.fit.merge_distance_mm,
                solver: t.fit.solver,
                direct_max_points: t.fit.direct_max_points,
                max_iterations: t.fit.max_iterations,
                pu_leaf_points: t.fit.pu_leaf_points,
                pu_overlap: t.fit.pu_overlap,
                pu_min_overlap_mm: t.fit.pu_min_overlap_mm,
                ..fit_defaults
            },
            surface: SurfaceOptions {
                resolution_mm: u.resolution_mm,
                seed_search_radius_cells: t.surface.seed_search_radius_cells,
                cluster_cell_factor: t.surface.cluster_cell_factor,
                max_newton_steps: t.surface.max_newton_steps,
                surface_tolerance_mm: t.surface.surface_tolerance_mm,
                ..SurfaceOptions::default()
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
            echo_sheet: SheetOptions {
                smoothing_mm: t.ridge.smoothing_mm,
                reach_mm: t.ridge.reach_mm,
                bridge_mm: t.ridge.bridge_mm,
                max_hole_perimeter_mm: t.ridge.max_hole_perimeter_mm,
            },
            weak_echoes: WeakEchoes {
                level_fraction: t.ridge.weak_level_fraction,
                reach_mm: t.ridge.weak_reach_mm,
            },
            memory_budget_bytes: Some(match t.memory_budget_mb {
                Some(mb) => (mb * 1e6) as u64,
                None => crate::budget::default_memory_budget_bytes(),
            }),
        }
    }
}

/// `Option<f64>` as a number or `"auto"` (TOML has no null).
mod auto_f64 {
    use serde::{Deserialize, Deserializer, Serialize, Serializer, de::Error};

    #[derive(Serialize, Deserialize)]
    #[serde(untagged)]
    enum AutoOr {
        Value(f64),
        Word(String),
    }

    pub fn serialize<S: Serializer>(value: &Option<f64>, s: S) -> Result<S::Ok, S::Error> {
        match value {
            Some(v) => AutoOr::Value(*v),
            None => AutoOr::Word("auto".into()),
        }
        .serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Option<f64>, D::Error> {
        match AutoOr::deserialize(d)? {
            AutoOr::Value(v) => Ok(Some(v)),
            AutoOr::Word(w) if w.eq_ignore_ascii_case("auto") => Ok(None),
            AutoOr::Word(w) => Err(D::Error::custom(format!(
                "expected a number or \"auto\", got \"{w}\""
            ))),
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

/// A unit-like enum as one of a few lower-case words.
macro_rules! word_serde {
    ($module:ident, $type:ty, [$($word:literal => $value:expr),+ $(,)?]) => {
        mod $module {
            use serde::{Deserialize, Deserializer, Serializer, de::Error};

            #[allow(unused_imports)]
            use super::*;

            pub fn serialize<S: Serializer>(value: &$type, s: S) -> Result<S::Ok, S::Error> {
                $(if *value == $value {
                    return s.serialize_str($word);
                })+
                unreachable!("every value has a word")
            }

            pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<$type, D::Error> {
                let word = String::deserialize(d)?;
                $(if word.eq_ignore_ascii_case($word) {
                    return Ok($value);
                })+
                Err(D::Error::custom(format!(
                    "expected one of {}, got \"{word}\"",
                    [$($word),+].join(", ")
                )))
            }
        }
    };
}

word_serde!(sheet_serde, Sheet, ["auto" => Sheet::Auto, "iso" => Sheet::Iso, "ridge" => Sheet::EchoRidge]);
word_serde!(world_serde, ReferenceChoice, [
    "auto" => ReferenceChoice::Auto,
    "tracker" => ReferenceChoice::Tracker,
    "reference" => ReferenceChoice::Reference,
]);
word_serde!(solver_serde, SolverChoice, [
    "auto" => SolverChoice::Auto,
    "direct" => SolverChoice::Direct,
    "pu" => SolverChoice::PartitionOfUnity,
    "fast" => SolverChoice::Fast,
]);

#[cfg(test)]
mod tests;
