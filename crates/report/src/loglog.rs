//! Log-log line plots (SALI/GALI against time, work-precision diagrams, ...).

use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use crate::canvas::{PixelRect, FONT_FAMILY};
use crate::error::{plot_err, ReportError};
use crate::figure::{write_figure, Figure};

/// A line (or point set) on a plot.
#[derive(Clone, Copy, Debug)]
pub struct Line<'a> {
    /// Legend text; an empty label leaves the line out of the legend.
    pub label: &'a str,
    /// x coordinates of the points.
    pub xs: &'a [f64],
    /// Must have the same length as `xs`.
    pub ys: &'a [f64],
}

/// A horizontal reference line (e.g. SALI thresholds 1e-4 and 1e-8), drawn dashed in grey.
#[derive(Clone, Copy, Debug)]
pub struct HLine<'a> {
    /// Legend text; an empty label leaves the line out of the legend.
    pub label: &'a str,
    /// Height of the line.
    pub y: f64,
}

/// A plot with logarithmic x and y axes.
#[derive(Clone, Debug)]
pub struct LogLogPlot<'a> {
    /// Title above the plot.
    pub title: &'a str,
    /// Label of the x axis.
    pub x_label: &'a str,
    /// Label of the y axis.
    pub y_label: &'a str,
    /// Lines (or point sets) drawn.
    pub lines: Vec<Line<'a>>,
    /// Horizontal reference lines.
    pub hlines: Vec<HLine<'a>>,
    /// Optional text labels attached to points: (x, y, text), as work-precision plots use.
    pub point_labels: Vec<(f64, f64, String)>,
    /// Draw a marker at each point in addition to the connecting lines.
    pub markers: bool,
}

/// Smallest and largest magnitudes drawn; values outside are skipped like non-positive ones
/// (this keeps every decade boundary a normal, finite `f64`).
const MIN_DRAWABLE: f64 = 1e-300;
const MAX_DRAWABLE: f64 = 1e300;

/// Line colours, cycled (a colour-blind-friendly categorical palette).
pub(crate) const PALETTE: [RGBColor; 14] = [
    RGBColor(0, 114, 178),   // blue
    RGBColor(213, 94, 0),    // vermilion
    RGBColor(0, 158, 115),   // bluish green
    RGBColor(204, 121, 167), // reddish purple
    RGBColor(230, 159, 0),   // orange
    RGBColor(86, 180, 233),  // sky blue
    RGBColor(0, 0, 0),       // black
    RGBColor(160, 130, 30),  // ochre
    RGBColor(120, 40, 140),  // plum
    RGBColor(150, 150, 150), // grey
    RGBColor(200, 30, 60),   // crimson
    RGBColor(40, 80, 30),    // dark green
    RGBColor(110, 70, 20),   // brown
    RGBColor(30, 40, 120),   // navy
];

/// Grey levels and dash patterns (dash, gap) for the reference lines, cycled.
const HLINE_GREYS: [RGBColor; 2] = [RGBColor(80, 80, 80), RGBColor(140, 140, 140)];
const HLINE_DASHES: [(f64, f64); 3] = [(10.0, 5.0), (4.0, 4.0), (16.0, 5.0)];

const BOLD_GRID: RGBColor = RGBColor(215, 215, 215);
const LIGHT_GRID: RGBColor = RGBColor(238, 238, 238);

/// Renders `plot` as a `width` x `height` image at `path`, PNG or SVG by its extension.
///
/// Points whose x or y is non-positive, NaN, infinite, or outside `[1e-300, 1e300]` cannot be
/// shown on log axes and are skipped; a line is broken at a skipped point rather than joined
/// across it. The axes span whole decades around the remaining data and the reference lines.
/// Returns [`ReportError::EmptyData`] when no line (or point label) has a drawable point.
pub fn render_loglog(
    plot: &LogLogPlot,
    path: &Path,
    width: u32,
    height: u32,
) -> Result<(), ReportError> {
    write_figure(plot, path, (width, height))
}

/// Every line has as many y values as x values.
pub(crate) fn check_lengths(lines: &[Line]) -> Result<(), ReportError> {
    match lines.iter().find(|l| l.xs.len() != l.ys.len()) {
        Some(line) => Err(ReportError::Plot(format!(
            "line {:?} has {} x values but {} y values",
            line.label,
            line.xs.len(),
            line.ys.len()
        ))),
        None => Ok(()),
    }
}

/// Whether a coordinate can be placed on a log axis.
fn drawable(v: f64) -> bool {
    v.is_finite() && (MIN_DRAWABLE..=MAX_DRAWABLE).contains(&v)
}

/// Splits a line into maximal runs of consecutive drawable points.
pub(crate) fn drawable_segments(xs: &[f64], ys: &[f64]) -> Vec<Vec<(f64, f64)>> {
    let mut segments = Vec::new();
    let mut current = Vec::new();
    for (&x, &y) in xs.iter().zip(ys) {
        if drawable(x) && drawable(y) {
            current.push((x, y));
        } else if !current.is_empty() {
            segments.push(std::mem::take(&mut current));
        }
    }
    if !current.is_empty() {
        segments.push(current);
    }
    segments
}

/// `10^e`, correctly rounded (`powi` does not promise that).
fn decade(e: i32) -> f64 {
    format!("1e{e}").parse().unwrap_or(f64::NAN)
}

/// Largest `e` with `10^e <= v`, for drawable `v`.
pub(crate) fn decade_floor(v: f64) -> i32 {
    let mut e = v.log10().floor() as i32;
    while decade(e) > v {
        e -= 1;
    }
    while decade(e + 1) <= v {
        e += 1;
    }
    e
}

/// Smallest `e` with `10^e >= v`, for drawable `v`.
pub(crate) fn decade_ceil(v: f64) -> i32 {
    let mut e = v.log10().ceil() as i32;
    while decade(e) < v {
        e += 1;
    }
    while decade(e - 1) >= v {
        e -= 1;
    }
    e
}

/// Running min/max of drawable values.
#[derive(Clone, Copy, Debug)]
struct Bounds {
    min: f64,
    max: f64,
}

impl Bounds {
    fn include(bounds: &mut Option<Bounds>, v: f64) {
        match bounds {
            Some(b) => {
                b.min = b.min.min(v);
                b.max = b.max.max(v);
            }
            None => *bounds = Some(Bounds { min: v, max: v }),
        }
    }

    /// Exponents of the enclosing whole decades, at least one decade wide.
    fn decades(self) -> (i32, i32) {
        let (lo, hi) = (decade_floor(self.min), decade_ceil(self.max));
        if lo < hi {
            (lo, hi)
        } else {
            (lo - 1, hi + 1)
        }
    }
}

/// Decade exponents `(x_lo, x_hi, y_lo, y_hi)` of the axes for `plot`, or `EmptyData`.
pub(crate) fn axis_decades(plot: &LogLogPlot) -> Result<(i32, i32, i32, i32), ReportError> {
    let mut xb = None;
    let mut yb = None;
    for line in &plot.lines {
        for seg in drawable_segments(line.xs, line.ys) {
            for (x, y) in seg {
                Bounds::include(&mut xb, x);
                Bounds::include(&mut yb, y);
            }
        }
    }
    for &(x, y, _) in &plot.point_labels {
        if drawable(x) && drawable(y) {
            Bounds::include(&mut xb, x);
            Bounds::include(&mut yb, y);
        }
    }
    for h in &plot.hlines {
        if drawable(h.y) {
            Bounds::include(&mut yb, h.y);
        }
    }
    // x bounds exist exactly when some point is drawable; reference lines alone give only y.
    let (Some(xb), Some(yb)) = (xb, yb) else {
        return Err(ReportError::EmptyData(
            "no line has a point with finite, positive x and y",
        ));
    };
    let (x_lo, x_hi) = xb.decades();
    let (y_lo, y_hi) = yb.decades();
    Ok((x_lo, x_hi, y_lo, y_hi))
}

/// Tick positions of one log axis.
struct LogTicks {
    /// Labelled decades.
    bold: Vec<f64>,
    /// Unlabelled grid lines: 2..9 x 10^e on short axes, skipped decades on long ones.
    light: Vec<f64>,
}

fn log_ticks(lo_e: i32, hi_e: i32, max_labels: usize) -> LogTicks {
    let max_labels = max_labels.max(2);
    // Label every `step`-th decade, `step` a "nice" 1, 2, 5, 10, 20, 50, ... chosen as small as
    // the space allows.
    let labelled = |step: i32| hi_e.div_euclid(step) - (lo_e + step - 1).div_euclid(step) + 1;
    let mut nice = (0..).map(|k: u32| [1, 2, 5][(k % 3) as usize] * 10i32.pow(k / 3));
    let step = nice
        .find(|&st| labelled(st) as usize <= max_labels || st >= 1000)
        .unwrap_or(1000);
    // Unlabelled decades get light grid lines every `sub` decades (at most 4 per interval).
    let sub = [1, 2, 5]
        .iter()
        .flat_map(|&m| (0..4).map(move |k| m * 10i32.pow(k)))
        .filter(|&c| 5 * c >= step && step % c == 0)
        .min()
        .unwrap_or(1);
    let n_decades = hi_e - lo_e;
    let mut bold = Vec::new();
    let mut light = Vec::new();
    for e in lo_e..=hi_e {
        if e.rem_euclid(step) == 0 {
            bold.push(decade(e));
        } else if e.rem_euclid(sub) == 0 {
            light.push(decade(e));
        }
        if step == 1 && n_decades <= 6 && e < hi_e {
            for m in 2..=9 {
                light.push(format!("{m}e{e}").parse().unwrap_or(f64::NAN));
            }
        }
    }
    LogTicks { bold, light }
}

/// Tick label of a decade: `1e-4`, `1e0`, `1e3`.
pub(crate) fn decade_label(v: f64) -> String {
    if !(v.is_finite() && v > 0.0) {
        return String::new();
    }
    let e = v.log10().round() as i32;
    if (v / decade(e) - 1.0).abs() < 1e-9 {
        format!("1e{e}")
    } else {
        format!("{v:e}")
    }
}

/// A legend row.
pub(crate) enum Swatch {
    Line(RGBColor),
    Dashed(RGBColor, (f64, f64)),
}

impl Figure for LogLogPlot<'_> {
    fn validate(&self) -> Result<(), ReportError> {
        check_lengths(&self.lines)?;
        axis_decades(self).map(|_| ())
    }

    fn draw<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
        (width, height): (u32, u32),
    ) -> Result<PixelRect, ReportError> {
        paint(self, axis_decades(self)?, root, (width, height), None)
    }
}

/// Log-log plots stacked in one image, top to bottom, each with its own axes and legend, their
/// plotting areas equally wide.
#[derive(Clone, Debug)]
pub struct Panels<'a> {
    /// The plots, top to bottom.
    pub panels: Vec<LogLogPlot<'a>>,
}

/// Renders `panels` as a `width` x `height` image at `path`, PNG or SVG by its extension, the
/// height shared evenly. A panel with nothing drawable is an error, as for one plot.
pub fn render_panels(
    panels: &Panels,
    path: &Path,
    width: u32,
    height: u32,
) -> Result<(), ReportError> {
    write_figure(panels, path, (width, height))
}

impl Figure for Panels<'_> {
    fn validate(&self) -> Result<(), ReportError> {
        if self.panels.is_empty() {
            return Err(ReportError::EmptyData("no panel"));
        }
        self.panels.iter().try_for_each(|p| p.validate())
    }

    /// Returns the first panel's data area.
    fn draw<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
        (width, height): (u32, u32),
    ) -> Result<PixelRect, ReportError> {
        let n = self.panels.len() as u32;
        let areas = root.split_evenly((self.panels.len(), 1));
        let mut first = None;
        // One legend width and one span of x for all, so that the panels' x axes line up.
        let legend_w = width / 4;
        let decades = self
            .panels
            .iter()
            .map(axis_decades)
            .collect::<Result<Vec<_>, _>>()?;
        let x_lo = decades.iter().map(|d| d.0).min().expect("validated");
        let x_hi = decades.iter().map(|d| d.1).max().expect("validated");
        for ((plot, area), d) in self.panels.iter().zip(&areas).zip(decades) {
            let size = (width, height / n);
            let rect = paint(plot, (x_lo, x_hi, d.2, d.3), area, size, Some(legend_w))?;
            first.get_or_insert(rect);
        }
        Ok(first.expect("validated: at least one panel"))
    }
}

fn paint<DB: DrawingBackend>(
    plot: &LogLogPlot,
    (x_lo_e, x_hi_e, y_lo_e, y_hi_e): (i32, i32, i32, i32),
    root: &DrawingArea<DB, Shift>,
    (width, height): (u32, u32),
    fixed_legend_w: Option<u32>,
) -> Result<PixelRect, ReportError> {
    let s = (f64::from(width.min(height)) / 600.0).clamp(0.5, 3.0);
    let px = |v: f64| (v * s).round().max(1.0) as u32;
    let title_font = (FONT_FAMILY, 22.0 * s).into_font().color(&BLACK);
    let desc_font = (FONT_FAMILY, 16.0 * s).into_font().color(&BLACK);
    let tick_font = (FONT_FAMILY, 13.0 * s).into_font().color(&BLACK);
    let legend_font = (FONT_FAMILY, 14.0 * s).into_font().color(&BLACK);
    let note_font = (FONT_FAMILY, 11.0 * s).into_font().color(&BLACK);
    let stroke = px(2.0);

    // Legend rows: drawable lines and reference lines that carry a label.
    let mut legend: Vec<(&str, Swatch)> = Vec::new();
    for (k, line) in plot.lines.iter().enumerate() {
        if !line.label.is_empty() && !drawable_segments(line.xs, line.ys).is_empty() {
            legend.push((line.label, Swatch::Line(PALETTE[k % PALETTE.len()])));
        }
    }
    for (k, h) in plot.hlines.iter().enumerate() {
        if !h.label.is_empty() && drawable(h.y) {
            let style = (HLINE_GREYS[k % 2], HLINE_DASHES[k % 3]);
            legend.push((h.label, Swatch::Dashed(style.0, style.1)));
        }
    }
    let swatch_w = 34.0 * s;
    let legend_w = if let Some(w) = fixed_legend_w {
        w
    } else if legend.is_empty() {
        0
    } else {
        let mut text_w = 0;
        for (label, _) in &legend {
            let (w, _) = root
                .estimate_text_size(label, &legend_font)
                .map_err(plot_err)?;
            text_w = text_w.max(w);
        }
        let wanted = text_w + (swatch_w + 30.0 * s) as u32;
        wanted.min(width * 35 / 100)
    };
    let (chart_area, legend_area) = if legend_w > 0 {
        let (a, b) = root.split_horizontally(width - legend_w);
        (a, Some(b))
    } else {
        (root.clone(), None)
    };

    let x_ticks = log_ticks(x_lo_e, x_hi_e, (f64::from(width) / (90.0 * s)) as usize);
    let y_ticks = log_ticks(y_lo_e, y_hi_e, (f64::from(height) / (45.0 * s)) as usize);
    let (x_lo, x_hi) = (decade(x_lo_e), decade(x_hi_e));
    let (y_lo, y_hi) = (decade(y_lo_e), decade(y_hi_e));

    let mut chart = ChartBuilder::on(&chart_area)
        .caption(plot.title, title_font)
        .margin(px(14.0))
        .x_label_area_size(px(50.0))
        .y_label_area_size(px(72.0))
        .build_cartesian_2d(
            (x_lo..x_hi)
                .log_scale()
                .with_key_points(x_ticks.bold)
                .with_light_points(x_ticks.light),
            (y_lo..y_hi)
                .log_scale()
                .with_key_points(y_ticks.bold)
                .with_light_points(y_ticks.light),
        )
        .map_err(plot_err)?;
    let label_fmt = |v: &f64| decade_label(*v);
    chart
        .configure_mesh()
        .x_desc(plot.x_label)
        .y_desc(plot.y_label)
        .x_label_formatter(&label_fmt)
        .y_label_formatter(&label_fmt)
        .label_style(tick_font)
        .axis_desc_style(desc_font)
        .bold_line_style(BOLD_GRID)
        .light_line_style(LIGHT_GRID)
        .axis_style(BLACK)
        .set_all_tick_mark_size(px(5.0))
        .draw()
        .map_err(plot_err)?;
    let plot_area = PixelRect::from_ranges(chart.plotting_area().get_pixel_range());

    // Reference lines first, so that data is drawn on top of them.
    for (k, h) in plot.hlines.iter().enumerate() {
        if !drawable(h.y) {
            continue;
        }
        let (dash, gap) = HLINE_DASHES[k % 3];
        let style = HLINE_GREYS[k % 2].stroke_width(stroke);
        chart
            .draw_series(DashedLineSeries::new(
                [(x_lo, h.y), (x_hi, h.y)],
                px(dash),
                px(gap),
                style,
            ))
            .map_err(plot_err)?;
    }

    let marker_r = px(3.5) as i32;
    for (k, line) in plot.lines.iter().enumerate() {
        let colour = PALETTE[k % PALETTE.len()];
        for seg in drawable_segments(line.xs, line.ys) {
            if seg.len() > 1 {
                chart
                    .draw_series(LineSeries::new(
                        seg.iter().copied(),
                        colour.stroke_width(stroke),
                    ))
                    .map_err(plot_err)?;
            }
            if plot.markers || seg.len() == 1 {
                chart
                    .draw_series(
                        seg.iter()
                            .map(|&p| Circle::new(p, marker_r, colour.filled())),
                    )
                    .map_err(plot_err)?;
            }
        }
    }

    let offset = px(5.0) as i32;
    let mut placed: Vec<PixelRect> = Vec::new();
    for (x, y, text) in &plot.point_labels {
        if !(drawable(*x) && drawable(*y)) {
            continue;
        }
        let (w, h) = root
            .estimate_text_size(text, &note_font)
            .map_err(plot_err)?;
        let (w, h) = (w as i32, h as i32);
        // In `root`'s own pixels (a panel's area starts below the image's top).
        let (abs, base) = (chart.backend_coord(&(*x, *y)), root.get_base_pixel());
        let at = (abs.0 - base.0, abs.1 - base.1);
        // Above right of the point, else the first free spot of the others around it (or
        // further up and down), so that labels of neighbouring points stay apart.
        let spots = [
            (offset, -offset - h),
            (offset, offset),
            (-offset - w, -offset - h),
            (-offset - w, offset),
            (offset, -2 * offset - 2 * h),
            (offset, 2 * offset + h),
        ];
        let rect_at = |(dx, dy): (i32, i32)| PixelRect {
            x0: at.0 + dx,
            y0: at.1 + dy,
            x1: at.0 + dx + w,
            y1: at.1 + dy + h,
        };
        let free = |r: &PixelRect| !placed.iter().any(|p| overlap(p, r));
        let rect = spots
            .into_iter()
            .map(rect_at)
            .find(free)
            .unwrap_or(rect_at(spots[0]));
        let anchored = note_font.pos(Pos::new(HPos::Left, VPos::Top));
        root.draw(&Text::new(text.clone(), (rect.x0, rect.y0), anchored))
            .map_err(plot_err)?;
        placed.push(rect);
    }

    if let Some(area) = legend_area {
        draw_legend(&area, &legend, plot_area.y0, s, &legend_font, stroke)?;
    }
    Ok(plot_area)
}

/// Whether two pixel rectangles share a pixel.
fn overlap(a: &PixelRect, b: &PixelRect) -> bool {
    a.x0 < b.x1 && b.x0 < a.x1 && a.y0 < b.y1 && b.y0 < a.y1
}

/// Draws the legend rows in the strip to the right of the chart, starting level with the top of
/// the plotting area (`top`, in image pixels).
pub(crate) fn draw_legend<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    rows: &[(&str, Swatch)],
    top: i32,
    s: f64,
    font: &TextStyle,
    stroke: u32,
) -> Result<(), ReportError> {
    let (_, ay0) = area.get_base_pixel();
    let row_h = (24.0 * s) as i32;
    let x_start = (6.0 * s) as i32;
    let x_end = x_start + (28.0 * s) as i32;
    let text_x = x_end + (8.0 * s) as i32;
    let text_style = font.pos(Pos::new(HPos::Left, VPos::Center));
    for (k, (label, swatch)) in rows.iter().enumerate() {
        let y = top - ay0 + (12.0 * s) as i32 + k as i32 * row_h;
        match swatch {
            Swatch::Line(colour) => {
                area.draw(&PathElement::new(
                    [(x_start, y), (x_end, y)],
                    colour.stroke_width(stroke),
                ))
                .map_err(plot_err)?;
            }
            Swatch::Dashed(colour, (dash, gap)) => {
                let (dash, gap) = ((dash * s).max(1.0) as i32, (gap * s).max(1.0) as i32);
                let mut x = x_start;
                while x < x_end {
                    let to = (x + dash).min(x_end);
                    area.draw(&PathElement::new(
                        [(x, y), (to, y)],
                        colour.stroke_width(stroke),
                    ))
                    .map_err(plot_err)?;
                    x = to + gap;
                }
            }
        }
        area.draw(&Text::new(
            label.to_string(),
            (text_x, y),
            text_style.clone(),
        ))
        .map_err(plot_err)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::canvas::Canvas;
    use crate::figure::draw_png;

    fn draw_loglog(plot: &LogLogPlot, width: u32, height: u32) -> Result<Canvas, ReportError> {
        draw_png(plot, (width, height))
    }

    /// A pixel that is drawn ink (text, axes, data, reference lines), not background or grid.
    fn is_ink(p: [u8; 3]) -> bool {
        p.iter().any(|&c| c < 200)
    }

    fn near(p: [u8; 3], c: RGBColor, tol: u8) -> bool {
        let RGBColor(r, g, b) = c;
        p[0].abs_diff(r) <= tol && p[1].abs_diff(g) <= tol && p[2].abs_diff(b) <= tol
    }

    /// Image row of `y` on a log axis spanning `10^lo_e ..= 10^hi_e` (plotters maps the range
    /// onto the pixel rows `y1 - 1` (bottom) ..= `y0` (top)).
    fn row_of(c: &Canvas, y: f64, lo_e: i32, hi_e: i32) -> i32 {
        let a = c.plot_area;
        let f = (y.log10() - f64::from(lo_e)) / f64::from(hi_e - lo_e);
        ((f64::from(a.y1 - 1)) - f * f64::from(a.y1 - 1 - a.y0)).round() as i32
    }

    fn col_of(c: &Canvas, x: f64, lo_e: i32, hi_e: i32) -> i32 {
        let a = c.plot_area;
        let f = (x.log10() - f64::from(lo_e)) / f64::from(hi_e - lo_e);
        (f64::from(a.x0) + f * f64::from(a.x1 - 1 - a.x0)).round() as i32
    }

    /// Fraction of the interior of plotting-area row `y` whose pixels satisfy `pred`.
    fn row_fraction(c: &Canvas, y: i32, pred: impl Fn([u8; 3]) -> bool) -> f64 {
        let a = c.plot_area;
        let xs = (a.x0 + 3)..(a.x1 - 3);
        let n = xs.len();
        xs.filter(|&x| pred(c.pixel(x, y))).count() as f64 / n as f64
    }

    const XS: [f64; 4] = [1.0, 10.0, 100.0, 1000.0];
    const YS: [f64; 4] = [1e-10, 1e-7, 1e-3, 1.0];

    fn sali_plot<'a>(xs: &'a [f64], ys: &'a [f64]) -> LogLogPlot<'a> {
        LogLogPlot {
            title: "SALI",
            x_label: "t",
            y_label: "SALI",
            lines: vec![Line {
                label: "orbit",
                xs,
                ys,
            }],
            hlines: vec![HLine {
                label: "1e-4",
                y: 1e-4,
            }],
            point_labels: vec![],
            markers: false,
        }
    }

    #[test]
    fn hline_lands_on_its_row_and_background_is_white() {
        let plot = sali_plot(&XS, &YS);
        assert_eq!(axis_decades(&plot).unwrap(), (0, 3, -10, 0));
        let c = draw_loglog(&plot, 800, 600).unwrap();
        let a = c.plot_area;
        assert!(a.x0 > 0 && a.y0 > 0 && a.x1 < 800 && a.y1 < 600, "{a:?}");
        assert!(
            a.width() > 400 && a.height() > 350,
            "plot area too small: {a:?}"
        );

        // The dashed grey line covers most of one row within a few pixels of 1e-4.
        let r = row_of(&c, 1e-4, -10, 0);
        let (best_row, best) = (r - 3..=r + 3)
            .map(|y| (y, row_fraction(&c, y, is_ink)))
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap();
        assert!(best > 0.5, "ink fraction near the 1e-4 row only {best}");
        // ... and it is grey (the data line crosses it at a few pixels only).
        let grey = row_fraction(&c, best_row, |p| {
            is_ink(p) && p[0].abs_diff(p[1]) < 8 && p[1].abs_diff(p[2]) < 8
        });
        assert!(grey > 0.45, "reference line is not grey: {grey}");

        // Half-decade rows away from the reference line are background: white or light grid.
        for y in [10f64.powf(-5.5), 10f64.powf(-2.5), 10f64.powf(-8.5)] {
            let row = row_of(&c, y, -10, 0);
            let ink = row_fraction(&c, row, is_ink);
            let white = row_fraction(&c, row, |p| p == [255, 255, 255]);
            assert!(ink < 0.03, "row for {y:e} has ink fraction {ink}");
            assert!(white > 0.85, "row for {y:e} is only {white} white");
        }
        // Image corners are margin.
        for (x, y) in [(0, 0), (799, 0), (0, 599), (799, 599)] {
            assert_eq!(c.pixel(x, y), [255, 255, 255], "corner ({x}, {y})");
        }
    }

    #[test]
    fn data_line_passes_through_its_points() {
        let plot = sali_plot(&XS, &YS);
        let c = draw_loglog(&plot, 800, 600).unwrap();
        // Midway (in log space) between (10, 1e-7) and (100, 1e-3).
        let (cx, cy) = (col_of(&c, 10f64.powf(1.5), 0, 3), row_of(&c, 1e-5, -10, 0));
        let hit = (cx - 3..=cx + 3)
            .flat_map(|x| (cy - 3..=cy + 3).map(move |y| (x, y)))
            .any(|(x, y)| near(c.pixel(x, y), PALETTE[0], 30));
        assert!(hit, "no line colour near ({cx}, {cy})");
        // Nowhere near the line (upper left of it), no line colour.
        let (fx, fy) = (col_of(&c, 10f64.powf(0.5), 0, 3), row_of(&c, 1e-2, -10, 0));
        assert!(!near(c.pixel(fx, fy), PALETTE[0], 60));
    }

    #[test]
    fn text_is_rendered_with_the_embedded_font() {
        let c = draw_loglog(&sali_plot(&XS, &YS), 800, 600).unwrap();
        let a = c.plot_area;
        // Title above the plotting area.
        let title_ink = (0..a.y0)
            .flat_map(|y| (a.x0..a.x1).map(move |x| (x, y)))
            .filter(|&(x, y)| is_ink(c.pixel(x, y)))
            .count();
        assert!(title_ink > 30, "title has {title_ink} ink pixels");
        // Tick labels left of the axis (well clear of the axis line itself).
        let tick_ink = (a.y0..a.y1)
            .flat_map(|y| (0..a.x0 - 8).map(move |x| (x, y)))
            .filter(|&(x, y)| is_ink(c.pixel(x, y)))
            .count();
        assert!(tick_ink > 100, "y tick labels have {tick_ink} ink pixels");
        // Legend to the right of the plotting area shows the line colour and its label.
        let legend_colour = (a.y0..a.y1)
            .flat_map(|y| (a.x1 + 2..800).map(move |x| (x, y)))
            .filter(|&(x, y)| near(c.pixel(x, y), PALETTE[0], 10))
            .count();
        assert!(
            legend_colour > 20,
            "legend swatch has {legend_colour} pixels"
        );
    }

    #[test]
    fn non_positive_and_non_finite_points_are_skipped() {
        let xs = [1.0, 2.0, 3.0, 4.0, 5.0, 0.0, 6.0];
        let ys = [1e-3, 0.0, -1.0, f64::NAN, f64::INFINITY, 1.0, 1e2];
        let plot = LogLogPlot {
            hlines: vec![HLine {
                label: "bad",
                y: -1.0,
            }],
            ..sali_plot(&xs, &ys)
        };
        // Ranges come from (1, 1e-3) and (6, 1e2) only; the negative reference line is ignored.
        assert_eq!(axis_decades(&plot).unwrap(), (0, 1, -3, 2));
        let c = draw_loglog(&plot, 640, 480).unwrap();
        // Both surviving points are isolated, so they are drawn as dots.
        let (px_, py) = (col_of(&c, 6.0, 0, 1), row_of(&c, 1e2, -3, 2));
        let hit = (px_ - 2..=px_ + 2)
            .flat_map(|x| (py - 2..=py + 2).map(move |y| (x, y)))
            .any(|(x, y)| near(c.pixel(x, y), PALETTE[0], 30));
        assert!(hit, "isolated point (6, 1e2) not drawn");
    }

    #[test]
    fn lines_break_at_skipped_points() {
        let xs = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0];
        let ys = [1.0, 2.0, 0.0, 4.0, f64::NAN, 6.0];
        let segs = drawable_segments(&xs, &ys);
        assert_eq!(
            segs,
            vec![
                vec![(1.0, 1.0), (2.0, 2.0)],
                vec![(4.0, 4.0)],
                vec![(6.0, 6.0)]
            ]
        );
        assert!(drawable_segments(&[-1.0, 1e-320, 1e301], &[1.0, 1.0, 1.0]).is_empty());
    }

    #[test]
    fn hlines_widen_the_y_axis() {
        let xs = [1.0, 100.0];
        let ys = [0.5, 50.0];
        let plot = LogLogPlot {
            hlines: vec![HLine {
                label: "1e-8",
                y: 1e-8,
            }],
            ..sali_plot(&xs, &ys)
        };
        assert_eq!(axis_decades(&plot).unwrap(), (0, 2, -8, 2));
        // A single point exactly on a decade still gets a non-degenerate axis.
        let plot = LogLogPlot {
            hlines: vec![],
            ..sali_plot(&[10.0], &[1.0])
        };
        assert_eq!(axis_decades(&plot).unwrap(), (0, 2, -1, 1));
        draw_loglog(&plot, 400, 300).unwrap();
    }

    #[test]
    fn all_nan_input_is_empty_data() {
        let nan = [f64::NAN; 3];
        let plot = sali_plot(&XS[..3], &nan);
        assert!(matches!(
            draw_loglog(&plot, 800, 600),
            Err(ReportError::EmptyData(_))
        ));
        let negative = [-1.0, 0.0, -3.0];
        assert!(matches!(
            draw_loglog(&sali_plot(&XS[..3], &negative), 800, 600),
            Err(ReportError::EmptyData(_))
        ));
        // Reference lines alone are not data.
        let only_hlines = LogLogPlot {
            lines: vec![],
            ..sali_plot(&[], &[])
        };
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("empty.png");
        assert!(matches!(
            render_loglog(&only_hlines, &path, 800, 600),
            Err(ReportError::EmptyData(_))
        ));
        assert!(!path.exists(), "no file is written for an empty plot");
    }

    #[test]
    fn smallest_size_and_empty_texts_render() {
        let plot = LogLogPlot {
            title: "",
            x_label: "",
            y_label: "",
            lines: vec![
                Line {
                    label: "",
                    xs: &XS,
                    ys: &YS,
                },
                Line {
                    label: "a label far too long to fit into the legend strip of a tiny image",
                    xs: &XS,
                    ys: &XS,
                },
            ],
            ..sali_plot(&XS, &YS)
        };
        for (w, h) in [(160, 120), (3000, 200), (200, 2000)] {
            let c = draw_loglog(&plot, w, h).unwrap();
            assert!(c.plot_area.width() > 0 && c.plot_area.height() > 0);
        }
    }

    #[test]
    fn malformed_requests_are_errors() {
        assert!(matches!(
            draw_loglog(&sali_plot(&XS, &YS[..3]), 800, 600),
            Err(ReportError::Plot(_))
        ));
        assert!(matches!(
            draw_loglog(&sali_plot(&XS, &YS), 10, 10),
            Err(ReportError::Plot(_))
        ));
    }

    /// The texts of an SVG document, in order.
    fn svg_texts(svg: &str) -> Vec<&str> {
        svg.split("<text")
            .skip(1)
            .filter_map(|t| t.split('>').nth(1)?.split('<').next())
            .map(str::trim)
            .collect()
    }

    #[test]
    fn panels_share_one_time_axis_and_draw_the_same_in_svg_and_png() {
        use crate::figure::counting::{png_counts, svg_counts};
        use crate::figure::draw_svg;
        let late_x = [1e3, 1e4];
        let late_y = [1e-2, 1e-3];
        let panels = Panels {
            panels: vec![
                sali_plot(&XS, &YS),
                LogLogPlot {
                    title: "",
                    ..sali_plot(&late_x, &late_y)
                },
            ],
        };
        let size = (800, 900);
        let svg = draw_svg(&panels, size).unwrap();
        assert_eq!(svg_counts(&svg), png_counts(&panels, size));
        // The first panel's data end at 1e3, the second's start there: both time axes run
        // from 1e0 to 1e4 (no y axis reaches 1e1).
        let texts = svg_texts(&svg);
        for label in ["1e1", "1e4"] {
            assert_eq!(
                texts.iter().filter(|t| **t == label).count(),
                2,
                "{texts:?}"
            );
        }
        let first = draw_png(&panels, size).unwrap().plot_area;
        assert!(
            first.y1 < 450,
            "the first panel lies in the upper half: {first:?}"
        );
    }

    #[test]
    fn labels_of_neighbouring_points_keep_apart() {
        use crate::figure::draw_svg;
        let plot = LogLogPlot {
            point_labels: vec![
                (10.0, 1e-7, "first label".to_string()),
                (10.5, 1.05e-7, "second label".to_string()),
                (11.0, 1.1e-7, "third label".to_string()),
            ],
            ..sali_plot(&XS, &YS)
        };
        let svg = draw_svg(&plot, (800, 600)).unwrap();
        // Each label's text element and its (x, y).
        let spot = |label: &str| -> (i32, i32) {
            let start = svg[..svg.find(label).unwrap()].rfind("<text").unwrap();
            let tag = &svg[start..];
            let attr = |name: &str| -> i32 {
                let from = tag.find(&format!(" {name}=\"")).unwrap() + name.len() + 3;
                tag[from..].split('"').next().unwrap().parse().unwrap()
            };
            (attr("x"), attr("y"))
        };
        let spots = [
            spot("first label"),
            spot("second label"),
            spot("third label"),
        ];
        for (k, a) in spots.iter().enumerate() {
            for b in &spots[k + 1..] {
                // Apart by a line of 11-pixel text, or side by side by a label's width (11
                // characters, 4 pixels each at the least).
                assert!(
                    (a.1 - b.1).abs() >= 11 || (a.0 - b.0).abs() >= 44,
                    "{spots:?}"
                );
            }
        }
    }

    #[test]
    fn panels_need_a_drawable_panel_each() {
        let nan = [f64::NAN; 4];
        let empty = Panels { panels: vec![] };
        assert!(matches!(
            draw_png(&empty, (800, 600)),
            Err(ReportError::EmptyData(_))
        ));
        let one_empty = Panels {
            panels: vec![sali_plot(&XS, &YS), sali_plot(&XS, &nan)],
        };
        assert!(draw_png(&one_empty, (800, 600)).is_err());
    }

    #[test]
    fn png_file_has_png_signature() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sali.png");
        let plot = LogLogPlot {
            markers: true,
            point_labels: vec![(10.0, 1e-7, "h = 0.1".to_string())],
            ..sali_plot(&XS, &YS)
        };
        render_loglog(&plot, &path, 640, 480).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert!(bytes.len() > 1000);
        assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");

        let wrong = dir.path().join("sali.jpg");
        assert!(matches!(
            render_loglog(&plot, &wrong, 640, 480),
            Err(ReportError::Plot(_))
        ));
        let missing_dir = dir.path().join("no/such/dir/sali.png");
        assert!(matches!(
            render_loglog(&plot, &missing_dir, 640, 480),
            Err(ReportError::Io(_))
        ));
    }

    #[test]
    fn decades_and_labels() {
        assert_eq!((decade_floor(1e-10), decade_ceil(1e-10)), (-10, -10));
        assert_eq!((decade_floor(3e-5), decade_ceil(3e-5)), (-5, -4));
        assert_eq!((decade_floor(1.0), decade_ceil(1.0)), (0, 0));
        assert_eq!((decade_floor(0.999), decade_ceil(0.999)), (-1, 0));
        assert_eq!((decade_floor(1.0001), decade_ceil(1.0001)), (0, 1));
        assert_eq!((decade_floor(1e300), decade_ceil(1e-300)), (300, -300));
        assert_eq!(decade_label(1e-4), "1e-4");
        assert_eq!(decade_label(1.0), "1e0");
        assert_eq!(decade_label(1000.0), "1e3");
        assert_eq!(decade(-4), 1e-4);
    }

    #[test]
    fn ticks_thin_out_on_long_axes() {
        // Ten decades fit: every decade labelled, no minor lines.
        let t = log_ticks(-10, 0, 13);
        assert_eq!(t.bold.len(), 11);
        assert!(t.light.is_empty());
        // Three decades: every decade labelled plus 2..9 minor lines.
        let t = log_ticks(0, 3, 8);
        assert_eq!(t.bold, vec![1.0, 10.0, 100.0, 1000.0]);
        assert_eq!(t.light.len(), 24);
        // 280 decades: labels every 50 decades, minor lines every 10.
        let t = log_ticks(-280, 0, 13);
        let labels: Vec<String> = t.bold.iter().map(|&v| decade_label(v)).collect();
        assert_eq!(
            labels,
            ["1e-250", "1e-200", "1e-150", "1e-100", "1e-50", "1e0"]
        );
        assert_eq!(t.light.len(), 29 - 6);
    }
}
