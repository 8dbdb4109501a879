//! The library's option names in the terms of the subcommand that ran: its flag, or for `extract`
//! the `--config` TOML key of a knob that has no flag. The library's messages name its own fields
//! ([`echosurf::OptionName`]); only the CLI knows its flags.

use echosurf::OptionName;

/// Whose flags an error is phrased in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Terms {
    /// `extract`, and what runs it (`batch`, `slicer-module`).
    Extract,
    Fit,
    Surface,
    Compare,
    /// `segment` and `sample`.
    Segment,
    /// Subcommands that set none of these options: the library's field names.
    Library,
}

/// How `terms` spells `option`.
pub fn option_name(terms: Terms, option: OptionName) -> String {
    use OptionName as O;
    let name = match (terms, option) {
        (Terms::Library, _) => None,
        (_, O::MemoryBudget) => Some("--memory-budget"),
        (Terms::Extract, O::MaxSamples) => Some("--max-samples"),
        (Terms::Extract, O::FitSmoothing) => Some("--smoothing"),
        (Terms::Extract, O::SurfaceResolution) => Some("--resolution"),
        (Terms::Extract, O::IsoLevels) => Some("--iso"),
        (Terms::Extract, O::FitSolver) => Some("tuning.fit.solver (--config)"),
        (Terms::Extract, O::FitAccuracy) => Some("tuning.fit.accuracy_grey (--config)"),
        (Terms::Extract, O::MinEdgelRelativeStrength) => {
            Some("tuning.segment.min_edgel_relative_strength")
        }
        (Terms::Fit, O::FitSolver) => Some("--solver"),
        (Terms::Fit, O::FitAccuracy) => Some("--accuracy"),
        (Terms::Fit, O::FitSmoothing) => Some("--smoothing"),
        (Terms::Fit, O::FitMaxCentres) => Some("--max-centres"),
        (Terms::Surface, O::SurfaceResolution) => Some("--resolution"),
        (Terms::Surface, O::IsoLevels) => Some("--iso"),
        (Terms::Compare, O::CompareSamplesPerMm2) => Some("--samples-per-mm2"),
        (Terms::Compare, O::CompareMaxSamples) => Some("--max-samples"),
        (Terms::Segment, O::MaxSamples) => Some("--max-samples"),
        (Terms::Segment, O::MinEdgelRelativeStrength) => Some("--edgel-floor"),
        _ => None,
    };
    name.map_or_else(|| option.field().to_string(), str::to_string)
}

/// The error and its causes on one line, each cause once, the library's options named in `terms`.
/// The library's file errors already end with their cause (so a library user's `to_string()` says
/// why), and anyhow's `{:#}` would repeat it: "a.mha: No such file or directory (os error 2): No such
/// file or directory (os error 2)".
pub fn error_message(error: &anyhow::Error, terms: Terms) -> String {
    let mut message = String::new();
    for cause in error.chain() {
        let text = match cause.downcast_ref::<echosurf::Error>() {
            Some(e) => e.render(&|o| option_name(terms, o)),
            None => cause.to_string(),
        };
        if message.is_empty() {
            message = text;
        } else if !message.ends_with(&text) {
            message.push_str(": ");
            message.push_str(&text);
        }
    }
    message
}

#[cfg(test)]
mod tests {
    use super::*;
    use anyhow::Context;

    fn missing_file_error() -> echosurf::Error {
        let source = std::io::Error::from(std::io::ErrorKind::NotFound);
        echosurf::Error::io("sweep.mha", source)
    }

    #[test]
    fn a_file_error_names_its_cause_once() {
        let cause = std::io::Error::from(std::io::ErrorKind::NotFound).to_string();
        let error = anyhow::Error::new(missing_file_error());
        assert_eq!(
            error_message(&error, Terms::Library),
            format!("sweep.mha: {cause}")
        );
        let in_context = Err::<(), _>(missing_file_error())
            .context("segmenting sweep.mha")
            .unwrap_err();
        assert_eq!(
            error_message(&in_context, Terms::Library),
            format!("segmenting sweep.mha: sweep.mha: {cause}")
        );
    }

    #[test]
    fn causes_not_already_said_are_all_kept() {
        let error = anyhow::anyhow!("the innermost")
            .context("the middle")
            .context("the outer");
        assert_eq!(
            error_message(&error, Terms::Library),
            "the outer: the middle: the innermost"
        );
    }

    #[test]
    fn library_options_are_named_as_the_subcommand_s_flags() {
        let fit = echosurf::rbf::FitOptions::default();
        let error =
            echosurf::budget::check_fit_budget(1000, &fit, 0, &echosurf::progress::NoProgress)
                .unwrap_err();
        let library = error.to_string();
        let error = anyhow::Error::new(error).context("fitting cloud.ply");
        let text = error_message(&error, Terms::Fit);
        assert!(text.starts_with("fitting cloud.ply: "), "{text}");
        for flag in ["--max-centres", "--solver", "--memory-budget"] {
            assert!(text.contains(flag), "{text}");
        }
        assert!(!text.contains("FitOptions::"), "{text}");
        assert!(library.contains("FitOptions::solver"), "{library}");
        // Every option has a name in every subcommand's terms.
        for terms in [Terms::Extract, Terms::Fit, Terms::Surface, Terms::Compare] {
            assert_eq!(
                option_name(terms, OptionName::MemoryBudget),
                "--memory-budget"
            );
        }
        assert_eq!(
            option_name(Terms::Extract, OptionName::FitSolver),
            "tuning.fit.solver (--config)"
        );
    }
}
