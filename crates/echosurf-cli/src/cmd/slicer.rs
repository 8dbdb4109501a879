//! `echosurf slicer-module`: echosurf as a 3D Slicer command-line module (Slicer Execution Model).
//! `--xml` prints the module description; a run maps Slicer's arguments onto `echosurf extract` (its
//! checks, pipeline and writers, unchanged), prints `<filter-progress>` lines for Slicer's progress bar
//! and writes the results Slicer shows (triangles, pieces, seconds) to `--returnparameterfile`.
//! Slicer runs `EXE --xml` with no subcommand, so the `echosurf-slicer` binary forwards to this one.

use std::io::Write;
use std::path::PathBuf;
use std::sync::Mutex;

use clap::Parser;

/// Defaults shared by the description and the argument parser, so the two cannot disagree.
const DEFAULT_ISO: f64 = 60.0;
const DEFAULT_RESOLUTION_MM: f64 = 0.5;
const DEFAULT_MAX_SAMPLES: usize = 100_000;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Print the Slicer module description (XML) on stdout and nothing else.
    #[arg(long)]
    pub xml: bool,
    /// Tracked sequence (.mha / .igs.mha / .nrrd).
    #[arg(required_unless_present = "xml")]
    pub sequence: Option<PathBuf>,
    /// PLUS device-set configuration XML (probe calibration, clip rectangle).
    #[arg(required_unless_present = "xml")]
    pub calibration: Option<PathBuf>,
    /// Output model (.vtk as Slicer hands it; .ply, .stl, .obj also work).
    #[arg(required_unless_present = "xml")]
    pub output_model: Option<PathBuf>,
    /// Choose the iso-level from the echo levels of the kept pixels (ignores --iso).
    #[arg(long = "autoIso")]
    pub auto_iso: bool,
    /// Iso-level of the boundary echo (grey level) when --autoIso is not given.
    #[arg(long, default_value_t = DEFAULT_ISO)]
    pub iso: f64,
    /// Smoothing weight w in mm.
    #[arg(long, default_value_t = echosurf::pipeline::DEFAULT_SMOOTHING_MM)]
    pub smoothing: f64,
    /// Output surface: auto, iso or ridge (as `extract --sheet`).
    #[arg(long, default_value = "auto")]
    pub sheet: String,
    /// Lattice spacing of the surfacer in mm.
    #[arg(long, default_value_t = DEFAULT_RESOLUTION_MM)]
    pub resolution: f64,
    /// Samples handed to the fit.
    #[arg(long = "maxSamples", default_value_t = DEFAULT_MAX_SAMPLES)]
    pub max_samples: usize,
    /// Coordinates of the model written: ras or lps (as `extract --space`).
    #[arg(long, default_value = "ras")]
    pub space: String,
    /// Where Slicer wants the results (`name = value` lines).
    #[arg(long)]
    pub returnparameterfile: Option<PathBuf>,
    /// Given by Slicer to modules loaded as shared libraries; unused by an executable.
    #[arg(long, hide = true)]
    pub processinformationaddress: Option<String>,
}

/// The module description Slicer reads from `--xml`, valid against the Execution Model's
/// `ModuleDescription.xsd` as shipped in `shared/slicer`: that schema allows one `<element>` per
/// enumeration and no `<channel>` on scalars, so the choices are strings (checked by `extract`) and
/// the results are plain scalars named as the return parameter file names them.
pub fn module_description() -> String {
    let smoothing = echosurf::pipeline::DEFAULT_SMOOTHING_MM;
    format!(
        r#"<?xml version="1.0" encoding="utf-8"?>
<executable>
  <category>Ultrasound</category>
  <title>echosurf surface extraction</title>
  <description><![CDATA[Extracts the surface of the structures a tracked freehand ultrasound sweep (PLUS sequence) recorded, directly from the tracked pixels: segments the boundary echoes in every frame, fits one smooth implicit function (biharmonic RBF) to them and draws its iso-surface or echo-ridge sheet. The model is written in the sequence's own coordinates, so it overlays the sweep loaded with the Sequences module.]]></description>
  <version>{version}</version>
  <documentation-url>https://example.invalid/echosurf/docs/guide/slicer.md</documentation-url>
  <license>MIT OR Apache-2.0</license>
  <contributor>echosurf authors</contributor>
  <parameters>
    <label>Input and output</label>
    <description><![CDATA[The tracked sweep, its calibration and the surface model made from them.]]></description>
    <file fileExtensions=".mha,.mhd,.nrrd">
      <name>sequence</name>
      <label>Tracked sequence</label>
      <description><![CDATA[PLUS tracked ultrasound sequence (.igs.mha, .mha, .mhd or .igs.nrrd).]]></description>
      <channel>input</channel>
      <index>0</index>
    </file>
    <file fileExtensions=".xml">
      <name>calibration</name>
      <label>PLUS calibration</label>
      <description><![CDATA[PLUS device-set configuration XML with the probe calibration (ImageToProbe) and the clip rectangle.]]></description>
      <channel>input</channel>
      <index>1</index>
    </file>
    <geometry type="model" fileExtensions=".vtk">
      <name>outputModel</name>
      <label>Surface model</label>
      <description><![CDATA[The extracted surface.]]></description>
      <channel>output</channel>
      <index>2</index>
    </geometry>
  </parameters>
  <parameters>
    <label>Surface</label>
    <description><![CDATA[Where the surface is drawn and how smooth it is.]]></description>
    <boolean>
      <name>autoIso</name>
      <longflag>autoIso</longflag>
      <label>Automatic iso-level</label>
      <description><![CDATA[Choose the iso-level between the background and boundary echo levels of the kept pixels (the Iso-level below is then ignored).]]></description>
      <default>true</default>
    </boolean>
    <double>
      <name>iso</name>
      <longflag>iso</longflag>
      <label>Iso-level</label>
      <description><![CDATA[Grey level of the boundary echo, used when the automatic iso-level is off.]]></description>
      <default>{iso}</default>
      <constraints>
        <minimum>0</minimum>
        <maximum>255</maximum>
        <step>1</step>
      </constraints>
    </double>
    <double>
      <name>smoothing</name>
      <longflag>smoothing</longflag>
      <label>Smoothing (mm)</label>
      <description><![CDATA[Smoothing weight of the fit in mm: larger is smoother; 0 interpolates the speckle.]]></description>
      <default>{smoothing}</default>
      <constraints>
        <minimum>0</minimum>
        <maximum>20</maximum>
        <step>0.1</step>
      </constraints>
    </double>
    <string>
      <name>sheet</name>
      <longflag>sheet</longflag>
      <label>Sheet (auto, iso or ridge)</label>
      <description><![CDATA[auto, iso or ridge. iso: the iso-surface (a sheath around a thin echo); ridge: one sheet through the echoes' ridge; auto: ridge where the echoes are thin ridges, iso otherwise.]]></description>
      <default>auto</default>
    </string>
    <double>
      <name>resolution</name>
      <longflag>resolution</longflag>
      <label>Resolution (mm)</label>
      <description><![CDATA[Lattice spacing of the surfacer in mm.]]></description>
      <default>{resolution}</default>
      <constraints>
        <minimum>0.1</minimum>
        <maximum>5</maximum>
        <step>0.1</step>
      </constraints>
    </double>
    <integer>
      <name>maxSamples</name>
      <longflag>maxSamples</longflag>
      <label>Samples</label>
      <description><![CDATA[How many tracked pixels the fit is given (random decimation, echoes first).]]></description>
      <default>{max_samples}</default>
      <constraints>
        <minimum>1000</minimum>
        <maximum>1000000</maximum>
        <step>1000</step>
      </constraints>
    </integer>
    <string>
      <name>space</name>
      <longflag>space</longflag>
      <label>File coordinates (ras or lps)</label>
      <description><![CDATA[ras or lps: coordinate system of the model file, tagged SPACE=RAS or SPACE=LPS, which Slicer reads either way.]]></description>
      <default>ras</default>
    </string>
  </parameters>
  <parameters>
    <label>Results</label>
    <description><![CDATA[What the run made, written by the module to its return parameter file.]]></description>
    <integer>
      <name>triangles</name>
      <label>Triangles</label>
      <description><![CDATA[Triangles in the model.]]></description>
    </integer>
    <integer>
      <name>pieces</name>
      <label>Pieces</label>
      <description><![CDATA[Connected pieces of the model.]]></description>
    </integer>
    <double>
      <name>seconds</name>
      <label>Time (s)</label>
      <description><![CDATA[Time the extraction took, in seconds.]]></description>
    </double>
  </parameters>
</executable>
"#,
        version = env!("CARGO_PKG_VERSION"),
        iso = DEFAULT_ISO,
        resolution = DEFAULT_RESOLUTION_MM,
        max_samples = DEFAULT_MAX_SAMPLES,
    )
}

/// Progress as the Execution Model's `<filter-progress>` lines on stdout: overall progress rises
/// monotonically (each stage covers half of what is left, since the stage count depends on the route),
/// and each stage's own fraction goes in `<filter-stage-progress>`.
#[derive(Debug, Default)]
struct FilterProgress {
    state: Mutex<FilterState>,
}

#[derive(Debug, Default)]
struct FilterState {
    stages_done: u32,
    total: u64,
    /// The last overall and stage fractions printed, in percent.
    printed: (u32, u32),
}

impl FilterState {
    fn overall(&self, stage_fraction: f64) -> f64 {
        let left = 0.5f64.powi(self.stages_done as i32);
        1.0 - left + left * 0.5 * stage_fraction
    }
}

fn emit(line: &str) {
    let mut out = std::io::stdout().lock();
    // Slicer reads the lines as they come: flush each one.
    let _ = writeln!(out, "{line}").and_then(|_| out.flush());
}

impl echosurf::progress::Progress for FilterProgress {
    fn start(&self, stage: &str, total: u64) {
        if let Ok(mut s) = self.state.lock() {
            s.total = total;
            s.printed.1 = 0;
            emit(&format!(
                "<filter-start><filter-name>echosurf</filter-name><filter-comment>{stage}</filter-comment></filter-start>"
            ));
        }
    }

    fn advance(&self, done: u64) {
        if let Ok(mut s) = self.state.lock() {
            if s.total == 0 {
                return;
            }
            let stage = (done as f64 / s.total as f64).clamp(0.0, 1.0);
            let percent = ((100.0 * s.overall(stage)) as u32, (100.0 * stage) as u32);
            // A line per whole percent of the stage: enough for a bar, not a flood.
            if percent.1 != s.printed.1 {
                s.printed = percent;
                emit(&format!(
                    "<filter-progress>{:.2}</filter-progress>\n<filter-stage-progress>{:.2}</filter-stage-progress>",
                    percent.0 as f64 / 100.0,
                    percent.1 as f64 / 100.0
                ));
            }
        }
    }

    fn finish(&self) {
        if let Ok(mut s) = self.state.lock() {
            s.stages_done += 1;
            s.total = 0;
            emit(&format!(
                "<filter-progress>{:.2}</filter-progress>",
                s.overall(0.0)
            ));
        }
    }
    fn memory_estimate(&self, bytes: u64) {
        crate::memory::record_estimate(bytes);
    }
}

/// `echosurf extract` as the module runs it: its arguments, parsed by extract's own parser.
#[derive(Debug, Parser)]
struct ExtractCommand {
    #[command(flatten)]
    args: super::extract::Args,
}

/// The `echosurf extract` arguments that a module run stands for.
fn extract_arguments(args: &Args) -> anyhow::Result<Vec<std::ffi::OsString>> {
    let (Some(sequence), Some(config), Some(model)) =
        (&args.sequence, &args.calibration, &args.output_model)
    else {
        anyhow::bail!("give the sequence, the calibration and the output model");
    };
    let iso = if args.auto_iso {
        "auto".to_string()
    } else {
        args.iso.to_string()
    };
    let mut out: Vec<std::ffi::OsString> = vec!["extract".into(), sequence.into()];
    for (flag, value) in [
        ("--calibration", config.as_os_str().to_owned()),
        ("--out", model.as_os_str().to_owned()),
        ("--iso", iso.into()),
        ("--smoothing", args.smoothing.to_string().into()),
        ("--sheet", args.sheet.clone().into()),
        ("--resolution", args.resolution.to_string().into()),
        ("--max-samples", args.max_samples.to_string().into()),
        ("--space", args.space.clone().into()),
    ] {
        out.push(flag.into());
        out.push(value);
    }
    Ok(out)
}

pub fn run(args: Args) -> anyhow::Result<()> {
    if args.xml {
        print!("{}", module_description());
        return Ok(());
    }
    if let Some(path) = &args.returnparameterfile {
        super::outputs::check_outputs(
            &[],
            &[super::outputs::output(
                "--returnparameterfile",
                path,
                super::outputs::Holds::AnyName,
            )],
        )?;
    }
    let extract = ExtractCommand::try_parse_from(extract_arguments(&args)?)
        .map_err(|e| anyhow::anyhow!("{}", e.to_string().trim_end()))?
        .args;
    let progress = FilterProgress::default();
    let output = super::extract::run_with(extract, &progress)?;
    emit("<filter-progress>1</filter-progress>");
    emit("<filter-end><filter-name>echosurf</filter-name></filter-end>");
    let triangles: usize = output.surfaces.iter().map(|s| s.mesh.triangles.len()).sum();
    let pieces: usize = output
        .surfaces
        .iter()
        .map(|s| s.mesh.topology().components)
        .sum();
    if let Some(path) = &args.returnparameterfile {
        let text = format!(
            "triangles = {triangles}\npieces = {pieces}\nseconds = {:.3}\n",
            output.report.total_seconds
        );
        echosurf::io::atomic::write_bytes_atomic(path, text.as_bytes())?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overall_progress_rises_and_stays_below_one() {
        let mut s = FilterState::default();
        let mut last = -1.0;
        for _ in 0..6 {
            for f in [0.0, 0.5, 1.0] {
                let p = s.overall(f);
                assert!(p >= last && p < 1.0, "{p} after {last}");
                last = p;
            }
            s.stages_done += 1;
        }
    }

    #[test]
    fn a_run_maps_onto_extract_arguments_that_extract_accepts() {
        let args = Args::try_parse_from_for_test(&["s.mha", "c.xml", "m.vtk", "--autoIso"]);
        let mapped = extract_arguments(&args).unwrap();
        let extract = ExtractCommand::try_parse_from(&mapped).unwrap().args;
        assert_eq!(extract.iso.as_deref(), Some("auto"));
        assert_eq!(extract.out, Some(PathBuf::from("m.vtk")));
        assert_eq!(extract.max_samples, Some(DEFAULT_MAX_SAMPLES));
        let args = Args::try_parse_from_for_test(&["s.mha", "c.xml", "m.vtk", "--iso", "72.5"]);
        let extract = ExtractCommand::try_parse_from(extract_arguments(&args).unwrap())
            .unwrap()
            .args;
        assert_eq!(extract.iso.as_deref(), Some("72.5"));
    }

    impl Args {
        fn try_parse_from_for_test(words: &[&str]) -> Args {
            #[derive(Parser)]
            struct Wrap {
                #[command(flatten)]
                args: Args,
            }
            Wrap::try_parse_from(std::iter::once("m").chain(words.iter().copied()))
                .unwrap()
                .args
        }
    }
}
