//! One error type for the whole library. Every error that comes from a user's file names that file, so a
//! user with a folder of sweeps can tell which one is broken and why.

use std::path::{Path, PathBuf};

/// What is wrong with a file's content. Tests match on this rather than on message text.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FormatProblem {
    /// The file ends before the data its header promises.
    Truncated,
    /// A header size disagrees with the data that is actually there (or is absurd).
    SizeMismatch,
    /// A compressed stream or binary section does not decode.
    Corrupt,
    /// A required field or element is absent.
    MissingField,
    /// A field is present but its value does not parse or is not finite.
    BadValue,
    /// A valid file of a kind or variant echosurf does not handle.
    Unsupported,
    /// A sequence in which no frame can be used.
    NoValidFrames,
    /// A transform needed to place the frames is missing.
    MissingTransform,
}

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The operating system refused to read or write a file.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A file's content is malformed or unusable.
    #[error("{}: {message}", path.display())]
    Format {
        path: PathBuf,
        problem: FormatProblem,
        message: String,
    },
    /// Parameters or in-memory data that cannot be processed (no file involved).
    #[error("{0}")]
    InvalidInput(String),
    /// A numerical procedure failed (singular system, no convergence, non-finite values).
    #[error("{0}")]
    Numerical(String),
    /// The work would exceed a memory or size budget; the message says what would fit.
    #[error("{0}")]
    ResourceLimit(String),
    /// The work would need more memory than the budget: how much, the budget, the option that sets
    /// the budget (`None`: fixed at half the machine's memory) and a message naming the options that
    /// would make it fit.
    #[error("{message}")]
    OverBudget {
        needed_bytes: u64,
        budget_bytes: u64,
        budget_option: Option<OptionName>,
        message: Phrase,
    },
    /// Parameters or a numerical result that cannot be used, with a remedy naming options (`kind`
    /// says which of [`Error::InvalidInput`] or [`Error::Numerical`] it would otherwise be).
    #[error("{message}")]
    Options {
        kind: OptionsErrorKind,
        message: Phrase,
    },
}

/// What an [`Error::Options`] is about.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OptionsErrorKind {
    /// Parameters out of range, or data they do not suit.
    InvalidInput,
    /// A numerical procedure did not reach what the options ask.
    Numerical,
}

/// A library option an error names (as the remedy), so an application can phrase it in its own
/// terms (the CLI as a flag or a TOML key) while the library's messages name only its own fields.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum OptionName {
    /// The memory budget a run is checked against (`ExtractOptions::memory_budget_bytes`, the
    /// `budget_bytes` of the `budget::check_*` functions).
    MemoryBudget,
    /// `ExtractOptions::max_samples`: samples handed to the fit.
    MaxSamples,
    /// `rbf::FitOptions::solver`.
    FitSolver,
    /// `rbf::FitOptions::accuracy`.
    FitAccuracy,
    /// `rbf::FitOptions::smoothing`.
    FitSmoothing,
    /// `rbf::FitOptions::max_centres`.
    FitMaxCentres,
    /// `surface::SurfaceOptions::resolution_mm`.
    SurfaceResolution,
    /// `metrics::CompareOptions::samples_per_mm2`.
    CompareSamplesPerMm2,
    /// `metrics::CompareOptions::max_samples`.
    CompareMaxSamples,
    /// `ExtractOptions::iso`.
    IsoLevels,
    /// `segment::SegmentOptions::min_edgel_relative_strength`.
    MinEdgelRelativeStrength,
}

impl OptionName {
    /// Every option name, for applications that map each one.
    pub const ALL: [OptionName; 11] = [
        OptionName::MemoryBudget,
        OptionName::MaxSamples,
        OptionName::FitSolver,
        OptionName::FitAccuracy,
        OptionName::FitSmoothing,
        OptionName::FitMaxCentres,
        OptionName::SurfaceResolution,
        OptionName::CompareSamplesPerMm2,
        OptionName::CompareMaxSamples,
        OptionName::IsoLevels,
        OptionName::MinEdgelRelativeStrength,
    ];

    /// The option as the library spells it: its struct and field.
    pub fn field(self) -> &'static str {
        match self {
            OptionName::MemoryBudget => "ExtractOptions::memory_budget_bytes",
            OptionName::MaxSamples => "ExtractOptions::max_samples",
            OptionName::FitSolver => "FitOptions::solver",
            OptionName::FitAccuracy => "FitOptions::accuracy",
            OptionName::FitSmoothing => "FitOptions::smoothing",
            OptionName::FitMaxCentres => "FitOptions::max_centres",
            OptionName::SurfaceResolution => "SurfaceOptions::resolution_mm",
            OptionName::CompareSamplesPerMm2 => "CompareOptions::samples_per_mm2",
            OptionName::CompareMaxSamples => "CompareOptions::max_samples",
            OptionName::IsoLevels => "ExtractOptions::iso",
            OptionName::MinEdgelRelativeStrength => "SegmentOptions::min_edgel_relative_strength",
        }
    }
}

/// One piece of a [`Phrase`].
#[derive(Debug, Clone, PartialEq)]
enum PhrasePart {
    Text(String),
    Option(OptionName),
}

/// A message whose option names are slots: `Display` writes each as the library's field
/// ([`OptionName::field`]); [`Phrase::render`] lets an application write its own names.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Phrase {
    parts: Vec<PhrasePart>,
}

impl Phrase {
    /// A phrase starting with `text`.
    pub fn new(text: impl Into<String>) -> Self {
        Phrase::default().text(text)
    }

    /// Appends plain text.
    pub fn text(mut self, text: impl Into<String>) -> Self {
        self.parts.push(PhrasePart::Text(text.into()));
        self
    }

    /// Appends the name of `option`.
    pub fn option(mut self, option: OptionName) -> Self {
        self.parts.push(PhrasePart::Option(option));
        self
    }

    /// Appends another phrase.
    pub fn then(mut self, other: Phrase) -> Self {
        self.parts.extend(other.parts);
        self
    }

    /// The options the phrase names, in order.
    pub fn options(&self) -> impl Iterator<Item = OptionName> + '_ {
        self.parts.iter().filter_map(|p| match p {
            PhrasePart::Option(o) => Some(*o),
            PhrasePart::Text(_) => None,
        })
    }

    /// The text with each option written as `name(option)`.
    pub fn render(&self, name: &dyn Fn(OptionName) -> String) -> String {
        let mut out = String::new();
        for part in &self.parts {
            match part {
                PhrasePart::Text(t) => out.push_str(t),
                PhrasePart::Option(o) => out.push_str(&name(*o)),
            }
        }
        out
    }
}

impl std::fmt::Display for Phrase {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.render(&|o| o.field().to_string()))
    }
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    pub fn io(path: impl AsRef<Path>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.as_ref().to_path_buf(),
            source,
        }
    }

    pub fn format(
        path: impl AsRef<Path>,
        problem: FormatProblem,
        message: impl Into<String>,
    ) -> Self {
        Error::Format {
            path: path.as_ref().to_path_buf(),
            problem,
            message: message.into(),
        }
    }

    /// The message with each option it names written as `name(option)` (for an application's flags);
    /// the same as `to_string()` for errors that name no option.
    pub fn render(&self, name: &dyn Fn(OptionName) -> String) -> String {
        match self {
            Error::OverBudget { message, .. } | Error::Options { message, .. } => {
                message.render(name)
            }
            other => other.to_string(),
        }
    }

    /// The options this error names as its remedy.
    pub fn options(&self) -> Vec<OptionName> {
        match self {
            Error::OverBudget { message, .. } | Error::Options { message, .. } => {
                message.options().collect()
            }
            _ => Vec::new(),
        }
    }

    /// The format problem, if this is a file-content error.
    pub fn problem(&self) -> Option<FormatProblem> {
        match self {
            Error::Format { problem, .. } => Some(*problem),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::progress::NoProgress;

    /// Every error the library builds from its options, with the budget at 0 so each refuses.
    fn option_errors() -> Vec<Error> {
        use crate::budget::{self, FitPlan, SegmentedCounts};
        let fit = crate::rbf::FitOptions::default();
        let triangle = crate::mesh::Mesh {
            vertices: vec![
                glam::DVec3::ZERO,
                glam::DVec3::X * 10.0,
                glam::DVec3::Y * 10.0,
            ],
            normals: Vec::new(),
            triangles: vec![[0, 1, 2]],
        };
        let counts = SegmentedCounts {
            frame_pixels: 1000,
            kept_pixels: 1000,
            bin_px: [1, 1],
            bone_sweep: false,
        };
        let plan = FitPlan {
            max_samples: 1000,
            fit: &fit,
        };
        let segment = crate::segment::SegmentOptions {
            min_edgel_relative_strength: -1.0,
            ..Default::default()
        };
        vec![
            budget::check_fit_budget(1000, &fit, 0, &NoProgress).unwrap_err(),
            budget::check_surface_budget(1000, 0.5, 0, &NoProgress).unwrap_err(),
            budget::check_extract_budget_after_segmentation(counts, plan, 0, &NoProgress)
                .unwrap_err(),
            budget::check_extract_budget_after_segmentation(counts, plan, 1 << 40, &NoProgress)
                .map_or_else(
                    |e| e,
                    |()| {
                        // Room for the samples but not the fit: the advice names a sample cap.
                        let e = budget::estimate_extract_memory(counts, plan);
                        budget::check_extract_budget_after_segmentation(
                            counts,
                            plan,
                            e.total() - e.fit / 2,
                            &NoProgress,
                        )
                        .unwrap_err()
                    },
                ),
            budget::check_compare_budget(
                &triangle,
                &triangle,
                &crate::metrics::CompareOptions::default(),
                0,
                &NoProgress,
            )
            .unwrap_err(),
            segment.validate().unwrap_err(),
        ]
    }

    #[test]
    fn no_error_message_names_a_command_line_flag() {
        for option in OptionName::ALL {
            assert!(!option.field().contains("--"), "{option:?}");
        }
        let errors = option_errors();
        let named: std::collections::HashSet<OptionName> =
            errors.iter().flat_map(Error::options).collect();
        for option in [
            OptionName::MemoryBudget,
            OptionName::MaxSamples,
            OptionName::FitSolver,
            OptionName::FitMaxCentres,
            OptionName::SurfaceResolution,
            OptionName::CompareSamplesPerMm2,
            OptionName::CompareMaxSamples,
            OptionName::MinEdgelRelativeStrength,
        ] {
            assert!(named.contains(&option), "{option:?} named by none");
        }
        for error in &errors {
            let text = error.to_string();
            assert!(!text.contains("--"), "{text}");
            assert!(matches!(
                error,
                Error::OverBudget { .. } | Error::Options { .. }
            ));
            // Each option slot is where an application's name goes, and only there.
            let flags = error.render(&|o| format!("<{o:?}>"));
            for option in error.options() {
                assert!(text.contains(option.field()), "{text}");
                assert!(flags.contains(&format!("<{option:?}>")), "{flags}");
            }
            assert!(!flags.contains("Options::"), "{flags}");
        }
    }

    #[test]
    fn an_over_budget_error_carries_the_figures_and_the_option() {
        let error = crate::budget::check_surface_budget(1000, 0.5, 7, &NoProgress).unwrap_err();
        let Error::OverBudget {
            needed_bytes,
            budget_bytes,
            budget_option,
            ..
        } = error
        else {
            panic!("{error:?}")
        };
        assert!(needed_bytes > 7);
        assert_eq!(budget_bytes, 7);
        assert_eq!(budget_option, Some(OptionName::MemoryBudget));
    }

    #[test]
    fn a_phrase_renders_its_slots_with_the_given_names() {
        let phrase = Phrase::new("raise ")
            .option(OptionName::FitAccuracy)
            .text(" or ")
            .option(OptionName::FitSmoothing);
        assert_eq!(
            phrase.to_string(),
            "raise FitOptions::accuracy or FitOptions::smoothing"
        );
        let name = |o: OptionName| match o {
            OptionName::FitAccuracy => "--accuracy".to_string(),
            other => other.field().to_string(),
        };
        assert_eq!(
            phrase.render(&name),
            "raise --accuracy or FitOptions::smoothing"
        );
        assert_eq!(
            phrase.options().collect::<Vec<_>>(),
            [OptionName::FitAccuracy, OptionName::FitSmoothing]
        );
    }
}
