//! Pictures and pages for people who would rather look than read: line charts as PNG
//! (plotters, bitmap backend; text from a font bundled in the binary so it needs nothing from
//! the system), and a self-contained HTML report (PNG files beside it, no scripts, no network)
//! with a table of figures next to each chart. Used by `demo` and `bench refine`.

use anyhow::{anyhow, Context, Result};
use plotters::prelude::*;
use std::fmt::Write as _;
use std::path::Path;
use std::sync::Once;

const FONT: &str = "sans-serif";

fn register_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The font is compiled in; a failure here would be a broken build, so it is logged
        // rather than propagated (charts then lack text but are still drawn).
        if plotters::style::register_font(
            FONT,
            FontStyle::Normal,
            epaint_default_fonts::UBUNTU_LIGHT,
        )
        .is_err()
        {
            tracing::warn!("the bundled chart font could not be loaded");
        }
    });
}

/// One line of a chart.
#[derive(Debug, Clone)]
pub struct Series {
    /// Legend label.
    pub label: String,
    /// Points (non-finite ones are skipped).
    pub points: Vec<(f64, f64)>,
    /// Draw as a dashed marker line (budgets, thresholds) rather than data.
    pub marker: bool,
}

impl Series {
    /// A data series.
    pub fn new(label: impl Into<String>, points: Vec<(f64, f64)>) -> Series {
        Series {
            label: label.into(),
            points,
            marker: false,
        }
    }

    /// A marker line (e.g. a vertical line at a budget).
    pub fn marker(label: impl Into<String>, points: Vec<(f64, f64)>) -> Series {
        Series {
            label: label.into(),
            points,
            marker: true,
        }
    }
}

/// A line chart.
#[derive(Debug, Clone)]
pub struct Chart {
    /// Title above the plot.
    pub title: String,
    /// X axis label.
    pub x_label: String,
    /// Y axis label.
    pub y_label: String,
    /// Logarithmic x axis (positive x only).
    pub log_x: bool,
    /// The lines.
    pub series: Vec<Series>,
}

/// An axis value as people write it: whole numbers without ".0", thousands and millions as
/// "20 k" and "1.5 M", at most three significant digits.
pub fn axis_label(v: f64) -> String {
    if !v.is_finite() {
        return String::new();
    }
    let (scaled, suffix) = match v.abs() {
        a if a >= 1e6 => (v / 1e6, " M"),
        a if a >= 1e4 => (v / 1e3, " k"),
        _ => (v, ""),
    };
    let digits = if scaled == 0.0 {
        0
    } else {
        (2 - scaled.abs().log10().floor() as i32).clamp(0, 6) as usize
    };
    let text = format!("{scaled:.digits$}");
    let text = if text.contains('.') {
        text.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        text
    };
    let text = if text == "-0" { "0".to_string() } else { text };
    format!("{text}{suffix}")
}

/// A log axis labels only 1, 2 and 5 times a power of ten, so that labels cannot run into
/// each other ("3000.04000.05000.0").
fn log_axis_label(v: f64) -> String {
    if !(v.is_finite() && v > 0.0) {
        return String::new();
    }
    let mantissa = v / 10f64.powf(v.log10().floor());
    if [1.0, 2.0, 5.0, 10.0]
        .iter()
        .any(|m| (mantissa - m).abs() < 1e-6 * m)
    {
        axis_label(v)
    } else {
        String::new()
    }
}

fn range(values: impl Iterator<Item = f64>, log: bool) -> Option<(f64, f64)> {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values.filter(|v| v.is_finite() && (!log || *v > 0.0)) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() {
        return None;
    }
    if hi <= lo {
        let pad = if log {
            lo * 0.5
        } else {
            lo.abs().max(1.0) * 0.05
        };
        return Some((lo - pad, hi + pad));
    }
    if log {
        Some((lo / 1.1, hi * 1.1))
    } else {
        let pad = (hi - lo) * 0.05;
        Some((lo - pad, hi + pad))
    }
}

impl Chart {
    /// Draws the chart into a `width`×`height` PNG at `path`.
    pub fn write_png(&self, path: &Path, width: u32, height: u32) -> Result<()> {
        register_font();
        let points = || {
            self.series
                .iter()
                .flat_map(|s| s.points.iter().copied())
                .filter(|(x, y)| x.is_finite() && y.is_finite() && (!self.log_x || *x > 0.0))
        };
        let (x0, x1) = range(points().map(|p| p.0), self.log_x).unwrap_or((0.0, 1.0));
        let (y0, y1) = range(points().map(|p| p.1), false).unwrap_or((0.0, 1.0));
        let root = BitMapBackend::new(path, (width, height)).into_drawing_area();
        let err = |e: &dyn std::fmt::Display| anyhow!("drawing {}: {e}", path.display());
        root.fill(&WHITE).map_err(|e| err(&e))?;
        let mut builder = ChartBuilder::on(&root);
        builder
            .caption(&self.title, (FONT, 18))
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(56);
        let palette = [
            RGBColor(31, 119, 180),
            RGBColor(255, 127, 14),
            RGBColor(44, 160, 44),
            RGBColor(214, 39, 40),
            RGBColor(148, 103, 189),
            RGBColor(140, 86, 75),
            RGBColor(227, 119, 194),
            RGBColor(127, 127, 127),
        ];
        let x_format = if self.log_x {
            log_axis_label
        } else {
            axis_label
        };
        macro_rules! draw {
            ($chart:expr) => {{
                let mut chart = $chart;
                chart
                    .configure_mesh()
                    .x_desc(self.x_label.as_str())
                    .y_desc(self.y_label.as_str())
                    .x_label_formatter(&|x| x_format(*x))
                    .y_label_formatter(&|y| axis_label(*y))
                    .label_style((FONT, 13))
                    .light_line_style(RGBColor(235, 235, 235))
                    .draw()
                    .map_err(|e| err(&e))?;
                let mut data_index = 0usize;
                for s in &self.series {
                    let pts: Vec<(f64, f64)> = s
                        .points
                        .iter()
                        .copied()
                        .filter(|(x, y)| {
                            x.is_finite() && y.is_finite() && (!self.log_x || *x > 0.0)
                        })
                        .collect();
                    let color = if s.marker {
                        RGBColor(90, 90, 90)
                    } else {
                        let c = palette[data_index % palette.len()];
                        data_index += 1;
                        c
                    };
                    let style = ShapeStyle::from(&color).stroke_width(if s.marker { 1 } else { 2 });
                    let drawn = if s.marker {
                        chart.draw_series(DashedLineSeries::new(pts, 6, 4, style))
                    } else {
                        chart.draw_series(LineSeries::new(pts, style))
                    };
                    drawn
                        .map_err(|e| err(&e))?
                        .label(s.label.as_str())
                        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], style));
                }
                chart
                    .configure_series_labels()
                    .label_font((FONT, 13))
                    .background_style(WHITE.mix(0.85))
                    .border_style(RGBColor(200, 200, 200))
                    .position(SeriesLabelPosition::LowerRight)
                    .draw()
                    .map_err(|e| err(&e))?;
            }};
        }
        if self.log_x {
            draw!(builder
                .build_cartesian_2d((x0..x1).log_scale(), y0..y1)
                .map_err(|e| err(&e))?);
        } else {
            draw!(builder
                .build_cartesian_2d(x0..x1, y0..y1)
                .map_err(|e| err(&e))?);
        }
        root.present().map_err(|e| err(&e))?;
        Ok(())
    }
}

/// HTML-escapes text.
pub fn escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            c => out.push(c),
        }
    }
    out
}

/// A table: header row and rows of cells (text, escaped when written).
#[derive(Debug, Clone, Default)]
pub struct Table {
    /// Column headings.
    pub head: Vec<String>,
    /// Rows.
    pub rows: Vec<Vec<String>>,
}

impl Table {
    fn html(&self, out: &mut String) {
        out.push_str("<table><tr>");
        for h in &self.head {
            let _ = write!(out, "<th>{}</th>", escape(h));
        }
        out.push_str("</tr>");
        for r in &self.rows {
            out.push_str("<tr>");
            for c in r {
                let _ = write!(out, "<td>{}</td>", escape(c));
            }
            out.push_str("</tr>");
        }
        out.push_str("</table>");
    }
}

/// A section of the report: a heading, a paragraph, charts (PNG paths relative to the report)
/// with a table beside them, and images (frames) below.
#[derive(Debug, Clone, Default)]
pub struct Section {
    /// Heading.
    pub title: String,
    /// Paragraph of text.
    pub text: String,
    /// Chart PNGs (relative paths).
    pub charts: Vec<String>,
    /// The figures beside the charts.
    pub table: Table,
    /// Frame images (relative path, caption).
    pub images: Vec<(String, String)>,
}

/// Writes a self-contained HTML report (PNG files referenced by relative path).
pub fn write_html(path: &Path, title: &str, intro: &str, sections: &[Section]) -> Result<()> {
    let mut out = String::new();
    let _ = write!(
        out,
        "<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>{}</title><style>\
body{{font-family:sans-serif;margin:24px;color:#222}}\
h2{{border-bottom:1px solid #ccc;padding-bottom:4px;margin-top:32px}}\
.row{{display:flex;flex-wrap:wrap;gap:16px;align-items:flex-start}}\
table{{border-collapse:collapse;font-size:13px}}\
td,th{{border:1px solid #ccc;padding:3px 8px;text-align:right}}\
th{{background:#f3f3f3}}\
figure{{margin:0;display:inline-block;text-align:center;font-size:12px}}\
img.frame{{image-rendering:pixelated;border:1px solid #ddd}}\
</style></head><body><h1>{}</h1><p>{}</p>",
        escape(title),
        escape(title),
        escape(intro)
    );
    for s in sections {
        let _ = write!(
            out,
            "<h2>{}</h2><p>{}</p><div class=\"row\">",
            escape(&s.title),
            escape(&s.text)
        );
        for c in &s.charts {
            let _ = write!(out, "<img src=\"{}\" alt=\"chart\">", escape(c));
        }
        s.table.html(&mut out);
        out.push_str("</div>");
        if !s.images.is_empty() {
            out.push_str("<div class=\"row\">");
            for (src, caption) in &s.images {
                let _ = write!(
                    out,
                    "<figure><img class=\"frame\" src=\"{}\" width=\"192\"><figcaption>{}</figcaption></figure>",
                    escape(src),
                    escape(caption)
                );
            }
            out.push_str("</div>");
        }
    }
    out.push_str("</body></html>\n");
    std::fs::write(path, out).with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_chart_is_a_png_of_the_asked_size() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.png");
        Chart {
            title: "Q_I against time".into(),
            x_label: "ms".into(),
            y_label: "dB".into(),
            log_x: true,
            series: vec![
                Series::new("a", vec![(1.0, 2.0), (10.0, 5.0), (f64::NAN, 1.0)]),
                Series::marker("budget", vec![(3.0, 0.0), (3.0, 6.0)]),
            ],
        }
        .write_png(&p, 320, 200)
        .unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!(&bytes[1..4], b"PNG");
        // IHDR width and height.
        assert_eq!(u32::from_be_bytes(bytes[16..20].try_into().unwrap()), 320);
        assert_eq!(u32::from_be_bytes(bytes[20..24].try_into().unwrap()), 200);
    }

    #[test]
    fn an_empty_chart_still_draws() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("e.png");
        Chart {
            title: "nothing".into(),
            x_label: "x".into(),
            y_label: "y".into(),
            log_x: false,
            series: vec![Series::new("none", vec![])],
        }
        .write_png(&p, 100, 80)
        .unwrap();
        assert!(p.exists());
    }

    #[test]
    fn axis_labels_read_as_people_write_numbers() {
        for (v, want) in [
            (0.0, "0"),
            (45.0, "45"),
            (65.5, "65.5"),
            (0.01, "0.01"),
            (1000.0, "1000"),
            (20_000.0, "20 k"),
            (1_500_000.0, "1.5 M"),
            (-2.0, "-2"),
            (0.123456, "0.123"),
        ] {
            assert_eq!(axis_label(v), want, "{v}");
        }
        assert_eq!(log_axis_label(3000.0), "");
        assert_eq!(log_axis_label(5000.0), "5000");
        assert_eq!(log_axis_label(100.0), "100");
    }

    #[test]
    fn html_escapes_what_it_is_given() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("r.html");
        let s = Section {
            title: "<b>".into(),
            text: "a & b".into(),
            table: Table {
                head: vec!["x".into()],
                rows: vec![vec!["\"q\"".into()]],
            },
            ..Default::default()
        };
        write_html(&p, "T", "i", &[s]).unwrap();
        let h = std::fs::read_to_string(&p).unwrap();
        assert!(h.contains("&lt;b&gt;") && h.contains("a &amp; b") && h.contains("&quot;q&quot;"));
        assert!(!h.contains("<b>"));
    }
}
