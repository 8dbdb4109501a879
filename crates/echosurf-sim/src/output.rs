//! Files of a simulation: the PLUS sequence and device set, the true surfaces, a JSON description, and a
//! preview montage.

use std::path::{Path, PathBuf};

use glam::DVec3;

use super::phantom::Phantom;
use super::{Simulation, SimulationOptions};
use echosurf::io::sequence::mat4_to_row_major;
use echosurf::mesh::Mesh;
use echosurf::progress::Progress;
use echosurf::surface::{FnField, SurfaceDomain, SurfaceOptions, extract_surfaces};
use echosurf::{Error, Result};

/// Paths written by [`write_simulation`].
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SimulationFiles {
    pub sequence: PathBuf,
    pub calibration: PathBuf,
    /// `truth.ply` (all true surfaces in one mesh) first, then one file per surface when there are several.
    pub truth: Vec<PathBuf>,
    pub description: PathBuf,
}

/// The true surfaces: the mesh phantom's own mesh, or the zero level of each analytic surface extracted on
/// a full lattice (outward normals: the field handed to the surfacer is minus the signed distance, and
/// the surfacer orients normals toward lower values).
pub fn truth_meshes(
    phantom: &dyn Phantom,
    resolution_mm: f64,
    progress: &dyn Progress,
) -> Result<Vec<(String, Mesh)>> {
    if let Some(meshes) = phantom.exact_meshes() {
        return Ok(meshes);
    }
    let (lo, hi) = phantom.bounds();
    let margin = DVec3::splat(2.0 * resolution_mm + 1.0);
    let domain = SurfaceDomain {
        bounds_min_mm: lo - margin,
        bounds_max_mm: hi + margin,
        seeds: Vec::new(),
        trust_points: Vec::new(),
    };
    // No trust points: the whole lattice is evaluated, nothing is clipped.
    let options = SurfaceOptions {
        resolution_mm,
        ..SurfaceOptions::default()
    };
    let surfaces = phantom.surfaces();
    progress.start("truth", surfaces.len() as u64);
    let mut meshes = Vec::with_capacity(surfaces.len());
    for (k, (name, sdf)) in surfaces.into_iter().enumerate() {
        let field = FnField(|p: DVec3| {
            let (d, g) = sdf(p);
            (-d, -g)
        });
        let mut extracted = extract_surfaces(&field, &[0.0], &domain, &options)?;
        let mesh = extracted.pop().unwrap_or_default();
        meshes.push((name, mesh));
        progress.advance(k as u64 + 1);
    }
    progress.finish();
    Ok(meshes)
}

/// All truth surfaces in one mesh.
pub fn merged_truth(truth: &[(String, Mesh)]) -> Mesh {
    Mesh::merged(truth.iter().map(|(_, m)| m))
}

/// The file names a simulation writes into its folder.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SimulationNames {
    /// Base name of the sequence (`NAME.mha`) and calibration (`NAME_config.xml`).
    pub name: String,
    /// Prefix of the truth meshes and the description: empty (`truth.ply`, `phantom.json`) or
    /// `NAME_` (`NAME_truth.ply`, `NAME_phantom.json`), so runs of other names share a folder.
    pub truth_prefix: String,
}

impl SimulationNames {
    /// `NAME.mha`, `NAME_config.xml`, `truth.ply`, `phantom.json`.
    pub fn plain(name: &str) -> SimulationNames {
        SimulationNames {
            name: name.to_string(),
            truth_prefix: String::new(),
        }
    }

    /// `NAME.mha`, `NAME_config.xml`, `NAME_truth.ply`, `NAME_phantom.json`.
    pub fn prefixed(name: &str) -> SimulationNames {
        SimulationNames {
            name: name.to_string(),
            truth_prefix: format!("{name}_"),
        }
    }

    pub fn sequence(&self, dir: &Path) -> PathBuf {
        dir.join(format!("{}.mha", self.name))
    }

    pub fn calibration(&self, dir: &Path) -> PathBuf {
        dir.join(format!("{}_config.xml", self.name))
    }

    /// All true surfaces in one mesh.
    pub fn truth(&self, dir: &Path) -> PathBuf {
        dir.join(format!("{}truth.ply", self.truth_prefix))
    }

    /// One true surface, written when there are several.
    pub fn truth_surface(&self, dir: &Path, surface: &str) -> PathBuf {
        dir.join(format!("{}truth_{surface}.ply", self.truth_prefix))
    }

    pub fn description(&self, dir: &Path) -> PathBuf {
        dir.join(format!("{}phantom.json", self.truth_prefix))
    }

    /// Every file written for these surfaces, in writing order.
    pub fn files(&self, dir: &Path, surfaces: &[String]) -> Vec<PathBuf> {
        let mut files = vec![self.sequence(dir), self.calibration(dir), self.truth(dir)];
        if surfaces.len() > 1 {
            files.extend(surfaces.iter().map(|s| self.truth_surface(dir, s)));
        }
        files.push(self.description(dir));
        files
    }
}

/// Writes `NAME.mha`, `NAME_config.xml`, `truth.ply` (+ `truth_NAME.ply` per surface when there are
/// several) and `phantom.json` into `dir` (created if missing); the truth meshes tagged RAS.
pub fn write_simulation(
    dir: &Path,
    name: &str,
    sim: &Simulation,
    options: &SimulationOptions,
) -> Result<SimulationFiles> {
    write_simulation_as(
        dir,
        &SimulationNames::plain(name),
        sim,
        options,
        echosurf::io::Space::Ras,
    )
}

/// [`write_simulation`] with the file names of `names` and the truth meshes written in `truth_space`.
pub fn write_simulation_as(
    dir: &Path,
    names: &SimulationNames,
    sim: &Simulation,
    options: &SimulationOptions,
    truth_space: echosurf::io::Space,
) -> Result<SimulationFiles> {
    let name = names.name.as_str();
    if name.is_empty() || name.contains(['/', '\\']) {
        return Err(Error::InvalidInput(format!(
            "simulation name {name:?} must be a plain file name"
        )));
    }
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let sequence = names.sequence(dir);
    echosurf::io::write_sequence(&sequence, &sim.sequence, options.compress)?;
    let calibration = names.calibration(dir);
    echosurf::io::write_calibration(&calibration, &sim.calibration_written)?;
    let mut truth = vec![names.truth(dir)];
    echosurf::io::write_mesh_in(&truth[0], &merged_truth(&sim.truth), truth_space)?;
    if sim.truth.len() > 1 {
        for (surface, mesh) in &sim.truth {
            let path = names.truth_surface(dir, surface);
            echosurf::io::write_mesh_in(&path, mesh, truth_space)?;
            truth.push(path);
        }
    }
    let description = names.description(dir);
    let json = description_json(name, sim, options, &truth, truth_space);
    let text = serde_json::to_string_pretty(&json)
        .map_err(|e| Error::InvalidInput(format!("phantom.json: {e}")))?;
    echosurf::io::atomic::write_bytes_atomic(&description, (text + "\n").as_bytes())?;
    Ok(SimulationFiles {
        sequence,
        calibration,
        truth,
        description,
    })
}

fn description_json(
    name: &str,
    sim: &Simulation,
    options: &SimulationOptions,
    truth_files: &[PathBuf],
    truth_space: echosurf::io::Space,
) -> serde_json::Value {
    let file_name = |p: &PathBuf| {
        p.file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    serde_json::json!({
        "generator": concat!("echosurf ", env!("CARGO_PKG_VERSION"), " simulate"),
        "name": name,
        "phantom": options.phantom.name(),
        "seed": options.seed,
        "frames": sim.sequence.frames.len(),
        "sweeps": sim.sweeps.iter().map(|r| [r.start, r.end]).collect::<Vec<_>>(),
        "sweep_plans": sim.sweep_specs,
        "suggested_iso": sim.suggested_iso,
        "background_level": sim.background_level,
        "boundary_level": sim.boundary_level,
        "world_frame": "Tracker (= phantom frame at t = 0), mm",
        "coordinates": {"frame": "Tracker", "space": truth_space},
        "phantom_bounds_mm": [sim.phantom_bounds.0.to_array(), sim.phantom_bounds.1.to_array()],
        "image_to_probe_true": mat4_to_row_major(&sim.calibration_true.image_to_probe),
        "image_to_probe_written": mat4_to_row_major(&sim.calibration_written.image_to_probe),
        "truth_files": truth_files.iter().map(file_name).collect::<Vec<_>>(),
        "truth_surfaces": sim.truth.iter().map(|(n, m)| serde_json::json!({
            "name": n,
            "vertices": m.vertices.len(),
            "triangles": m.triangles.len(),
            "area_mm2": m.area_mm2(),
        })).collect::<Vec<_>>(),
        "options": options,
    })
}

/// Writes a montage of up to `count` frames spread evenly over the sweeps (4 per row, 4 px gaps) as an
/// 8-bit grey PNG.
pub fn write_preview(path: &Path, sim: &Simulation, count: usize) -> Result<()> {
    let seq = &sim.sequence;
    let n = seq.frames.len();
    let echosurf::io::PixelData::U8(pixels) = &seq.pixels else {
        return Err(Error::InvalidInput("preview needs 8-bit frames".into()));
    };
    if n == 0 || count == 0 {
        return Err(Error::InvalidInput("preview: no frames to show".into()));
    }
    // Evenly inside each sweep (its first and last frames are usually past the object's ends).
    let sweeps: Vec<std::ops::Range<usize>> = if sim.sweeps.is_empty() {
        std::iter::once(0..n).collect()
    } else {
        sim.sweeps.clone()
    };
    let per_sweep = count.div_ceil(sweeps.len()).max(1);
    let mut picks: Vec<usize> = Vec::new();
    for sweep in &sweeps {
        let len = sweep.end.saturating_sub(sweep.start);
        for k in 0..per_sweep.min(len) {
            picks.push(sweep.start + (k + 1) * len / (per_sweep.min(len) + 1));
        }
    }
    picks.truncate(count);
    picks.retain(|&f| f < n);
    if picks.is_empty() {
        return Err(Error::InvalidInput("preview: no frames to show".into()));
    }
    let shown = picks.len();
    let columns = shown.min(4);
    let rows = shown.div_ceil(columns);
    let gap = 4;
    let (w, h) = (seq.width, seq.height);
    let total_w = columns * w + (columns + 1) * gap;
    let total_h = rows * h + (rows + 1) * gap;
    let mut image = vec![40u8; total_w * total_h];
    for (k, &frame) in picks.iter().enumerate() {
        let (cx, cy) = (k % columns, k / columns);
        let (x0, y0) = (gap + cx * (w + gap), gap + cy * (h + gap));
        for v in 0..h {
            let src = &pixels[frame * w * h + v * w..frame * w * h + (v + 1) * w];
            let dst = (y0 + v) * total_w + x0;
            image[dst..dst + w].copy_from_slice(src);
        }
    }
    echosurf::io::atomic::write_png_atomic(
        path,
        total_w as u32,
        total_h as u32,
        png::ColorType::Grayscale,
        &image,
    )
}
