//! The benchmark's results as a markdown table and SVG plots.

use crate::fit_scaling::ScalingRow;
use crate::run::{ROUTES, RouteResult};
use crate::svg;

fn mb(bytes: Option<u64>) -> String {
    bytes.map_or_else(|| "n/a".into(), |b| format!("{:.0}", b as f64 / 1e6))
}

/// The results as a markdown table, one row per case and route.
pub fn markdown_table(results: &[RouteResult]) -> String {
    let mut out = String::from(
        "| case | route | iso | accuracy mean (mm) | accuracy p95 (mm) | completeness (1 mm) | completeness, <= 30 deg (1 mm) | components | truth patches, <= 30 deg | patches whole / split / missed | probe side <= 20 deg: completeness; patches whole / split / missed of n | triangles | time (s) | peak extra memory (MB) |\n\
         |---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in results {
        let note = r
            .error
            .as_deref()
            .map(|e| format!(" ({e})"))
            .unwrap_or_default();
        out.push_str(&format!(
            "| {} | {}{} | {:.1} | {:.2} | {:.2} | {:.1} % | {:.1} % | {} | {} | {} / {} / {} | {} | {} | {:.2} | {} |\n",
            r.case,
            r.route,
            note,
            r.iso,
            r.accuracy_mean_mm,
            r.accuracy_p95_mm,
            100.0 * r.completeness_1mm,
            100.0 * r.completeness_strong_echo_1mm,
            r.components,
            r.truth_patches_strong_echo,
            r.patch_coverage.whole,
            r.patch_coverage.split,
            r.patch_coverage.missed,
            r.probe_facing.as_ref().map_or_else(
                || "n/a".to_string(),
                |p| format!(
                    "{:.1} %; {} / {} / {} of {}",
                    100.0 * p.completeness_1mm,
                    p.patch_coverage.whole,
                    p.patch_coverage.split,
                    p.patch_coverage.missed,
                    p.truth_patches
                )
            ),
            r.triangles,
            r.seconds,
            mb(r.peak_extra_bytes),
        ));
    }
    out
}

/// Accuracy (mean, mm) against time (s), one series per route.
pub fn accuracy_vs_time_plot(results: &[RouteResult]) -> svg::Plot {
    let series = ROUTES
        .iter()
        .map(|(route, _)| route)
        .map(|route| svg::Series {
            name: format!("{route} route"),
            points: results
                .iter()
                .filter(|r| r.route == *route)
                .map(|r| (r.seconds, r.accuracy_mean_mm))
                .collect(),
            connect: false,
        })
        .collect();
    svg::Plot {
        title: "Accuracy against time, all cases".into(),
        x_label: "time (s, log)".into(),
        y_label: "mean distance mesh -> truth (mm)".into(),
        x_log: true,
        y_log: false,
        series,
    }
}

/// Fit time against the number of samples, log-log.
pub fn fit_scaling_plot(rows: &[ScalingRow]) -> svg::Plot {
    // One pair of lines per sample source, in the order the rows come.
    let mut sources: Vec<&str> = Vec::new();
    for r in rows {
        if !sources.contains(&r.samples_from.as_str()) {
            sources.push(&r.samples_from);
        }
    }
    let series_of = |source: &str, what: &str, seconds: fn(&ScalingRow) -> f64| svg::Series {
        name: if sources.len() > 1 {
            format!("{what}, {source}")
        } else {
            what.to_string()
        },
        points: rows
            .iter()
            .filter(|r| r.samples_from == source)
            .map(|r| (r.samples as f64, seconds(r)))
            .collect(),
        connect: true,
    };
    svg::Plot {
        title: "RBF fit time against samples".into(),
        x_label: "samples".into(),
        y_label: "seconds".into(),
        x_log: true,
        y_log: true,
        series: sources
            .iter()
            .flat_map(|&s| {
                [
                    series_of(s, "fit", |r| r.fit_seconds),
                    series_of(s, "evaluate N points", |r| r.eval_seconds),
                ]
            })
            .collect(),
    }
}
