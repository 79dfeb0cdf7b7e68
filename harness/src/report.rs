//! Pictures and pages for people who would rather look than read: line charts as PNG
//! (plotters, bitmap backend; text from a font bundled in the binary so it needs nothing from
//! the system), and a self-contained HTML report (PNG files beside it, no scripts, no network)
//! with a table of figures next to each chart. Used by `demo` and `bench refine`.

use anyhow::{anyhow, Context, Result};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
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

/// One axis of a chart: the interval `[lo, hi]` (never empty: `lo < hi`) and its scale.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Axis {
    /// Lower end.
    pub lo: f64,
    /// Upper end.
    pub hi: f64,
    /// Logarithmic scale.
    pub log: bool,
}

impl Axis {
    /// A linear axis over values from `lo` to `hi` with 5 % margins; one value (every byte
    /// arrived at once, a flat line) gets ±5 % of its magnitude (at least ±0.05), so the axis
    /// has an extent and ticks.
    pub fn linear(lo: f64, hi: f64) -> Axis {
        let magnitude = lo.abs().max(hi.abs()).max(1.0);
        let pad = if hi - lo > 1e-9 * magnitude {
            (hi - lo) * 0.05
        } else {
            magnitude * 0.05
        };
        Axis {
            lo: lo - pad,
            hi: hi + pad,
            log: false,
        }
    }

    /// The axis for `values` (non-finite ones ignored, and non-positive ones when `log`):
    /// logarithmic when asked and the values span at least a decade, linear otherwise —
    /// plotters ticks a logarithmic axis at powers of ten only, so a narrower one would have
    /// no numbers. `None` when no value is usable.
    pub fn fit(values: impl Iterator<Item = f64>, log: bool) -> Option<Axis> {
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for v in values.filter(|v| v.is_finite() && (!log || *v > 0.0)) {
            lo = lo.min(v);
            hi = hi.max(v);
        }
        if !lo.is_finite() {
            return None;
        }
        Some(if log && hi >= 10.0 * lo {
            Axis {
                lo: lo / 1.1,
                hi: hi * 1.1,
                log: true,
            }
        } else {
            Axis::linear(lo, hi)
        })
    }

    /// Whether `v` lies on the axis.
    pub fn contains(&self, v: f64) -> bool {
        v >= self.lo && v <= self.hi
    }

    /// `v` where lines are straight: its logarithm on a logarithmic axis.
    fn straight(&self, v: f64) -> f64 {
        if self.log {
            v.ln()
        } else {
            v
        }
    }

    fn unstraight(&self, u: f64) -> f64 {
        if self.log {
            u.exp()
        } else {
            u
        }
    }
}

/// The part of the segment `a`–`b` inside the box `[x0, x1] × [y0, y1]`, as fractions of the
/// way from `a` to `b` (Liang–Barsky); `None` when it misses the box.
fn clip_fractions(a: (f64, f64), b: (f64, f64), bx: [f64; 4]) -> Option<(f64, f64)> {
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [
        (-dx, a.0 - bx[0]),
        (dx, bx[1] - a.0),
        (-dy, a.1 - bx[2]),
        (dy, bx[3] - a.1),
    ] {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else {
            let r = q / p;
            if p < 0.0 {
                t0 = t0.max(r);
            } else {
                t1 = t1.min(r);
            }
        }
    }
    (t0 <= t1).then_some((t0, t1))
}

/// The pieces of the polyline `points` inside the frame `x` × `y`, cut where it crosses the
/// frame's edges (in the axes' drawing space, where the lines are straight), so that nothing
/// drawn leaves the frame.
pub fn clip_to_frame(points: &[(f64, f64)], x: &Axis, y: &Axis) -> Vec<Vec<(f64, f64)>> {
    let bx = [
        x.straight(x.lo),
        x.straight(x.hi),
        y.straight(y.lo),
        y.straight(y.hi),
    ];
    let to = |p: (f64, f64)| (x.straight(p.0), y.straight(p.1));
    let back = |u: (f64, f64)| (x.unstraight(u.0), y.unstraight(u.1));
    let mut pieces = Vec::new();
    if let [p] = points {
        if x.contains(p.0) && y.contains(p.1) {
            pieces.push(vec![*p]);
        }
        return pieces;
    }
    let mut piece: Vec<(f64, f64)> = Vec::new();
    for w in points.windows(2) {
        let (a, b) = (to(w[0]), to(w[1]));
        let Some((t0, t1)) = clip_fractions(a, b, bx) else {
            if !piece.is_empty() {
                pieces.push(std::mem::take(&mut piece));
            }
            continue;
        };
        let at = |t: f64, whole: (f64, f64)| {
            if t == 0.0 {
                w[0]
            } else if t == 1.0 {
                whole
            } else {
                back((a.0 + t * (b.0 - a.0), a.1 + t * (b.1 - a.1)))
            }
        };
        if t0 > 0.0 || piece.is_empty() {
            if !piece.is_empty() {
                pieces.push(std::mem::take(&mut piece));
            }
            piece.push(at(t0, w[0]));
        }
        piece.push(at(t1, w[1]));
        if t1 < 1.0 {
            pieces.push(std::mem::take(&mut piece));
        }
    }
    if !piece.is_empty() {
        pieces.push(piece);
    }
    pieces
}

/// Where a chart was drawn, in pixels of its image: the plot frame and the legend beside it
/// (`x0..x1`, `y0..y1`).
#[derive(Debug, Clone, PartialEq)]
pub struct Drawn {
    /// The plot frame.
    pub plot: (std::ops::Range<i32>, std::ops::Range<i32>),
    /// The legend, right of the frame (empty without labelled series).
    pub legend: (std::ops::Range<i32>, std::ops::Range<i32>),
}

const PALETTE: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
];
const MARKER: RGBColor = RGBColor(90, 90, 90);

impl Chart {
    /// The points drawn: finite, with positive x when the x axis was asked to be logarithmic.
    fn plotted<'a>(&'a self, s: &'a Series) -> impl Iterator<Item = (f64, f64)> + 'a {
        s.points
            .iter()
            .copied()
            .filter(|(x, y)| x.is_finite() && y.is_finite() && (!self.log_x || *x > 0.0))
    }

    /// The chart's axes (x, y), fitted to every plotted point: each contains every value it
    /// shows, with a margin, and has an extent even when all values are equal.
    pub fn axes(&self) -> (Axis, Axis) {
        let all = || self.series.iter().flat_map(|s| self.plotted(s));
        let x = Axis::fit(all().map(|p| p.0), self.log_x).unwrap_or(Axis {
            lo: 0.0,
            hi: 1.0,
            log: false,
        });
        let y = Axis::fit(all().map(|p| p.1), false).unwrap_or(Axis {
            lo: 0.0,
            hi: 1.0,
            log: false,
        });
        (x, y)
    }

    /// Draws the chart into a `width`×`height` PNG at `path`.
    pub fn write_png(&self, path: &Path, width: u32, height: u32) -> Result<()> {
        let root = BitMapBackend::new(path, (width, height)).into_drawing_area();
        self.draw(&root)
            .and_then(|_| root.present().map_err(|e| anyhow!("{e}")))
            .map_err(|e| anyhow!("drawing {}: {e}", path.display()))?;
        Ok(())
    }

    /// Draws the chart on `root`: the title, the plot frame with its axes, and the legend in a
    /// column of its own right of the frame, so it covers no data. Lines are clipped to the
    /// frame and drawn segment by segment (a wide polyline's mitred joins spike far past a
    /// sharp turn, such as a turn's dip). Returns where the frame and the legend are.
    pub fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result<Drawn> {
        register_font();
        let err = |e: &dyn std::fmt::Display| anyhow!("{e}");
        root.fill(&WHITE).map_err(|e| err(&e))?;
        let (width, _) = root.dim_in_pixel();
        let label_style: TextStyle = (FONT, 13).into_font().into();
        let labels: Vec<&str> = self
            .series
            .iter()
            .map(|s| s.label.as_str())
            .filter(|l| !l.is_empty())
            .collect();
        let mut text_width = 0u32;
        for l in &labels {
            let (w, _) = root
                .estimate_text_size(l, &label_style)
                .map_err(|e| err(&e))?;
            text_width = text_width.max(w);
        }
        let legend_width = if labels.is_empty() {
            0
        } else {
            (text_width + 40).min(width / 3)
        };
        let body = root.titled(&self.title, (FONT, 18)).map_err(|e| err(&e))?;
        let (plot_side, legend_side) = body.split_horizontally(width - legend_width);
        let (x, y) = self.axes();
        let mut builder = ChartBuilder::on(&plot_side);
        builder
            .margin(10)
            .margin_right(if legend_width > 0 { 4 } else { 10 })
            .x_label_area_size(40)
            .y_label_area_size(56);
        let x_format = if x.log { log_axis_label } else { axis_label };
        let styles: Vec<ShapeStyle> = {
            let mut data_index = 0usize;
            self.series
                .iter()
                .map(|s| {
                    if s.marker {
                        ShapeStyle::from(&MARKER).stroke_width(1)
                    } else {
                        let c = PALETTE[data_index % PALETTE.len()];
                        data_index += 1;
                        ShapeStyle::from(&c).stroke_width(2)
                    }
                })
                .collect()
        };
        macro_rules! draw {
            ($chart:expr) => {{
                let mut chart = $chart;
                chart
                    .configure_mesh()
                    .x_desc(self.x_label.as_str())
                    .y_desc(self.y_label.as_str())
                    .x_label_formatter(&|v| x_format(*v))
                    .y_label_formatter(&|v| axis_label(*v))
                    .label_style((FONT, 13))
                    .light_line_style(RGBColor(235, 235, 235))
                    .draw()
                    .map_err(|e| err(&e))?;
                for (s, style) in self.series.iter().zip(&styles) {
                    let pts: Vec<(f64, f64)> = self.plotted(s).collect();
                    for piece in clip_to_frame(&pts, &x, &y) {
                        if s.marker {
                            chart
                                .draw_series(DashedLineSeries::new(piece, 6, 4, *style))
                                .map_err(|e| err(&e))?;
                        } else {
                            chart
                                .draw_series(
                                    piece
                                        .windows(2)
                                        .map(|w| PathElement::new(vec![w[0], w[1]], *style)),
                                )
                                .map_err(|e| err(&e))?;
                        }
                    }
                }
                chart.plotting_area().get_pixel_range()
            }};
        }
        let plot = if x.log {
            draw!(builder
                .build_cartesian_2d((x.lo..x.hi).log_scale(), y.lo..y.hi)
                .map_err(|e| err(&e))?)
        } else {
            draw!(builder
                .build_cartesian_2d(x.lo..x.hi, y.lo..y.hi)
                .map_err(|e| err(&e))?)
        };
        // The legend: a short line in the series' style and its label, top down beside the
        // frame, aligned with the frame's top.
        let (legend_x, legend_y) = legend_side.get_pixel_range();
        let top = plot.1.start - legend_y.start;
        let mut row = 0;
        for (s, style) in self.series.iter().zip(&styles) {
            if s.label.is_empty() || legend_width == 0 {
                continue;
            }
            let cy = top + 8 + 18 * row;
            row += 1;
            let line = vec![(4, cy), (26, cy)];
            if s.marker {
                legend_side
                    .draw(&PathElement::new(vec![(4, cy), (10, cy)], *style))
                    .and_then(|_| {
                        legend_side.draw(&PathElement::new(vec![(16, cy), (22, cy)], *style))
                    })
                    .map_err(|e| err(&e))?;
            } else {
                legend_side
                    .draw(&PathElement::new(line, *style))
                    .map_err(|e| err(&e))?;
            }
            legend_side
                .draw(&Text::new(
                    s.label.clone(),
                    (32, cy),
                    label_style.pos(Pos::new(HPos::Left, VPos::Center)),
                ))
                .map_err(|e| err(&e))?;
        }
        Ok(Drawn {
            plot,
            legend: if legend_width == 0 {
                (
                    legend_x.start..legend_x.start,
                    legend_y.start..legend_y.start,
                )
            } else {
                (legend_x, legend_y)
            },
        })
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

    /// The RGB-head depth-cued walk's turn, as the demo drew it: Q_I from 95 dB to 34 dB
    /// between two frames 33 ms apart, on a logarithmic time axis.
    fn sharp_turn() -> Chart {
        let mut a: Vec<(f64, f64)> = (1..=40)
            .map(|i| (15.0 * i as f64, 40.0 + i as f64))
            .collect();
        a.extend([
            (2820.8, 95.0),
            (2854.2, 33.5),
            (2871.0, 43.0),
            (2887.6, 46.7),
        ]);
        a.extend((1..=60).map(|i| (2900.0 + 80.0 * i as f64, 46.7 + 0.8 * i as f64)));
        let b: Vec<(f64, f64)> = a.iter().map(|(x, y)| (x * 1.1, y - 9.0)).collect();
        Chart {
            title: "rgb-head: Q_I against time".into(),
            x_label: "time since opening (ms)".into(),
            y_label: "Q_I (dB, paper units)".into(),
            log_x: true,
            series: vec![Series::new("single", a), Series::new("depth-cued", b)],
        }
    }

    #[test]
    fn the_axes_contain_every_plotted_value() {
        for log_x in [false, true] {
            let mut c = sharp_turn();
            c.log_x = log_x;
            c.series
                .push(Series::marker("budget", vec![(16.6, 0.0), (16.6, 120.0)]));
            let (x, y) = c.axes();
            assert!(x.lo < x.hi && y.lo < y.hi);
            for s in &c.series {
                for &(px, py) in &s.points {
                    assert!(x.contains(px), "x {px} outside {x:?}");
                    assert!(y.contains(py), "y {py} outside {y:?}");
                }
            }
        }
    }

    #[test]
    fn a_degenerate_bytes_axis_gets_an_extent_with_ticks() {
        // Every byte at once: one x value. The axis has an extent and is linear (a
        // logarithmic one narrower than a decade has no tick at all).
        let one = Axis::fit([78_346.0; 5].into_iter(), true).unwrap();
        assert!(
            one.lo < 78_346.0 && 78_346.0 < one.hi && !one.log,
            "{one:?}"
        );
        // Bytes from 37 k to 78 k: still no power of ten inside, so linear.
        let narrow = Axis::fit([37_000.0, 52_000.0, 78_346.0].into_iter(), true).unwrap();
        assert!(!narrow.log && narrow.contains(37_000.0) && narrow.contains(78_346.0));
        // A decade or more: logarithmic, with a power of ten inside for its ticks.
        let wide = Axis::fit([400.0, 36_247.0].into_iter(), true).unwrap();
        assert!(wide.log && wide.contains(1_000.0) && wide.contains(10_000.0));
        // Zero and negative values cannot go on a log axis; nothing usable gives none.
        assert!(Axis::fit([0.0, -3.0, f64::NAN].into_iter(), true).is_none());
        // A flat line at zero still spans something.
        let zero = Axis::fit([0.0, 0.0].into_iter(), false).unwrap();
        assert!(zero.lo < 0.0 && zero.hi > 0.0);
    }

    #[test]
    fn clipping_cuts_lines_at_the_frame() {
        let x = Axis::linear(0.0, 10.0);
        let y = Axis {
            lo: 0.0,
            hi: 1.0,
            log: false,
        };
        // In, out above, back in: two pieces, each ending on the frame's top edge.
        let pieces = clip_to_frame(&[(0.0, 0.5), (2.0, 1.5), (4.0, 0.5)], &x, &y);
        assert_eq!(pieces.len(), 2, "{pieces:?}");
        assert_eq!(pieces[0][0], (0.0, 0.5));
        assert!((pieces[0][1].1 - 1.0).abs() < 1e-12 && (pieces[0][1].0 - 1.0).abs() < 1e-12);
        assert!((pieces[1][0].1 - 1.0).abs() < 1e-12 && (pieces[1][0].0 - 3.0).abs() < 1e-12);
        assert_eq!(pieces[1][1], (4.0, 0.5));
        // Wholly outside: nothing.
        assert!(clip_to_frame(&[(1.0, 5.0), (2.0, 6.0)], &x, &y).is_empty());
        // Wholly inside: unchanged.
        let inside = [(1.0, 0.1), (2.0, 0.2), (3.0, 0.3)];
        assert_eq!(clip_to_frame(&inside, &x, &y), vec![inside.to_vec()]);
    }

    /// Pixels of `chart` drawn at `w`×`h` in a data series' colour, and where it drew.
    fn coloured_pixels(chart: &Chart, w: u32, h: u32) -> (Vec<(i32, i32)>, Drawn) {
        let mut buf = vec![0u8; (w * h * 3) as usize];
        let drawn = {
            let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
            let d = chart.draw(&root).unwrap();
            root.present().unwrap();
            d
        };
        let colours: Vec<[u8; 3]> = PALETTE[..chart.series.len()]
            .iter()
            .map(|c| [c.0, c.1, c.2])
            .collect();
        let pixels = buf
            .chunks_exact(3)
            .enumerate()
            .filter(|(_, p)| colours.iter().any(|c| c == p))
            .map(|(i, _)| ((i as u32 % w) as i32, (i as u32 / w) as i32))
            .collect();
        (pixels, drawn)
    }

    #[test]
    fn lines_and_legend_stay_in_their_places() {
        for log_x in [true, false] {
            let mut chart = sharp_turn();
            chart.log_x = log_x;
            let (pixels, drawn) = coloured_pixels(&chart, 560, 360);
            let (px, py) = &drawn.plot;
            let (lx, ly) = &drawn.legend;
            assert!(
                !lx.is_empty() && px.end <= lx.start,
                "legend beside the frame: {drawn:?}"
            );
            // A stroke 2 pixels wide may reach one pixel past the frame's edge.
            let in_plot = |(x, y): &(i32, i32)| {
                (px.start - 1..px.end + 1).contains(x) && (py.start - 1..py.end + 1).contains(y)
            };
            let in_legend = |(x, y): &(i32, i32)| lx.contains(x) && ly.contains(y);
            let inside = pixels.iter().filter(|p| in_plot(p)).count();
            assert!(inside > 200, "the lines were drawn ({inside} pixels)");
            let stray: Vec<_> = pixels
                .iter()
                .filter(|p| !in_plot(p) && !in_legend(p))
                .collect();
            assert!(
                stray.is_empty(),
                "log_x {log_x}: {} pixels outside the frame, e.g. {:?}",
                stray.len(),
                &stray[..stray.len().min(5)]
            );
        }
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
