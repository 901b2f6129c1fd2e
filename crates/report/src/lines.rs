//! Line plots on linear axes (percentages against energy, ...): the same look as the log-log
//! plots (palette, font, legend to the right), for quantities that may be zero.

use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;

use crate::canvas::{PixelRect, FONT_FAMILY};
use crate::error::{plot_err, ReportError};
use crate::figure::{write_figure, Figure};
use crate::loglog::{check_lengths, draw_legend, Line, Swatch, PALETTE};

/// A plot with linear x and y axes.
#[derive(Clone, Debug)]
pub struct LinePlot<'a> {
    /// Title above the plot.
    pub title: &'a str,
    /// Label of the x axis.
    pub x_label: &'a str,
    /// Label of the y axis.
    pub y_label: &'a str,
    /// Lines (or point sets) drawn.
    pub lines: Vec<Line<'a>>,
    /// The y axis's span; `None`: the data's, padded.
    pub y_range: Option<(f64, f64)>,
    /// Points as dots, unjoined (a surface of section), instead of joined markers.
    pub dots: bool,
}

/// Renders `plot` as a `width` x `height` image at `path`, PNG or SVG by its extension. Points
/// with a non-finite coordinate are skipped; [`ReportError::EmptyData`] when none is left.
pub fn render_lines(
    plot: &LinePlot,
    path: &Path,
    width: u32,
    height: u32,
) -> Result<(), ReportError> {
    write_figure(plot, path, (width, height))
}

fn finite_points<'a>(line: &Line<'a>) -> Vec<(f64, f64)> {
    line.xs
        .iter()
        .zip(line.ys)
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .map(|(&x, &y)| (x, y))
        .collect()
}

/// The span of `values`, padded by 5 % (a single value gets ±1, or ±5 % of itself).
fn padded(values: impl Iterator<Item = f64>) -> Option<(f64, f64)> {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    if !lo.is_finite() {
        return None;
    }
    let pad = if hi > lo {
        0.05 * (hi - lo)
    } else {
        (0.05 * lo.abs()).max(1.0)
    };
    Some((lo - pad, hi + pad))
}

/// Every line's finite points and the axes' spans.
fn points_and_ranges(plot: &LinePlot) -> Result<(Vec<Points>, Ranges), ReportError> {
    check_lengths(&plot.lines)?;
    let points: Vec<Vec<(f64, f64)>> = plot.lines.iter().map(finite_points).collect();
    let all = || points.iter().flatten();
    let x_range = padded(all().map(|p| p.0)).ok_or(ReportError::EmptyData("no finite point"))?;
    let y_range = match plot.y_range {
        Some(r) if r.0 < r.1 => r,
        Some(r) => return Err(ReportError::Plot(format!("empty y range {r:?}"))),
        None => padded(all().map(|p| p.1)).ok_or(ReportError::EmptyData("no finite point"))?,
    };
    Ok((points, (x_range, y_range)))
}

impl Figure for LinePlot<'_> {
    fn validate(&self) -> Result<(), ReportError> {
        points_and_ranges(self).map(|_| ())
    }

    fn draw<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
        size: (u32, u32),
    ) -> Result<PixelRect, ReportError> {
        let (points, ranges) = points_and_ranges(self)?;
        paint(self, &points, ranges, root, size)
    }
}

type Ranges = ((f64, f64), (f64, f64));
type Points = Vec<(f64, f64)>;

fn paint<DB: DrawingBackend>(
    plot: &LinePlot,
    points: &[Vec<(f64, f64)>],
    ((x_lo, x_hi), (y_lo, y_hi)): Ranges,
    root: &DrawingArea<DB, Shift>,
    (width, height): (u32, u32),
) -> Result<PixelRect, ReportError> {
    let s = (f64::from(width.min(height)) / 600.0).clamp(0.5, 3.0);
    let px = |v: f64| (v * s).round().max(1.0) as u32;
    let font = |size: f64| (FONT_FAMILY, size * s).into_font().color(&BLACK);
    let stroke = px(2.0);
    let legend: Vec<(&str, Swatch)> = plot
        .lines
        .iter()
        .enumerate()
        .filter(|(k, l)| !l.label.is_empty() && !points[*k].is_empty())
        .map(|(k, l)| (l.label, Swatch::Line(PALETTE[k % PALETTE.len()])))
        .collect();
    let legend_font = font(14.0);
    let mut text_w = 0;
    for (label, _) in &legend {
        let (w, _) = root
            .estimate_text_size(label, &legend_font)
            .map_err(plot_err)?;
        text_w = text_w.max(w);
    }
    let legend_w = if legend.is_empty() {
        0
    } else {
        (text_w + (64.0 * s) as u32).min(width * 35 / 100)
    };
    let (chart_area, legend_area) = root.split_horizontally(width - legend_w);
    let mut chart = ChartBuilder::on(&chart_area)
        .caption(plot.title, font(22.0))
        .margin(px(14.0))
        .x_label_area_size(px(50.0))
        .y_label_area_size(px(72.0))
        .build_cartesian_2d(x_lo..x_hi, y_lo..y_hi)
        .map_err(plot_err)?;
    chart
        .configure_mesh()
        .x_desc(plot.x_label)
        .y_desc(plot.y_label)
        .label_style(font(13.0))
        .axis_desc_style(font(16.0))
        .bold_line_style(RGBColor(215, 215, 215))
        .light_line_style(RGBColor(238, 238, 238))
        .axis_style(BLACK)
        .set_all_tick_mark_size(px(5.0))
        .draw()
        .map_err(plot_err)?;
    let plot_area = PixelRect::from_ranges(chart.plotting_area().get_pixel_range());
    for (k, pts) in points.iter().enumerate() {
        let colour = PALETTE[k % PALETTE.len()];
        if plot.dots {
            chart
                .draw_series(
                    pts.iter()
                        .map(|&p| Circle::new(p, px(1.0) as i32, colour.filled())),
                )
                .map_err(plot_err)?;
            continue;
        }
        chart
            .draw_series(LineSeries::new(
                pts.iter().copied(),
                colour.stroke_width(stroke),
            ))
            .map_err(plot_err)?;
        chart
            .draw_series(
                pts.iter()
                    .map(|&p| Circle::new(p, px(3.5) as i32, colour.filled())),
            )
            .map_err(plot_err)?;
    }
    if !legend.is_empty() {
        draw_legend(&legend_area, &legend, plot_area.y0, s, &legend_font, stroke)?;
    }
    Ok(plot_area)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::canvas::Canvas;
    use crate::figure::draw_png;

    fn draw_lines(plot: &LinePlot, width: u32, height: u32) -> Result<Canvas, ReportError> {
        draw_png(plot, (width, height))
    }

    #[test]
    fn zero_values_are_drawn_and_lines_pass_through_their_points() {
        let (xs, ys) = ([0.05, 0.1, 0.15], [0.0, 50.0, 100.0]);
        let plot = LinePlot {
            title: "t",
            x_label: "H",
            y_label: "%",
            lines: vec![Line {
                label: "regular",
                xs: &xs,
                ys: &ys,
            }],
            y_range: Some((0.0, 100.0)),
            dots: false,
        };
        let c = draw_lines(&plot, 600, 400).unwrap();
        let a = c.plot_area;
        // The middle point (0.1, 50) lies at the centre of the plotting area in x (the x span
        // is padded symmetrically) and halfway up in y: its marker is the line's colour.
        let (cx, cy) = ((a.x0 + a.x1) / 2, (a.y0 + a.y1) / 2);
        assert_eq!(c.pixel(cx, cy), [PALETTE[0].0, PALETTE[0].1, PALETTE[0].2]);
        // The y = 0 point sits on the bottom edge, still inside the image.
        assert!(a.y1 < 400);
    }

    #[test]
    fn lines_without_a_finite_point_have_nothing_to_draw() {
        let (xs, ys) = ([f64::NAN], [1.0]);
        let plot = LinePlot {
            title: "t",
            x_label: "x",
            y_label: "y",
            lines: vec![Line {
                label: "a",
                xs: &xs,
                ys: &ys,
            }],
            y_range: None,
            dots: false,
        };
        assert!(matches!(
            draw_lines(&plot, 600, 400),
            Err(ReportError::EmptyData(_))
        ));
    }
}
