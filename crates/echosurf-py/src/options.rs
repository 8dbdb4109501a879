//! `extract`'s options from Python: the defaults, then the `config=` TOML (as `echosurf extract
//! --print-config` writes it), then the user-tier keywords; validated by the library, with errors that
//! name the keyword or the file.

use std::path::Path;

use echosurf::pipeline::{ExtractConfig, Tuning, UserOptions};
use pyo3::PyErr;
use pyo3::exceptions::{PyTypeError, PyValueError};
use serde_json::{Map, Value};

use crate::EchosurfError;

/// What the `config=` TOML holds: both tiers, and the CLI's `[outputs]` (refused when it sets a path:
/// the Python `extract` writes no files).
#[derive(Debug, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
struct ConfigToml {
    user: UserOptions,
    tuning: Tuning,
    outputs: Map<String, Value>,
}

impl Default for ConfigToml {
    fn default() -> Self {
        let ExtractConfig { user, tuning } = ExtractConfig::default();
        ConfigToml {
            user,
            tuning,
            outputs: Map::new(),
        }
    }
}

/// The keys of the user tier (`iso`, `smoothing_mm`, ...), as the TOML's `[user]` spells them.
pub fn user_option_names() -> Vec<String> {
    match serde_json::to_value(UserOptions::default()) {
        Ok(Value::Object(map)) => map.keys().cloned().collect(),
        _ => Vec::new(),
    }
}

/// Reads the `config=` TOML: unknown keys and bad values are errors naming the file and the key.
fn read_config(path: &Path) -> Result<ExtractConfig, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let text = String::from_utf8_lossy(&bytes);
    let looks_xml = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("xml"))
        || text
            .trim_start_matches('\u{feff}')
            .trim_start()
            .starts_with('<');
    if looks_xml {
        return Err(format!(
            "{} is a PLUS device-set XML; give it as the calibration (config= takes the TOML that \
             `echosurf extract --print-config` writes)",
            path.display()
        ));
    }
    let file: ConfigToml = toml::from_str(&text)
        .map_err(|e| format!("{}: {}", path.display(), e.to_string().trim_end()))?;
    if let Some(key) = file.outputs.keys().next() {
        return Err(format!(
            "{}: outputs.{key}: the Python extract writes no files (save the model with \
             echosurf.fit(...).save, the mesh with your own writer)",
            path.display()
        ));
    }
    let config = ExtractConfig {
        user: file.user,
        tuning: file.tuning,
    };
    config
        .validate()
        .map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(config)
}

/// The option set: defaults, then `config`, then the user-tier keywords of `options_json` (a JSON
/// object), then `memory_budget_mb`; validated. An unknown keyword is a `TypeError`, a bad value a
/// `ValueError` naming the keyword, a bad config file an `EchosurfError` naming the file.
pub fn build_config(
    config: Option<&Path>,
    options_json: &str,
    memory_budget_mb: Option<f64>,
) -> Result<ExtractConfig, PyErr> {
    let mut options = match config {
        Some(path) => read_config(path).map_err(EchosurfError::new_err)?,
        None => ExtractConfig::default(),
    };
    let overrides: Map<String, Value> = serde_json::from_str(options_json)
        .map_err(|e| PyValueError::new_err(format!("options: {e}")))?;
    let mut user = serde_json::to_value(&options.user)
        .map_err(|e| PyValueError::new_err(format!("options: {e}")))?;
    for (key, value) in &overrides {
        let Some(object) = user.as_object_mut() else {
            break;
        };
        if !object.contains_key(key) {
            return Err(PyTypeError::new_err(format!(
                "extract() got an unexpected keyword argument '{key}' (options: {}, and config, \
                 init, space, memory_budget_mb, progress)",
                user_option_names().join(", ")
            )));
        }
        object.insert(key.clone(), value.clone());
        // One key at a time, so that a value of the wrong kind is reported with its keyword.
        serde_json::from_value::<UserOptions>(user.clone())
            .map_err(|e| PyValueError::new_err(format!("{key}: {e}")))?;
    }
    options.user =
        serde_json::from_value(user).map_err(|e| PyValueError::new_err(format!("options: {e}")))?;
    if let Some(mb) = memory_budget_mb {
        options.tuning.memory_budget_mb = Some(mb);
    }
    options.validate().map_err(|e| {
        let keyword = e
            .field
            .strip_prefix("user.")
            .filter(|k| overrides.contains_key(*k));
        match (keyword, config) {
            (Some(keyword), _) => PyValueError::new_err(format!("{keyword} {}", e.problem)),
            _ if e.field == "tuning.memory_budget_mb" && memory_budget_mb.is_some() => {
                PyValueError::new_err(format!("memory_budget_mb {}", e.problem))
            }
            (None, Some(path)) => EchosurfError::new_err(format!("{}: {e}", path.display())),
            (None, None) => PyValueError::new_err(e.to_string()),
        }
    })?;
    Ok(options)
}

/// `memory_budget_mb` for `fit`: a positive number of MB, or half the machine's memory.
pub fn memory_budget_bytes(mb: Option<f64>) -> Result<u64, PyErr> {
    match mb {
        None => Ok(echosurf::budget::default_memory_budget_bytes()),
        Some(mb) if mb.is_finite() && mb > 0.0 => Ok((mb * 1e6) as u64),
        Some(mb) => Err(PyValueError::new_err(format!(
            "memory_budget_mb must be a positive number of MB, got {mb}"
        ))),
    }
}
