//! Memory budget of `extract`: an up-front estimate of the big buffers, refused with
//! [`Error::ResourceLimit`] saying what would fit (fewer samples, coarser resolution) instead of running
//! out of memory half-way. The voxel route has its own estimate (`voxel::estimated_memory_bytes`).

use std::path::Path;

use glam::DVec3;

use crate::io::{self, Calibration, TrackedSequence};
use crate::pipeline::ExtractOptions;
use crate::rbf::SolverChoice;
use crate::{Error, Result};

/// Fraction of the machine's memory a run may plan to use by default.
const DEFAULT_FRACTION: f64 = 0.5;
/// Budget when the machine's memory cannot be read.
const FALLBACK_BUDGET_BYTES: u64 = 8 << 30;
/// Per kept pixel before decimation: position (3 x f64), intensity (f64), frame/pixel index.
const SAMPLE_BYTES: u64 = 48;
/// Band mask and smoothed frame per pixel while segmenting (one byte + one f32).
const SEGMENT_BYTES_PER_PIXEL: u64 = 5;
/// Fast solver per centre: treecode nodes and moments, neighbour lists, Schwarz blocks, Krylov basis.
const FAST_FIT_BYTES_PER_CENTRE: u64 = 4096;
/// Surface lattice per node: the function value (f64) and crossing flags.
const LATTICE_BYTES_PER_NODE: u64 = 16;

/// Half of `MemTotal` from `/proc/meminfo`, or 8 GiB where that is unavailable.
pub fn default_memory_budget_bytes() -> u64 {
    std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|text| {
            let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
            let kib: u64 = line["MemTotal:".len()..]
                .trim()
                .trim_end_matches("kB")
                .trim()
                .parse()
                .ok()?;
            Some((kib as f64 * 1024.0 * DEFAULT_FRACTION) as u64)
        })
        .unwrap_or(FALLBACK_BUDGET_BYTES)
}

/// The big buffers of one extract run, in bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ExtractMemoryEstimate {
    /// The decoded pixels (already in memory when the estimate is made).
    pub sequence: u64,
    /// Band masks and smoothed frames.
    pub segment: u64,
    /// Samples of all kept pixels before decimation (upper bound: every pixel kept).
    pub samples: u64,
    /// The fit: dense matrix (direct solver) or treecode/preconditioner (fast solver).
    pub fit: u64,
    /// The surface lattice over the frames' bounding box.
    pub lattice: u64,
}

impl ExtractMemoryEstimate {
    pub fn total(&self) -> u64 {
        self.sequence
            .saturating_add(self.segment)
            .saturating_add(self.samples)
            .saturating_add(self.fit)
            .saturating_add(self.lattice)
    }
}

fn fit_bytes(samples: u64, options: &ExtractOptions) -> u64 {
    let direct = match options.fit.solver {
        SolverChoice::Direct => true,
        SolverChoice::Fast | SolverChoice::PartitionOfUnity => false,
        SolverChoice::Auto => samples <= options.fit.direct_max_points as u64,
    };
    if direct {
        // The (n + 4)^2 system in f64 and its LU factors in place.
        (samples + 4).saturating_mul(samples + 4).saturating_mul(8)
    } else {
        samples.saturating_mul(FAST_FIT_BYTES_PER_CENTRE)
    }
}

fn lattice_nodes(extent_mm: DVec3, resolution_mm: f64) -> u64 {
    let per_axis = |e: f64| ((e / resolution_mm).ceil().max(0.0) + 1.0).min(1e12) as u64;
    per_axis(extent_mm.x)
        .saturating_mul(per_axis(extent_mm.y))
        .saturating_mul(per_axis(extent_mm.z))
}

/// Extent (mm) of the frames' bounding box, or `None` when no frame can be placed (the pipeline then
/// reports why).
fn frames_extent_mm(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
) -> Option<DVec3> {
    let poses = io::resolve_poses(
        sequence,
        calibration,
        options.reference,
        Path::new("<sequence>"),
    )
    .ok()?;
    let (lo, hi) = io::world_bounds(sequence, &poses.poses)?;
    Some(hi - lo)
}

/// Estimates the big buffers of `pipeline::extract` on this sequence with these options.
pub fn estimate_extract_memory(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
) -> ExtractMemoryEstimate {
    let pixels = (sequence.width as u64)
        .saturating_mul(sequence.height as u64)
        .saturating_mul(sequence.frames.len() as u64);
    let samples_kept = (options.max_samples as u64).min(pixels);
    let lattice = frames_extent_mm(sequence, calibration, options)
        .map(|e| lattice_nodes(e, options.surface.resolution_mm))
        .unwrap_or(0)
        .saturating_mul(LATTICE_BYTES_PER_NODE);
    ExtractMemoryEstimate {
        sequence: (sequence.pixels.len() as u64)
            .saturating_mul(sequence.pixels.element_type().size_bytes() as u64),
        segment: pixels.saturating_mul(SEGMENT_BYTES_PER_PIXEL),
        samples: pixels.saturating_mul(SAMPLE_BYTES),
        fit: fit_bytes(samples_kept, options),
        lattice,
    }
}

fn mb(bytes: u64) -> String {
    format!("{:.0} MB", bytes as f64 / 1e6)
}

/// Refuses up front when the estimate exceeds `budget_bytes`, naming the parts and what would fit.
pub fn check_extract_budget(
    sequence: &TrackedSequence,
    calibration: Option<&Calibration>,
    options: &ExtractOptions,
    budget_bytes: u64,
) -> Result<()> {
    let e = estimate_extract_memory(sequence, calibration, options);
    if e.total() <= budget_bytes {
        return Ok(());
    }
    let fixed = e
        .sequence
        .saturating_add(e.segment)
        .saturating_add(e.samples);
    let mut advice = Vec::new();
    if fixed >= budget_bytes {
        advice.push(
            "the sequence itself is too large for this budget: split it (fewer frames) or raise --memory-budget"
                .to_string(),
        );
    } else {
        let room = budget_bytes - fixed;
        if e.fit > room / 2 {
            // Largest sample count whose fit takes at most half of what is left.
            let mut lo = 0u64;
            let mut hi = options.max_samples as u64;
            while lo < hi {
                let mid = (lo + hi).div_ceil(2);
                if fit_bytes(mid, options) <= room / 2 {
                    lo = mid;
                } else {
                    hi = mid - 1;
                }
            }
            advice.push(format!("--max-samples {lo} or fewer"));
        }
        if e.lattice > room / 2 {
            let scale = (e.lattice as f64 / (room / 2).max(1) as f64).cbrt();
            let coarser = options.surface.resolution_mm * scale * 1.05;
            advice.push(format!("--resolution {coarser:.2} (mm) or coarser"));
        }
        if advice.is_empty() {
            advice.push("fewer samples (--max-samples) and a coarser --resolution".into());
        }
    }
    Err(Error::ResourceLimit(format!(
        "extract would need about {} (pixels {}, segmentation {}, samples {}, fit {}, surface lattice {}) \
         but the memory budget is {}; would fit: {}",
        mb(e.total()),
        mb(e.sequence),
        mb(e.segment),
        mb(e.samples),
        mb(e.fit),
        mb(e.lattice),
        mb(budget_bytes),
        advice.join("; ")
    )))
}

/// Per area sample of `compare`: the point (3 x f64), its distance (f64) and the parallel collection's
/// chunk buffers.
const COMPARE_BYTES_PER_SAMPLE: u64 = 48;
/// Per triangle of either mesh in `compare`: the mesh, its bounding-volume hierarchy, the edge maps of
/// the topology and the vertex distances (fitted to measured peaks: docs/decisions/0028-memory-budget-estimates.md).
const COMPARE_BYTES_PER_TRIANGLE: u64 = 350;

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
) -> Result<()> {
    let mesh_samples = compare_sample_count(mesh.area_mm2(), options);
    let truth_samples = compare_sample_count(truth.area_mm2(), options);
    let samples = mesh_samples
        .saturating_add(truth_samples)
        .saturating_mul(COMPARE_BYTES_PER_SAMPLE);
    let meshes = ((mesh.triangles.len() + truth.triangles.len()) as u64)
        .saturating_mul(COMPARE_BYTES_PER_TRIANGLE);
    let need = samples.saturating_add(meshes);
    if need <= budget_bytes {
        return Ok(());
    }
    Err(Error::ResourceLimit(format!(
        "compare would place {mesh_samples} + {truth_samples} area samples at {} per mm^2 and \
         need about {} (samples {}, meshes {}) but the memory budget is {}: lower \
         --samples-per-mm2 or --max-samples, or raise --memory-budget",
        options.samples_per_mm2,
        mb(need),
        mb(samples),
        mb(meshes),
        mb(budget_bytes)
    )))
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

    #[test]
    fn default_budget_is_positive_and_below_total_memory() {
        let b = default_memory_budget_bytes();
        assert!(b >= 64 << 20, "{b}");
    }

    #[test]
    fn lattice_nodes_counts_both_ends() {
        assert_eq!(
            lattice_nodes(DVec3::new(10.0, 10.0, 10.0), 1.0),
            11 * 11 * 11
        );
        assert_eq!(
            lattice_nodes(DVec3::new(1e300, 1e300, 1e300), 1e-300),
            u64::MAX
        );
    }

    #[test]
    fn direct_fit_is_quadratic_fast_is_linear() {
        let mut o = ExtractOptions::default();
        o.fit.solver = SolverChoice::Direct;
        assert_eq!(fit_bytes(996, &o), 1000 * 1000 * 8);
        o.fit.solver = SolverChoice::Fast;
        assert_eq!(fit_bytes(1000, &o), 1000 * FAST_FIT_BYTES_PER_CENTRE);
    }
}
