//! A small hand-written SVG line / scatter plot with linear or logarithmic axes (no plotting crate).

mod axis;

use std::fmt::Write;

use axis::Axis;

/// One named series of (x, y) points.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
    /// Join the points (in the given order) with a line; else markers only.
    pub connect: bool,
}

/// A plot: axes, labels and series. Points that cannot be drawn (non-finite, or <= 0 on a log axis)
/// are left out.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Plot {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub x_log: bool,
    pub y_log: bool,
    pub series: Vec<Series>,
}

const WIDTH: f64 = 720.0;
const HEIGHT: f64 = 480.0;
const LEFT: f64 = 80.0;
const RIGHT: f64 = 190.0;
const TOP: f64 = 40.0;
const BOTTOM: f64 = 60.0;
const COLOURS: [&str; 8] = [
    "#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf",
];

fn escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

impl Plot {
    /// The plot as a standalone SVG document.
    pub fn to_svg(&self) -> String {
        let drawable = |x: f64, y: f64| {
            x.is_finite() && y.is_finite() && (!self.x_log || x > 0.0) && (!self.y_log || y > 0.0)
        };
        let all = || {
            self.series
                .iter()
                .flat_map(|s| s.points.iter().copied())
                .filter(|&(x, y)| drawable(x, y))
        };
        let x_axis = Axis::new(all().map(|p| p.0), self.x_log);
        let y_axis = Axis::new(all().map(|p| p.1), self.y_log);
        let (plot_w, plot_h) = (WIDTH - LEFT - RIGHT, HEIGHT - TOP - BOTTOM);
        let px = |x: f64| LEFT + x_axis.fraction(x) * plot_w;
        let py = |y: f64| TOP + (1.0 - y_axis.fraction(y)) * plot_h;

        let mut svg = String::new();
        let _ = writeln!(
            svg,
            r#"<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{HEIGHT}" viewBox="0 0 {WIDTH} {HEIGHT}" font-family="sans-serif" font-size="12">"#
        );
        let _ = writeln!(
            svg,
            r#"<rect x="0" y="0" width="{WIDTH}" height="{HEIGHT}" fill="white"/>"#
        );
        let _ = writeln!(
            svg,
            r#"<text x="{:.1}" y="22" text-anchor="middle" font-size="15">{}</text>"#,
            LEFT + plot_w / 2.0,
            escape(&self.title)
        );
        // Grid and ticks.
        for (v, label) in x_axis.ticks() {
            let x = px(v);
            let _ = writeln!(
                svg,
                r##"<line x1="{x:.1}" y1="{TOP:.1}" x2="{x:.1}" y2="{:.1}" stroke="#ddd"/>"##,
                TOP + plot_h
            );
            let _ = writeln!(
                svg,
                r#"<text x="{x:.1}" y="{:.1}" text-anchor="middle">{}</text>"#,
                TOP + plot_h + 18.0,
                escape(&label)
            );
        }
        for (v, label) in y_axis.ticks() {
            let y = py(v);
            let _ = writeln!(
                svg,
                r##"<line x1="{LEFT:.1}" y1="{y:.1}" x2="{:.1}" y2="{y:.1}" stroke="#ddd"/>"##,
                LEFT + plot_w
            );
            let _ = writeln!(
                svg,
                r#"<text x="{:.1}" y="{:.1}" text-anchor="end">{}</text>"#,
                LEFT - 6.0,
                y + 4.0,
                escape(&label)
            );
        }
        let _ = writeln!(
            svg,
            r#"<rect x="{LEFT:.1}" y="{TOP:.1}" width="{plot_w:.1}" height="{plot_h:.1}" fill="none" stroke="black"/>"#
        );
        let _ = writeln!(
            svg,
            r#"<text x="{:.1}" y="{:.1}" text-anchor="middle">{}</text>"#,
            LEFT + plot_w / 2.0,
            HEIGHT - 15.0,
            escape(&self.x_label)
        );
        let _ = writeln!(
            svg,
            r#"<text x="18" y="{:.1}" text-anchor="middle" transform="rotate(-90 18 {:.1})">{}</text>"#,
            TOP + plot_h / 2.0,
            TOP + plot_h / 2.0,
            escape(&self.y_label)
        );
        // Series and legend.
        for (i, s) in self.series.iter().enumerate() {
            let colour = COLOURS[i % COLOURS.len()];
            let points: Vec<(f64, f64)> = s
                .points
                .iter()
                .copied()
                .filter(|&(x, y)| drawable(x, y))
                .map(|(x, y)| (px(x), py(y)))
                .collect();
            if s.connect && points.len() > 1 {
                let path: Vec<String> = points
                    .iter()
                    .map(|(x, y)| format!("{x:.1},{y:.1}"))
                    .collect();
                let _ = writeln!(
                    svg,
                    r#"<polyline points="{}" fill="none" stroke="{colour}" stroke-width="2"/>"#,
                    path.join(" ")
                );
            }
            for (x, y) in &points {
                let _ = writeln!(
                    svg,
                    r#"<circle cx="{x:.1}" cy="{y:.1}" r="4" fill="{colour}"/>"#
                );
            }
            let ly = TOP + 10.0 + 18.0 * i as f64;
            let lx = WIDTH - RIGHT + 12.0;
            let _ = writeln!(
                svg,
                r#"<circle cx="{lx:.1}" cy="{ly:.1}" r="4" fill="{colour}"/>"#
            );
            let _ = writeln!(
                svg,
                r#"<text x="{:.1}" y="{:.1}">{}</text>"#,
                lx + 10.0,
                ly + 4.0,
                escape(&s.name)
            );
        }
        svg.push_str("</svg>\n");
        svg
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(svg: &str) -> roxmltree::Document<'_> {
        roxmltree::Document::parse(svg).expect("well-formed XML")
    }

    #[test]
    fn log_log_plot_is_well_formed_with_decade_ticks_and_power_law_as_a_line() {
        // y = x^2 on log-log axes is a straight line of slope 2 (in decades).
        let points: Vec<(f64, f64)> = [1e3, 3e3, 1e4, 3e4, 1e5]
            .iter()
            .map(|&x| (x, x * x * 1e-9))
            .collect();
        let plot = Plot {
            title: "fit <time> & samples".into(),
            x_label: "samples".into(),
            y_label: "seconds".into(),
            x_log: true,
            y_log: true,
            series: vec![Series {
                name: "direct".into(),
                points: points.clone(),
                connect: true,
            }],
        };
        let svg = plot.to_svg();
        let doc = parse(&svg);
        let texts: Vec<String> = doc
            .descendants()
            .filter(|n| n.has_tag_name("text"))
            .filter_map(|n| n.text().map(str::to_string))
            .collect();
        assert!(texts.contains(&"fit <time> & samples".to_string()));
        for decade in ["1000", "10000", "100000"] {
            assert!(texts.iter().any(|t| t == decade), "{decade} in {texts:?}");
        }
        let circles: Vec<(f64, f64)> = doc
            .descendants()
            .filter(|n| n.has_tag_name("circle"))
            .map(|n| {
                (
                    n.attribute("cx").unwrap().parse().unwrap(),
                    n.attribute("cy").unwrap().parse().unwrap(),
                )
            })
            .collect();
        // 5 data markers + 1 legend marker.
        assert_eq!(circles.len(), 6);
        // Collinear on screen, with twice the pixel rise per decade in y as in x per decade... relative
        // to each axis' decades: check equal steps between the 1e3, 1e4, 1e5 markers.
        let (a, b, c) = (circles[0], circles[2], circles[4]);
        assert!(((b.0 - a.0) - (c.0 - b.0)).abs() < 0.2);
        assert!(((b.1 - a.1) - (c.1 - b.1)).abs() < 0.2);
        assert!(b.1 < a.1, "larger y is higher on screen");
    }

    #[test]
    fn linear_plot_skips_undrawable_points_and_log_axis_drops_non_positive() {
        let plot = Plot {
            title: "t".into(),
            x_label: "x".into(),
            y_label: "y".into(),
            x_log: false,
            y_log: true,
            series: vec![Series {
                name: "s".into(),
                points: vec![(1.0, 1.0), (2.0, 0.0), (f64::NAN, 3.0), (3.0, 10.0)],
                connect: false,
            }],
        };
        let svg = plot.to_svg();
        let doc = parse(&svg);
        let markers = doc
            .descendants()
            .filter(|n| n.has_tag_name("circle"))
            .count();
        assert_eq!(markers, 2 + 1);
        assert!(!svg.contains("NaN") && !svg.contains("inf"));
    }
}
