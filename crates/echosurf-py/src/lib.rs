//! The native part of the `echosurf` Python package: thin pyo3 wrappers over the library's public API
//! (sequence reading, the extract pipeline, the RBF fit). The Python layer in `python/echosurf`
//! converts arguments and shapes the results; everything here releases the GIL while it computes.

mod options;
mod progress;

use std::path::{Path, PathBuf};

use echosurf::io::{self, PixelData, Space, TrackedSequence};
use echosurf::pipeline::{self, ExtractOutput, Method};
use echosurf::rbf::{self, FitOptions, RbfModel, SolverChoice};
use echosurf::segment::InitialBand;
use glam::DVec3;
use numpy::{
    AllowTypeChange, IntoPyArray, PyArrayLike2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2,
};
use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use progress::PyProgress;

create_exception!(
    _echosurf,
    EchosurfError,
    PyException,
    "An error of the echosurf library: a bad or unreadable file (the message names it), an option \
     out of range, a failed fit or a memory budget that would be exceeded."
);

/// A library error as [`EchosurfError`], with the library's message (which names the file).
fn library_error(error: impl std::fmt::Display) -> PyErr {
    EchosurfError::new_err(error.to_string())
}

/// The pixel array of a sequence as numpy, shape (frames, height, width) or (frames, height, width,
/// channels) in the file's element type.
fn frames_array<'py>(py: Python<'py>, sequence: TrackedSequence) -> PyResult<Bound<'py, PyAny>> {
    let (n, h, w, c) = (
        sequence.frames.len(),
        sequence.height,
        sequence.width,
        sequence.channels.max(1),
    );
    let shape: Vec<usize> = if sequence.pixels.is_empty() {
        vec![n, 0, 0]
    } else if c == 1 {
        vec![n, h, w]
    } else {
        vec![n, h, w, c]
    };
    Ok(match sequence.pixels {
        PixelData::U8(v) => v.into_pyarray(py).reshape(shape)?.into_any(),
        PixelData::I8(v) => v.into_pyarray(py).reshape(shape)?.into_any(),
        PixelData::U16(v) => v.into_pyarray(py).reshape(shape)?.into_any(),
        PixelData::I16(v) => v.into_pyarray(py).reshape(shape)?.into_any(),
        PixelData::F32(v) => v.into_pyarray(py).reshape(shape)?.into_any(),
    })
}

/// Reads a tracked sequence (`.mha`, `.mhd`, `.igs.nrrd`) into a dict of numpy arrays: `frames`,
/// `timestamps_s`, `image_valid`, `transforms` (name -> (frames, 4, 4)), `transform_valid`
/// (name -> (frames,)), and `orientation`, `width`, `height`, `channels`, `element_type`.
#[pyfunction]
fn read_sequence<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyDict>> {
    let sequence = py
        .detach(|| io::read_sequence(&path))
        .map_err(library_error)?;
    let out = PyDict::new(py);
    let n = sequence.frames.len();
    let timestamps: Vec<f64> = sequence
        .frames
        .iter()
        .map(|f| f.timestamp_s.unwrap_or(f64::NAN))
        .collect();
    let image_valid: Vec<bool> = sequence.frames.iter().map(|f| f.image_valid).collect();
    let transforms = PyDict::new(py);
    let transform_valid = PyDict::new(py);
    for name in sequence.transform_names() {
        let mut matrices = Vec::with_capacity(n * 16);
        let mut valid = Vec::with_capacity(n);
        for frame in &sequence.frames {
            match frame.transforms.get(&name) {
                Some(t) => {
                    matrices.extend(io::sequence::mat4_to_row_major(&t.matrix));
                    valid.push(t.valid);
                }
                None => {
                    matrices.extend([f64::NAN; 16]);
                    valid.push(false);
                }
            }
        }
        transforms.set_item(&name, matrices.into_pyarray(py).reshape([n, 4, 4])?)?;
        transform_valid.set_item(&name, valid.into_pyarray(py))?;
    }
    out.set_item("timestamps_s", timestamps.into_pyarray(py))?;
    out.set_item("image_valid", image_valid.into_pyarray(py))?;
    out.set_item("transforms", transforms)?;
    out.set_item("transform_valid", transform_valid)?;
    out.set_item("orientation", &sequence.orientation)?;
    out.set_item("width", sequence.width)?;
    out.set_item("height", sequence.height)?;
    out.set_item("channels", sequence.channels)?;
    out.set_item(
        "element_type",
        sequence.pixels.element_type().metaimage_name(),
    )?;
    out.set_item("frames", frames_array(py, sequence)?)?;
    Ok(out)
}

/// The names of the user-tier options `extract` takes as keywords.
#[pyfunction]
fn user_option_names() -> Vec<String> {
    options::user_option_names()
}

/// One surface for Python: (level, vertices (N, 3) float64, faces (M, 3) int32, normals (N, 3) or (0, 3)).
type SurfaceTuple<'py> = (f64, Bound<'py, PyAny>, Bound<'py, PyAny>, Bound<'py, PyAny>);

/// `rows` of three as an (n, 3) numpy array.
fn rows3<'py, T: numpy::Element>(
    py: Python<'py>,
    flat: Vec<T>,
    rows: usize,
) -> PyResult<Bound<'py, PyAny>> {
    Ok(flat.into_pyarray(py).reshape([rows, 3])?.into_any())
}

/// Runs the pipeline as `echosurf extract` does: the options (defaults, then `config` TOML, then the
/// user-tier `options_json` object), the checks that need sequence and calibration, then
/// `pipeline::extract`. Returns the surfaces in `space` and the report JSON the CLI's `--report` writes.
#[pyfunction]
#[pyo3(signature = (sequence_path, calibration_path, options_json, config=None, init=None, space="ras", memory_budget_mb=None, progress=None))]
#[allow(clippy::too_many_arguments)]
fn extract<'py>(
    py: Python<'py>,
    sequence_path: PathBuf,
    calibration_path: PathBuf,
    options_json: &str,
    config: Option<PathBuf>,
    init: Option<PathBuf>,
    space: &str,
    memory_budget_mb: Option<f64>,
    progress: Option<Py<PyAny>>,
) -> PyResult<(Vec<SurfaceTuple<'py>>, String)> {
    let space = Space::parse(space)
        .ok_or_else(|| PyValueError::new_err(format!("space `{space}`: expected ras or lps")))?;
    let config = options::build_config(config.as_deref(), options_json, memory_budget_mb)?;
    let progress = PyProgress::new(progress);
    let output = progress.run(py, || {
        run_extract(
            &sequence_path,
            &calibration_path,
            init.as_deref(),
            &config,
            &progress,
        )
    })?;
    let report = report_json(&output, space).map_err(library_error)?;
    let surfaces = output
        .surfaces
        .into_iter()
        .map(|s| {
            let mesh = space.convert(&s.mesh);
            let vertices: Vec<f64> = mesh.vertices.iter().flat_map(|v| v.to_array()).collect();
            let normals: Vec<f64> = mesh.normals.iter().flat_map(|v| v.to_array()).collect();
            let faces: Vec<i32> = mesh
                .triangles
                .iter()
                .flatten()
                .map(|&i| i32::try_from(i).map_err(|_| library_error("mesh too large for int32")))
                .collect::<PyResult<_>>()?;
            Ok((
                s.level,
                rows3(py, vertices, mesh.vertices.len())?,
                rows3(py, faces, mesh.triangles.len())?,
                rows3(py, normals, mesh.normals.len())?,
            ))
        })
        .collect::<PyResult<Vec<_>>>()?;
    Ok((surfaces, report))
}

/// The work of [`extract`] without the GIL; errors carry the library's message and name the file.
fn run_extract(
    sequence_path: &Path,
    calibration_path: &Path,
    init: Option<&Path>,
    config: &pipeline::ExtractConfig,
    progress: &PyProgress,
) -> Result<ExtractOutput, String> {
    let sequence = io::read_sequence(sequence_path).map_err(|e| e.to_string())?;
    let calibration = io::read_calibration(calibration_path).map_err(|e| e.to_string())?;
    let init = match init {
        Some(path) => {
            InitialBand::load(path, sequence.width, sequence.height).map_err(|e| e.to_string())?
        }
        None => InitialBand::Auto,
    };
    io::check_clip_fits(&calibration, &sequence, calibration_path, sequence_path)
        .map_err(|e| e.to_string())?;
    let options = config.to_extract_options(init);
    let voxel = matches!(options.method, Method::Voxel(_));
    pipeline::extract(&sequence, Some(&calibration), &options, progress).map_err(|e| {
        let message = match e {
            echosurf::Error::ResourceLimit(m) if voxel => format!(
                "{m} (tuning.voxel.spacing_mm sets the spacing, memory_budget_mb the budget)"
            ),
            other => other.to_string(),
        };
        format!(
            "extracting a surface from {}: {message}",
            sequence_path.display()
        )
    })
}

/// The report as `extract --report` writes it: the library's report with the coordinates (tracking
/// frame and space) the meshes are in.
fn report_json(output: &ExtractOutput, space: Space) -> Result<String, String> {
    let mut value = serde_json::to_value(&output.report).map_err(|e| e.to_string())?;
    let object = value
        .as_object_mut()
        .ok_or("the report does not serialise to a JSON object")?;
    object.insert(
        "coordinates".into(),
        serde_json::json!({ "frame": output.report.parameters.world_frame, "space": space }),
    );
    serde_json::to_string(&value).map_err(|e| e.to_string())
}

/// (N, 3) float64 points as library points.
fn points_from(array: &PyReadonlyArray2<'_, f64>, what: &str) -> PyResult<Vec<DVec3>> {
    let view = array.as_array();
    if view.ncols() != 3 {
        return Err(PyValueError::new_err(format!(
            "{what} must have shape (N, 3), got {:?}",
            view.shape()
        )));
    }
    Ok(view
        .rows()
        .into_iter()
        .map(|r| DVec3::new(r[0], r[1], r[2]))
        .collect())
}

/// A fitted RBF model: evaluate it (values and gradients), save it as `.esrbf`, load one.
#[pyclass(module = "echosurf._echosurf", name = "Model", frozen)]
#[derive(Debug)]
struct PyModel {
    model: RbfModel,
    /// The fit report as JSON (empty for a loaded model).
    report_json: String,
}

#[pymethods]
impl PyModel {
    /// Values (N,) and gradients (N, 3) of the model at `points` (N, 3; any array-like of numbers).
    fn evaluate<'py>(
        &self,
        py: Python<'py>,
        points: PyArrayLike2<'py, f64, AllowTypeChange>,
    ) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>)> {
        let points = points_from(&points, "points")?;
        let (values, gradients) = py.detach(|| self.model.values_and_gradients(&points));
        let n = gradients.len();
        let gradients: Vec<f64> = gradients.iter().flat_map(|g| g.to_array()).collect();
        Ok((values.into_pyarray(py).into_any(), rows3(py, gradients, n)?))
    }

    /// Writes the model as `.esrbf` (what `echosurf fit --out` writes), atomically.
    fn save(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        py.detach(|| self.model.save(&path)).map_err(library_error)
    }

    /// Reads a `.esrbf` model (from `echosurf fit` or [`PyModel::save`]).
    #[staticmethod]
    fn load(py: Python<'_>, path: PathBuf) -> PyResult<PyModel> {
        let model = py.detach(|| RbfModel::load(&path)).map_err(library_error)?;
        Ok(PyModel {
            model,
            report_json: String::new(),
        })
    }

    /// The fit report as JSON (`echosurf fit --json`); empty for a loaded model.
    #[getter]
    fn report_json(&self) -> &str {
        &self.report_json
    }

    /// Number of centres (summed over the patches for partition of unity).
    #[getter]
    fn centres(&self) -> usize {
        self.model.centres().len()
    }

    /// The smoothing weight w (mm) the model was fitted with.
    #[getter]
    fn smoothing(&self) -> f64 {
        self.model.smoothing()
    }

    fn __repr__(&self) -> String {
        format!(
            "Model(centres={}, smoothing={}, partition_of_unity={})",
            self.model.centres().len(),
            self.model.smoothing(),
            self.model.is_partition_of_unity()
        )
    }
}

/// Fits the smoothing biharmonic RBF to `values` (N,) at `points` (N, 3), as `echosurf fit` does
/// (same options, same memory check).
#[pyfunction]
#[pyo3(signature = (points, values, smoothing, accuracy, solver="auto", max_centres=None, reduce=false, seed=0, memory_budget_mb=None, progress=None))]
#[allow(clippy::too_many_arguments)]
fn fit(
    py: Python<'_>,
    points: PyReadonlyArray2<'_, f64>,
    values: PyReadonlyArray1<'_, f64>,
    smoothing: f64,
    accuracy: f64,
    solver: &str,
    max_centres: Option<usize>,
    reduce: bool,
    seed: u64,
    memory_budget_mb: Option<f64>,
    progress: Option<Py<PyAny>>,
) -> PyResult<PyModel> {
    let points = points_from(&points, "points")?;
    let values: Vec<f64> = values.as_array().to_vec();
    if values.len() != points.len() {
        return Err(PyValueError::new_err(format!(
            "{} values for {} points",
            values.len(),
            points.len()
        )));
    }
    let solver = match solver.to_ascii_lowercase().as_str() {
        "auto" => SolverChoice::Auto,
        "direct" => SolverChoice::Direct,
        "pu" => SolverChoice::PartitionOfUnity,
        "fast" => SolverChoice::Fast,
        other => {
            return Err(PyValueError::new_err(format!(
                "solver `{other}`: expected auto, direct, pu or fast"
            )));
        }
    };
    let budget = options::memory_budget_bytes(memory_budget_mb)?;
    let options = FitOptions {
        smoothing,
        accuracy,
        max_centres,
        reduce_centres: reduce,
        seed,
        solver,
        ..FitOptions::default()
    };
    let progress = PyProgress::new(progress);
    let (model, report) = progress.run(py, || {
        echosurf::budget::check_fit_budget(values.len() as u64, &options, budget, &progress)
            .and_then(|()| rbf::fit(&points, &values, &options, &progress))
            .map_err(|e| format!("fitting {} points: {e}", points.len()))
    })?;
    let report_json = serde_json::to_string(&report).map_err(library_error)?;
    Ok(PyModel { model, report_json })
}

/// Checks the user-tier options JSON and config file as `extract` would, and returns the full option
/// set as the TOML `echosurf extract --print-config` writes (without its `[outputs]`).
#[pyfunction]
#[pyo3(signature = (options_json, config=None, memory_budget_mb=None))]
fn options_toml(
    options_json: &str,
    config: Option<PathBuf>,
    memory_budget_mb: Option<f64>,
) -> PyResult<String> {
    let config = options::build_config(config.as_deref(), options_json, memory_budget_mb)?;
    toml::to_string(&config).map_err(library_error)
}

/// The library version this package was built from.
const VERSION: &str = env!("CARGO_PKG_VERSION");

#[pymodule]
fn _echosurf(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("EchosurfError", m.py().get_type::<EchosurfError>())?;
    m.add("__version__", VERSION)?;
    m.add_class::<PyModel>()?;
    m.add_function(wrap_pyfunction!(read_sequence, m)?)?;
    m.add_function(wrap_pyfunction!(extract, m)?)?;
    m.add_function(wrap_pyfunction!(fit, m)?)?;
    m.add_function(wrap_pyfunction!(user_option_names, m)?)?;
    m.add_function(wrap_pyfunction!(options_toml, m)?)?;
    Ok(())
}
