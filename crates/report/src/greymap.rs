//! Grey-scale maps of a scalar field over a 2-D grid (e.g. an indicator over the (q2, p2) plane).

use std::path::Path;

use plotters::backend::BitMapBackend;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use crate::canvas::{ensure_font, white_buffer, Canvas, PixelRect, FONT_FAMILY};
use crate::error::{plot_err, ReportError};

/// Colour of cells whose value is NaN (grey levels are reserved for finite values).
pub const NAN_COLOUR: [u8; 3] = [220, 40, 40];

/// Size in pixels of the PNG written by [`render_grey_map_png`].
pub const GREY_MAP_SIZE: (u32, u32) = (900, 760);

/// Grey-scale map of a 2-D field, row-major `values[i * ny + j]` with i along x (q2) and j along
/// y (p2), y increasing upward; NaN cells are drawn in [`NAN_COLOUR`]; values are clamped to
/// `[vmin, vmax]` (black = vmin, white = vmax, so +inf is white and -inf black); a colour bar and
/// axis labels are added. The image is [`GREY_MAP_SIZE`] pixels and `path` must end in `.png`.
///
/// `x_range` and `y_range` are the outer edges of the grid: cell `(i, j)` covers
/// `x0 + i·dx ..= x0 + (i+1)·dx` with `dx = (x1 - x0) / nx` (and likewise in y). A field
/// sampled at the points `x0 + (i + 1/2)·dx` is therefore drawn centred on its samples. Each
/// pixel shows the cell under its centre (no smoothing).
///
/// Errors: [`ReportError::EmptyData`] if `nx` or `ny` is zero; [`ReportError::Plot`] if
/// `values.len() != nx * ny`, or a range is not finite and increasing, or `vmin >= vmax`.
#[allow(clippy::too_many_arguments)]
pub fn render_grey_map_png(
    values: &[f64],
    nx: usize,
    ny: usize,
    x_range: (f64, f64),
    y_range: (f64, f64),
    vmin: f64,
    vmax: f64,
    title: &str,
    x_label: &str,
    y_label: &str,
    path: &Path,
) -> Result<(), ReportError> {
    let map = GreyMap {
        values,
        nx,
        ny,
        x_range,
        y_range,
        vmin,
        vmax,
        title,
        x_label,
        y_label,
    };
    draw_grey_map(&map, GREY_MAP_SIZE.0, GREY_MAP_SIZE.1)?.write_png(path)
}

/// The arguments of [`render_grey_map_png`], bundled.
pub(crate) struct GreyMap<'a> {
    pub values: &'a [f64],
    pub nx: usize,
    pub ny: usize,
    pub x_range: (f64, f64),
    pub y_range: (f64, f64),
    pub vmin: f64,
    pub vmax: f64,
    pub title: &'a str,
    pub x_label: &'a str,
    pub y_label: &'a str,
}

fn check_range(name: &str, (lo, hi): (f64, f64)) -> Result<(), ReportError> {
    if lo.is_finite() && hi.is_finite() && lo < hi {
        Ok(())
    } else {
        Err(ReportError::Plot(format!(
            "{name} must be finite and increasing, got ({lo}, {hi})"
        )))
    }
}

impl GreyMap<'_> {
    fn validate(&self) -> Result<(), ReportError> {
        if self.nx == 0 || self.ny == 0 {
            return Err(ReportError::EmptyData("grey map has no cells"));
        }
        if self.nx.checked_mul(self.ny) != Some(self.values.len()) {
            return Err(ReportError::Plot(format!(
                "grey map of {} x {} cells given {} values",
                self.nx,
                self.ny,
                self.values.len()
            )));
        }
        check_range("x range", self.x_range)?;
        check_range("y range", self.y_range)?;
        check_range("colour range (vmin, vmax)", (self.vmin, self.vmax))
    }

    /// The colour of a value.
    fn colour(&self, v: f64) -> RGBColor {
        if v.is_nan() {
            let [r, g, b] = NAN_COLOUR;
            return RGBColor(r, g, b);
        }
        grey((v - self.vmin) / (self.vmax - self.vmin))
    }
}

/// Grey level for a position `t` in the colour range (clamped to `[0, 1]`).
fn grey(t: f64) -> RGBColor {
    let g = (t.clamp(0.0, 1.0) * 255.0).round() as u8;
    RGBColor(g, g, g)
}

/// Index of the cell (out of `n`) under pixel `k` (out of `len`), by pixel centre.
fn cell_of(k: i32, len: i32, n: usize) -> usize {
    let f = (f64::from(k) + 0.5) / f64::from(len);
    ((f * n as f64) as usize).min(n - 1)
}

/// Tick label of a colour-bar value: short, without trailing zeros.
pub(crate) fn value_label(v: f64) -> String {
    if v == 0.0 {
        return "0".to_string();
    }
    let trim = |s: String| -> String {
        if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            s
        }
    };
    if v.abs() >= 1e4 || v.abs() < 1e-3 {
        let s = format!("{v:.2e}");
        match s.split_once('e') {
            Some((mantissa, exp)) => format!("{}e{exp}", trim(mantissa.to_string())),
            None => s,
        }
    } else {
        trim(format!("{v:.3}"))
    }
}

/// Draws the map onto a fresh in-memory canvas of `width` x `height` pixels.
pub(crate) fn draw_grey_map(map: &GreyMap, width: u32, height: u32) -> Result<Canvas, ReportError> {
    ensure_font()?;
    map.validate()?;
    let mut rgb = white_buffer(width, height)?;
    let (plot_area, bar) = paint(map, &mut rgb, width, height)?;
    Ok(Canvas {
        rgb,
        width,
        height,
        plot_area,
        colour_bar: Some(bar),
    })
}

fn paint(
    map: &GreyMap,
    rgb: &mut [u8],
    width: u32,
    height: u32,
) -> Result<(PixelRect, PixelRect), ReportError> {
    let s = (f64::from(width.min(height)) / 700.0).clamp(0.4, 3.0);
    let px = |v: f64| (v * s).round().max(1.0) as u32;
    let title_font = (FONT_FAMILY, 22.0 * s).into_font().color(&BLACK);
    let desc_font = (FONT_FAMILY, 16.0 * s).into_font().color(&BLACK);
    let tick_font = (FONT_FAMILY, 13.0 * s).into_font().color(&BLACK);

    let root = BitMapBackend::with_buffer(rgb, (width, height)).into_drawing_area();
    root.fill(&WHITE).map_err(plot_err)?;
    let bar_w = px(120.0).min(width / 4);
    let (map_area, bar_area) = root.split_horizontally(width - bar_w);

    let mut chart = ChartBuilder::on(&map_area)
        .caption(map.title, title_font)
        .margin(px(14.0))
        .x_label_area_size(px(55.0))
        .y_label_area_size(px(75.0))
        .build_cartesian_2d(map.x_range.0..map.x_range.1, map.y_range.0..map.y_range.1)
        .map_err(plot_err)?;
    chart
        .configure_mesh()
        .disable_mesh()
        .x_desc(map.x_label)
        .y_desc(map.y_label)
        .label_style(tick_font.clone())
        .axis_desc_style(desc_font)
        .axis_style(BLACK)
        .set_all_tick_mark_size(px(5.0))
        .draw()
        .map_err(plot_err)?;
    let area = PixelRect::from_ranges(chart.plotting_area().get_pixel_range());

    // One pixel at a time: the cost depends on the image size, not on the grid size.
    for py in area.y0..area.y1 {
        // Rows count downward, the y index upward.
        let j = map.ny - 1 - cell_of(py - area.y0, area.height(), map.ny);
        for px_ in area.x0..area.x1 {
            let i = cell_of(px_ - area.x0, area.width(), map.nx);
            let colour = map.colour(map.values[i * map.ny + j]);
            root.draw_pixel((px_, py), &colour).map_err(plot_err)?;
        }
    }

    // Colour bar: its plotting area is level with the map's.
    let top = area.y0.max(0) as u32;
    let bottom = (height as i32 - area.y1).max(0) as u32;
    let mut bar_chart = ChartBuilder::on(&bar_area)
        .margin_top(top)
        .margin_bottom(bottom)
        .margin_left(px(10.0))
        .margin_right(px(6.0))
        .right_y_label_area_size((bar_w / 2).max(px(40.0)))
        .build_cartesian_2d(0f64..1f64, map.vmin..map.vmax)
        .map_err(plot_err)?;
    let fmt = |v: &f64| value_label(*v);
    bar_chart
        .configure_mesh()
        .disable_mesh()
        .disable_x_axis()
        .y_label_formatter(&fmt)
        .label_style(tick_font.clone())
        .axis_style(BLACK)
        .set_all_tick_mark_size(px(5.0))
        .draw()
        .map_err(plot_err)?;
    let bar = PixelRect::from_ranges(bar_chart.plotting_area().get_pixel_range());
    for py in bar.y0..bar.y1 {
        let t = 1.0 - (f64::from(py - bar.y0) + 0.5) / f64::from(bar.height());
        let colour = grey(t);
        for px_ in bar.x0..bar.x1 {
            root.draw_pixel((px_, py), &colour).map_err(plot_err)?;
        }
    }
    root.draw(&Rectangle::new(
        [(bar.x0, bar.y0), (bar.x1 - 1, bar.y1 - 1)],
        BLACK.stroke_width(1),
    ))
    .map_err(plot_err)?;

    // A NaN swatch under the bar, when the field has NaN cells.
    if map.values.iter().any(|v| v.is_nan()) {
        let side = px(14.0) as i32;
        let y = bar.y1 + px(30.0) as i32;
        let [r, g, b] = NAN_COLOUR;
        root.draw(&Rectangle::new(
            [(bar.x0, y), (bar.x0 + side, y + side)],
            RGBColor(r, g, b).filled(),
        ))
        .map_err(plot_err)?;
        root.draw(&Text::new(
            "NaN",
            (bar.x0 + side + px(6.0) as i32, y + side / 2),
            tick_font.pos(Pos::new(HPos::Left, VPos::Center)),
        ))
        .map_err(plot_err)?;
    }
    root.present().map_err(plot_err)?;
    Ok((area, bar))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map<'a>(values: &'a [f64], nx: usize, ny: usize, vmin: f64, vmax: f64) -> GreyMap<'a> {
        GreyMap {
            values,
            nx,
            ny,
            x_range: (0.0, 1.0),
            y_range: (0.0, 1.0),
            vmin,
            vmax,
            title: "map",
            x_label: "q2",
            y_label: "p2",
        }
    }

    fn draw(m: &GreyMap) -> Canvas {
        draw_grey_map(m, 700, 600).unwrap()
    }

    /// Pixel at fractions `(fx, fy)` of the plotting area, `fy` measured upward from the bottom.
    fn at(c: &Canvas, fx: f64, fy: f64) -> [u8; 3] {
        let a = c.plot_area;
        let x = a.x0 + (fx * f64::from(a.width())) as i32;
        let y = a.y1 - 1 - (fy * f64::from(a.height())) as i32;
        c.pixel(x, y)
    }

    #[test]
    fn two_by_two_field_fills_the_right_quadrants() {
        // values[i * ny + j]: (0,0) vmin, (0,1) vmax, (1,0) NaN, (1,1) mid.
        let values = [-3.0, 5.0, f64::NAN, 1.0];
        let c = draw(&map(&values, 2, 2, -3.0, 5.0));
        let a = c.plot_area;
        assert!(a.width() > 300 && a.height() > 300, "{a:?}");
        assert_eq!(at(&c, 0.25, 0.25), [0, 0, 0], "bottom left = vmin");
        assert_eq!(at(&c, 0.25, 0.75), [255, 255, 255], "top left = vmax");
        assert_eq!(at(&c, 0.75, 0.25), NAN_COLOUR, "bottom right = NaN");
        let mid = at(&c, 0.75, 0.75);
        assert!(
            mid.iter().all(|&g| g.abs_diff(128) <= 1),
            "top right = mid grey, got {mid:?}"
        );
        // The cells meet in the middle of the plotting area (to within a pixel or two).
        let (xm, ym) = ((a.x0 + a.x1) / 2, (a.y0 + a.y1) / 2);
        assert_eq!(c.pixel(xm - 3, a.y0 + 5), [255, 255, 255]);
        assert_eq!(c.pixel(xm + 3, a.y0 + 5), [128, 128, 128]);
        assert_eq!(c.pixel(a.x0 + 5, ym - 3), [255, 255, 255]);
        assert_eq!(c.pixel(a.x0 + 5, ym + 3), [0, 0, 0]);
    }

    #[test]
    fn values_are_clamped_to_the_colour_range() {
        let values = [-10.0, 10.0, f64::INFINITY, f64::NEG_INFINITY];
        let c = draw(&map(&values, 2, 2, 0.0, 1.0));
        assert_eq!(at(&c, 0.25, 0.25), [0, 0, 0]);
        assert_eq!(at(&c, 0.25, 0.75), [255, 255, 255]);
        assert_eq!(at(&c, 0.75, 0.25), [255, 255, 255]);
        assert_eq!(at(&c, 0.75, 0.75), [0, 0, 0]);
    }

    #[test]
    fn index_i_runs_along_x_and_j_upward() {
        // nx = 3, ny = 1: value = i, so grey rises left to right.
        let c = draw(&map(&[0.0, 1.0, 2.0], 3, 1, 0.0, 2.0));
        assert_eq!(at(&c, 1.0 / 6.0, 0.5), [0, 0, 0]);
        assert_eq!(at(&c, 0.5, 0.5), [128, 128, 128]);
        assert_eq!(at(&c, 5.0 / 6.0, 0.5), [255, 255, 255]);
        // nx = 1, ny = 3: value = j, so grey rises bottom to top.
        let c = draw(&map(&[0.0, 1.0, 2.0], 1, 3, 0.0, 2.0));
        assert_eq!(at(&c, 0.5, 1.0 / 6.0), [0, 0, 0]);
        assert_eq!(at(&c, 0.5, 0.5), [128, 128, 128]);
        assert_eq!(at(&c, 0.5, 5.0 / 6.0), [255, 255, 255]);
    }

    #[test]
    fn colour_bar_runs_from_black_to_white() {
        let c = draw(&map(&[0.0, 1.0, 0.5, 0.25], 2, 2, 0.0, 1.0));
        let bar = c.colour_bar.expect("grey map has a colour bar");
        let a = c.plot_area;
        assert!(bar.x0 > a.x1, "bar {bar:?} is right of the map {a:?}");
        assert_eq!((bar.y0, bar.y1), (a.y0, a.y1), "bar is level with the map");
        let x = (bar.x0 + bar.x1) / 2;
        let column: Vec<u8> = (bar.y0 + 1..bar.y1 - 1).map(|y| c.pixel(x, y)[0]).collect();
        assert!(
            column[0] >= 250 && *column.last().unwrap() <= 5,
            "{column:?}"
        );
        assert!(column.windows(2).all(|w| w[0] >= w[1]), "not monotone");
    }

    #[test]
    fn nan_swatch_only_when_there_are_nan_cells() {
        let count_nan_outside_map = |c: &Canvas| {
            let a = c.plot_area;
            (0..c.height as i32)
                .flat_map(|y| (a.x1..c.width as i32).map(move |x| (x, y)))
                .filter(|&(x, y)| c.pixel(x, y) == NAN_COLOUR)
                .count()
        };
        let with_nan = draw(&map(&[0.0, f64::NAN], 1, 2, 0.0, 1.0));
        assert!(count_nan_outside_map(&with_nan) > 50);
        let without = draw(&map(&[0.0, 1.0], 1, 2, 0.0, 1.0));
        assert_eq!(count_nan_outside_map(&without), 0);
    }

    #[test]
    fn malformed_requests_are_errors_not_panics() {
        let v = [0.0; 4];
        assert!(matches!(
            draw_grey_map(&map(&[], 0, 3, 0.0, 1.0), 700, 600),
            Err(ReportError::EmptyData(_))
        ));
        assert!(matches!(
            draw_grey_map(&map(&v, 3, 2, 0.0, 1.0), 700, 600),
            Err(ReportError::Plot(_))
        ));
        assert!(matches!(
            draw_grey_map(&map(&v, usize::MAX, 2, 0.0, 1.0), 700, 600),
            Err(ReportError::Plot(_))
        ));
        for (vmin, vmax) in [
            (1.0, 1.0),
            (2.0, 1.0),
            (f64::NAN, 1.0),
            (0.0, f64::INFINITY),
        ] {
            assert!(matches!(
                draw_grey_map(&map(&v, 2, 2, vmin, vmax), 700, 600),
                Err(ReportError::Plot(_))
            ));
        }
        let bad_x = GreyMap {
            x_range: (1.0, 1.0),
            ..map(&v, 2, 2, 0.0, 1.0)
        };
        assert!(matches!(
            draw_grey_map(&bad_x, 700, 600),
            Err(ReportError::Plot(_))
        ));
    }

    #[test]
    fn empty_texts_and_large_grids_render() {
        let (nx, ny) = (1500, 1100);
        let values: Vec<f64> = (0..nx * ny).map(|k| (k % 13) as f64).collect();
        let m = GreyMap {
            title: "",
            x_label: "",
            y_label: "",
            ..map(&values, nx, ny, 0.0, 12.0)
        };
        draw_grey_map(&m, GREY_MAP_SIZE.0, GREY_MAP_SIZE.1).unwrap();
    }

    #[test]
    fn png_file_has_png_signature() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("map.png");
        let values: Vec<f64> = (0..50 * 40).map(|k| f64::from(k % 7) - 3.0).collect();
        render_grey_map_png(
            &values,
            50,
            40,
            (-0.5, 0.5),
            (-0.4, 0.4),
            -3.0,
            3.0,
            "log10 SALI",
            "q2",
            "p2",
            &path,
        )
        .unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
    }

    #[test]
    fn colour_bar_labels_are_short() {
        assert_eq!(value_label(0.0), "0");
        assert_eq!(value_label(-2.0), "-2");
        assert_eq!(value_label(0.25), "0.25");
        assert_eq!(value_label(-16.0), "-16");
        assert_eq!(value_label(1e-5), "1e-5");
        assert_eq!(value_label(12345.0), "1.23e4");
    }
}
