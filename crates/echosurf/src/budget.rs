//! Memory budgets of `extract`, `fit`, `surface` and `compare`: each estimate is what is resident now
//! plus the buffers still to come, computed from the inputs' real sizes before they are allocated and
//! refused with [`Error::ResourceLimit`] saying what would fit instead of running out of memory
//! half-way. The voxel grid has its own (`voxel::estimated_memory_bytes`). Constants and the table they
//! were measured on: docs/decisions/0028-memory-budget-estimates.md.

pub use crate::resources::default_memory_budget_bytes;

use crate::io::TrackedSequence;
use crate::progress::Progress;
use crate::rbf::SolverChoice;
use crate::{Error, OptionName, Phrase, Result};

/// Band masks and smoothing buffers per pixel while segmenting.
const SEGMENT_BYTES_PER_PIXEL: u64 = 2;
/// Per binned sample: position (3 x f64), grey level (f32), frame (u32), its block (2 x u32), with
/// the growth slack of the collecting vectors.
const SAMPLE_BYTES: u64 = 40;
/// Per binned sample while thinning them: the near-echo flags, the shuffled indices and the kept set.
const DECIMATE_BYTES_PER_SAMPLE: u64 = 16;
/// Partition-of-unity fit per sample handed to it inside `extract`: its patches' overlapping centres,
/// their dense blocks and the model, less what it reuses of the memory the sampling stages freed.
const PU_FIT_BYTES_PER_SAMPLE: u64 = 320;
/// The same fit in a process that did nothing before (`echosurf fit`): nothing freed to reuse.
const PU_FIT_FRESH_BYTES_PER_SAMPLE: u64 = 620;
/// Fast solver per centre: treecode nodes and moments, neighbour lists, Schwarz blocks, Krylov basis.
const FAST_FIT_BYTES_PER_CENTRE: u64 = 4096;
/// The fast solver's FMM translation tables (316 offsets of 147 x 147 f64 at the default accuracy for
/// the product, of 65 x 65 for the coarse level's) and their transient build, from
/// [`crate::rbf::FMM_MIN_POINTS`] samples.
const FAST_FIT_FMM_TABLE_BYTES: u64 = 96 << 20;
/// Surface per seed point at 0.5 mm: the lattice nodes followed from it, the trust buckets and the
/// meshes (the fitted model is resident when the check runs).
const SURFACE_BYTES_PER_SEED: u64 = 7000;

/// What the process holds now (binary, allocator, decoded inputs): the base every estimate adds the
/// buffers still to come to. 0 where the platform does not report it.
pub fn resident_bytes() -> u64 {
    crate::resources::current_rss_bytes().unwrap_or(0)
}

/// Tells `observer` the estimate `need` and refuses it past `budget_bytes` (set by
/// [`OptionName::MemoryBudget`]) with `message()`.
fn check_need(
    need: u64,
    budget_bytes: u64,
    observer: &dyn Progress,
    message: impl FnOnce() -> Phrase,
) -> Result<()> {
    observer.memory_estimate(need);
    if need <= budget_bytes {
        Ok(())
    } else {
        Err(Error::OverBudget {
            needed_bytes: need,
            budget_bytes,
            budget_option: Some(OptionName::MemoryBudget),
            message: message(),
        })
    }
}

/// "raise" and the memory budget's option.
fn or_raise_budget() -> Phrase {
    Phrase::new("raise ").option(OptionName::MemoryBudget)
}

/// The buffers of one RBF extract run still to come once the bands are segmented, in bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ExtractMemoryEstimate {
    /// Resident when the estimate is made: the decoded frames, their band masks and the process.
    pub resident: u64,
    /// The contrast-normalised copy of the frames a bone sweep samples from.
    pub normalised_frames: u64,
    /// Samples of the kept pixels (one per bin) and their thinning.
    pub samples: u64,
    /// The fit: dense matrix (direct solver), patches (partition of unity) or treecode (fast solver).
    pub fit: u64,
}

impl ExtractMemoryEstimate {
    pub fn total(&self) -> u64 {
        self.resident
            .saturating_add(self.normalised_frames)
            .saturating_add(self.samples)
            .saturating_add(self.fit)
    }
}

/// Bytes the fit of `samples` points takes with `options`' solver (as `rbf::fit` chooses it) after the
/// extract's earlier stages.
pub fn fit_bytes(samples: u64, options: &crate::rbf::FitOptions) -> u64 {
    fit_bytes_with(samples, options, PU_FIT_BYTES_PER_SAMPLE)
}

fn fit_bytes_with(samples: u64, options: &crate::rbf::FitOptions, pu_bytes_per_sample: u64) -> u64 {
    let solver = match options.solver {
        SolverChoice::Auto if samples <= options.direct_max_points as u64 => SolverChoice::Direct,
        SolverChoice::Auto => SolverChoice::PartitionOfUnity,
        s => s,
    };
    match solver {
        // The (n + 4)^2 system in f64 and its LU factors.
        SolverChoice::Direct => (samples + 4).saturating_mul(samples + 4).saturating_mul(16),
        SolverChoice::Fast => {
            let table = if samples >= crate::rbf::FMM_MIN_POINTS as u64 {
                FAST_FIT_FMM_TABLE_BYTES
            } else {
                0
            };
            samples
                .saturating_mul(FAST_FIT_BYTES_PER_CENTRE)
                .saturating_add(table)
        }
        _ => samples.saturating_mul(pu_bytes_per_sample),
    }
}

fn mb(bytes: u64) -> String {
    format!("{:.0} MB", bytes as f64 / 1e6)
}

/// Up-front check of the RBF route, before segmenting: what is resident plus the segmentation's
/// buffers over every pixel (a lower bound of the run; [`check_extract_budget_after_segmentation`]
/// knows the kept pixels).
/// The estimate goes to `observer` ([`Progress::memory_estimate`]), as in every check here.
pub fn check_extract_budget(
    sequence: &TrackedSequence,
    budget_bytes: u64,
    observer: &dyn Progress,
) -> Result<()> {
    let pixels = (sequence.width as u64)
        .saturating_mul(sequence.height as u64)
        .saturating_mul(sequence.frames.len() as u64);
    let resident = resident_bytes();
    let segment = pixels.saturating_mul(SEGMENT_BYTES_PER_PIXEL);
    let need = resident.saturating_add(segment);
    check_need(need, budget_bytes, observer, || {
        Phrase::new(format!(
            "extract would need at least {} before fitting ({} resident with the decoded frames, {} to \
            segment {pixels} pixels) but the memory budget is {}: split the sequence (fewer frames) or ",
            mb(need),
            mb(resident),
            mb(segment),
            mb(budget_bytes)
        ))
        .then(or_raise_budget())
    })
}

/// What the segmentation kept, for [`check_extract_budget_after_segmentation`].
#[derive(Debug, Clone, Copy)]
pub struct SegmentedCounts {
    /// Pixels of all frames.
    pub frame_pixels: u64,
    pub kept_pixels: u64,
    /// Pixels per sample block along the image's two axes.
    pub bin_px: [usize; 2],
    /// A bone sweep is sampled from a contrast-normalised copy of the frames.
    pub bone_sweep: bool,
}

/// What the RBF route's budget reads of its options: the sample cap and the fit's options (built by
/// `pipeline::fit_plan`, so this module does not depend on the pipeline's option struct).
#[derive(Debug, Clone, Copy)]
pub struct FitPlan<'a> {
    /// At most this many samples are fitted.
    pub max_samples: usize,
    pub fit: &'a crate::rbf::FitOptions,
}

/// Estimates the RBF route's peak once the bands are segmented: the samples from the kept pixels (one
/// per bin), the fit of at most `max_samples` of them with the solver `rbf::fit` will choose.
pub fn estimate_extract_memory(
    counts: SegmentedCounts,
    options: FitPlan<'_>,
) -> ExtractMemoryEstimate {
    let bin_area = (counts.bin_px[0].max(1) as u64).saturating_mul(counts.bin_px[1].max(1) as u64);
    let binned = counts.kept_pixels.div_ceil(bin_area);
    let fitted = binned.min(options.max_samples as u64);
    let thinning = if binned > fitted {
        binned.saturating_mul(DECIMATE_BYTES_PER_SAMPLE)
    } else {
        0
    };
    ExtractMemoryEstimate {
        resident: resident_bytes(),
        normalised_frames: if counts.bone_sweep {
            counts.frame_pixels
        } else {
            0
        },
        samples: binned.saturating_mul(SAMPLE_BYTES).saturating_add(thinning),
        fit: fit_bytes(fitted, options.fit),
    }
}

/// Second check of the RBF route, after segmenting and before the samples are collected: refuses
/// when the estimate exceeds `budget_bytes`, naming the parts and a sample cap that would fit.
pub fn check_extract_budget_after_segmentation(
    counts: SegmentedCounts,
    options: FitPlan<'_>,
    budget_bytes: u64,
    observer: &dyn Progress,
) -> Result<()> {
    let e = estimate_extract_memory(counts, options);
    check_need(e.total(), budget_bytes, observer, || {
        let fixed = e
            .resident
            .saturating_add(e.normalised_frames)
            .saturating_add(e.samples);
        let advice = if fixed >= budget_bytes {
            Phrase::new(
                "the frames and their kept pixels alone take that: a narrower band, fewer frames or a \
                larger ",
            )
            .option(OptionName::MemoryBudget)
        } else {
            // Largest sample count whose fit fits in what is left.
            let room = budget_bytes - fixed;
            let (mut lo, mut hi) = (0u64, options.max_samples as u64);
            while lo < hi {
                let mid = (lo + hi).div_ceil(2);
                if fit_bytes(mid, options.fit) <= room {
                    lo = mid;
                } else {
                    hi = mid - 1;
                }
            }
            Phrase::new("")
                .option(OptionName::MaxSamples)
                .text(format!(" {lo} or fewer would fit, or "))
                .then(or_raise_budget())
        };
        Phrase::new(format!(
            "extract would need about {} ({} resident with the frames and bands, normalised frames {}, \
            samples of {} kept pixels {}, fit {}; the surface is checked after the fit) but the memory \
             budget is {}: ",
            mb(e.total()),
            mb(e.resident),
            mb(e.normalised_frames),
            counts.kept_pixels,
            mb(e.samples),
            mb(e.fit),
            mb(budget_bytes),
        ))
        .then(advice)
    })
}

/// Refuses a `fit` of `points` points (already read) past `budget_bytes`.
pub fn check_fit_budget(
    points: u64,
    options: &crate::rbf::FitOptions,
    budget_bytes: u64,
    observer: &dyn Progress,
) -> Result<()> {
    let resident = resident_bytes();
    let fit = fit_bytes_with(points, options, PU_FIT_FRESH_BYTES_PER_SAMPLE);
    let need = resident.saturating_add(fit);
    check_need(need, budget_bytes, observer, || {
        Phrase::new(format!(
            "fitting {points} points would need about {} ({} resident, fit {}) but the memory budget \
            is {}: fewer points (",
            mb(need),
            mb(resident),
            mb(fit),
            mb(budget_bytes)
        ))
        .option(OptionName::FitMaxCentres)
        .text(", or thin the cloud), another ")
        .option(OptionName::FitSolver)
        .text(", or ")
        .then(or_raise_budget())
    })
}

/// Refuses surfacing from `seeds` seed points (the points near a level the surface is followed
/// from; `extract` and `surface` take at most `pipeline::MAX_SURFACE_SEEDS`) at `resolution_mm` past
/// `budget_bytes`. The fitted model is resident when this runs.
pub fn check_surface_budget(
    seeds: u64,
    resolution_mm: f64,
    budget_bytes: u64,
    observer: &dyn Progress,
) -> Result<()> {
    let resident = resident_bytes();
    let surface = surface_bytes(seeds, resolution_mm);
    let need = resident.saturating_add(surface);
    check_need(need, budget_bytes, observer, || {
        Phrase::new(format!(
            "surfacing from {seeds} seed points at {resolution_mm} mm would need about {} ({} \
             resident with the fitted model, surface {}) but the memory budget is {}: a coarser ",
            mb(need),
            mb(resident),
            mb(surface),
            mb(budget_bytes)
        ))
        .option(OptionName::SurfaceResolution)
        .text(", or ")
        .then(or_raise_budget())
    })
}

/// Bytes of the surface followed from `seeds` seed points on a `resolution_mm` lattice.
fn surface_bytes(seeds: u64, resolution_mm: f64) -> u64 {
    // Finer lattices follow more nodes over the same surface (area / resolution^2); 0.5 mm is the
    // default the per-seed figure was measured at.
    let scale = (0.5 / resolution_mm).powi(2).clamp(1e-6, 1e12);
    (seeds as f64 * SURFACE_BYTES_PER_SEED as f64 * scale).min(u64::MAX as f64) as u64
}

/// Per area sample of `compare`: the point (3 x f64), its distance (f64) and the parallel collection's
/// chunk buffers.
const COMPARE_BYTES_PER_SAMPLE: u64 = 48;
/// Per triangle of either (already read) mesh in `compare`: its bounding-volume hierarchy, the edge
/// maps of the topology and the vertex distances (fitted to measured peaks:
/// docs/decisions/0028-memory-budget-estimates.md).
const COMPARE_BYTES_PER_TRIANGLE: u64 = 300;

/// Area samples `compare` places on a surface of `area_mm2` (as `metrics::compare_meshes` counts them).
pub fn compare_sample_count(area_mm2: f64, options: &crate::metrics::CompareOptions) -> u64 {
    let wanted = (area_mm2 * options.samples_per_mm2).ceil();
    let wanted = if wanted.is_finite() { wanted } else { 0.0 };
    (wanted.max(options.min_samples as f64).min(u64::MAX as f64) as u64)
        .clamp(1, options.max_samples.max(1) as u64)
}

/// Refuses a comparison whose area samples on both surfaces would take more than `budget_bytes`,
/// naming the sample counts and the options that lower them.
pub fn check_compare_budget(
    mesh: &crate::mesh::Mesh,
    truth: &crate::mesh::Mesh,
    options: &crate::metrics::CompareOptions,
    budget_bytes: u64,
    observer: &dyn Progress,
) -> Result<()> {
    let mesh_samples = compare_sample_count(mesh.area_mm2(), options);
    let truth_samples = compare_sample_count(truth.area_mm2(), options);
    let samples = mesh_samples
        .saturating_add(truth_samples)
        .saturating_mul(COMPARE_BYTES_PER_SAMPLE);
    let meshes = ((mesh.triangles.len() + truth.triangles.len()) as u64)
        .saturating_mul(COMPARE_BYTES_PER_TRIANGLE);
    let resident = resident_bytes();
    let need = resident.saturating_add(samples).saturating_add(meshes);
    check_need(need, budget_bytes, observer, || {
        Phrase::new(format!(
            "compare would place {mesh_samples} + {truth_samples} area samples at {} per mm^2 and \
             need about {} ({} resident with the meshes, samples {}, mesh search structures {}) but \
             the memory budget is {}: lower ",
            options.samples_per_mm2,
            mb(need),
            mb(resident),
            mb(samples),
            mb(meshes),
            mb(budget_bytes)
        ))
        .option(OptionName::CompareSamplesPerMm2)
        .text(" or ")
        .option(OptionName::CompareMaxSamples)
        .text(", or ")
        .then(or_raise_budget())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compare_samples_follow_the_density_within_the_cap() {
        let options = crate::metrics::CompareOptions {
            samples_per_mm2: 1e300,
            max_samples: usize::MAX,
            ..crate::metrics::CompareOptions::default()
        };
        assert_eq!(compare_sample_count(100.0, &options), u64::MAX);
        let default = crate::metrics::CompareOptions::default();
        assert_eq!(
            compare_sample_count(1e12, &default),
            default.max_samples as u64
        );
    }

    /// Keeps every estimate it is told.
    #[derive(Default)]
    struct Estimates(std::sync::Mutex<Vec<u64>>);

    impl Progress for Estimates {
        fn start(&self, _stage: &str, _total: u64) {}
        fn advance(&self, _done: u64) {}
        fn finish(&self) {}
        fn memory_estimate(&self, bytes: u64) {
            self.0.lock().unwrap().push(bytes);
        }
    }

    #[test]
    fn every_check_tells_its_observer_the_estimate_it_compared() {
        let estimates = Estimates::default();
        check_need(5, 10, &estimates, || unreachable!()).unwrap();
        check_need(30, 10, &estimates, || Phrase::new("over")).unwrap_err();
        check_surface_budget(1000, 0.5, 0, &estimates).unwrap_err();
        let told = estimates.0.lock().unwrap().clone();
        assert_eq!(told[..2], [5, 30]);
        assert!(told[2] >= 1000 * SURFACE_BYTES_PER_SEED, "{told:?}");
    }

    #[test]
    fn an_estimate_past_the_budget_is_refused_with_the_message() {
        assert!(check_need(10, 10, &crate::progress::NoProgress, || unreachable!()).is_ok());
        let e =
            check_need(11, 10, &crate::progress::NoProgress, || Phrase::new("over")).unwrap_err();
        assert!(matches!(
            e,
            Error::OverBudget { needed_bytes: 11, budget_bytes: 10, budget_option: Some(OptionName::MemoryBudget), ref message }
                if message.to_string() == "over"
        ));
    }

    #[test]
    fn kept_pixels_are_counted_once_per_bin() {
        let extract = crate::pipeline::ExtractOptions::default();
        let options = crate::pipeline::fit_plan(&extract);
        let counts = SegmentedCounts {
            frame_pixels: 400,
            kept_pixels: 400,
            bin_px: [2, 2],
            bone_sweep: false,
        };
        let e = estimate_extract_memory(counts, options);
        assert_eq!(e.samples, 100 * SAMPLE_BYTES);
        assert_eq!(e.fit, fit_bytes(100, options.fit));
        assert_eq!(e.normalised_frames, 0);
        let bone = estimate_extract_memory(
            SegmentedCounts {
                bone_sweep: true,
                ..counts
            },
            options,
        );
        assert_eq!(bone.normalised_frames, 400);
    }

    #[test]
    fn direct_fit_is_quadratic_fast_is_linear() {
        let mut o = crate::rbf::FitOptions {
            solver: SolverChoice::Direct,
            ..Default::default()
        };
        assert_eq!(fit_bytes(996, &o), 1000 * 1000 * 16);
        o.solver = SolverChoice::Fast;
        assert_eq!(fit_bytes(1000, &o), 1000 * FAST_FIT_BYTES_PER_CENTRE);
        o.solver = SolverChoice::Auto;
        assert_eq!(fit_bytes(o.direct_max_points as u64, &o), {
            let n = o.direct_max_points as u64 + 4;
            n * n * 16
        });
        assert_eq!(
            fit_bytes(1_000_000, &o),
            1_000_000 * PU_FIT_BYTES_PER_SAMPLE
        );
    }
}
