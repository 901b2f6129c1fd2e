//! Maps of cells over a 2-D grid, each cell coloured by its category: the class of every cell
//! of a section with a legend, or a quantity in bands (log₁₀ SALI) with a stepped colour bar.
//! PNG or SVG from the same drawing ([`crate::figure`]).

use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use crate::canvas::{PixelRect, FONT_FAMILY};
use crate::error::{plot_err, ReportError};
use crate::figure::{draw_png, write_figure, write_figure_at, Figure};

/// Size in pixels of the images [`render_cell_map`] writes.
pub const CELL_MAP_SIZE: (u32, u32) = (1100, 760);

/// One category of a [`CellMap`]: its legend text and colour.
#[derive(Clone, Copy, Debug)]
pub struct Category<'a> {
    /// Legend text.
    pub label: &'a str,
    /// Colour as RGB.
    pub colour: [u8; 3],
}

/// Bands of a quantity: category k (< `edges.len() − 1`) holds the values from `edges[k]` to
/// `edges[k + 1]`, drawn as a stepped colour bar labelled `label` instead of in the legend.
#[derive(Clone, Copy, Debug)]
pub struct Scale<'a> {
    /// Label of the colour bar.
    pub label: &'a str,
    /// Increasing, finite.
    pub edges: &'a [f64],
}

/// A field of categories over an `nx` × `ny` grid: `codes[i * ny + j]` is the index in
/// `categories` of cell (i, j), i along x, j along y (upward). `x_range` and `y_range` are the
/// grid's outer edges. The legend lists the categories in their order (after the colour bar of
/// the bands of `scale`, when there is one).
#[derive(Clone, Copy, Debug)]
pub struct CellMap<'a> {
    /// Category index of each cell, `codes[i * ny + j]` for cell (i, j).
    pub codes: &'a [u8],
    /// The categories the codes index.
    pub categories: &'a [Category<'a>],
    /// Cells along x.
    pub nx: usize,
    /// Cells along y.
    pub ny: usize,
    /// Outer edges of the grid along x.
    pub x_range: (f64, f64),
    /// Outer edges of the grid along y.
    pub y_range: (f64, f64),
    /// Title above the map.
    pub title: &'a str,
    /// Label of the x axis.
    pub x_label: &'a str,
    /// Label of the y axis.
    pub y_label: &'a str,
    /// Bands of a quantity drawn as a colour bar (`None`: legend only).
    pub scale: Option<Scale<'a>>,
}

/// Writes `map` at `path` as PNG or SVG (by the extension), [`CELL_MAP_SIZE`] pixels. Each
/// cell is one filled rectangle between the pixel edges nearest its own, runs of equal cells
/// along y merged, so both formats show the same cells at the same pixels.
///
/// Errors: [`ReportError::EmptyData`] for an empty grid; [`ReportError::Plot`] when the codes
/// do not fill the grid, a code has no category, or a range is not finite and increasing.
pub fn render_cell_map(map: &CellMap, path: &Path) -> Result<(), ReportError> {
    write_figure(map, path, CELL_MAP_SIZE)
}

/// The resolution at which [`CELL_MAP_SIZE`] is the map's size (11 × 7.6 inches).
pub const CELL_MAP_DPI: u32 = 100;

/// The resolutions [`render_cell_map_at`] takes.
pub const CELL_MAP_DPI_RANGE: std::ops::RangeInclusive<u32> = 50..=600;

/// [`render_cell_map`] with a PNG of `dpi` (in [`CELL_MAP_DPI_RANGE`]): [`CELL_MAP_SIZE`] ×
/// dpi / [`CELL_MAP_DPI`] pixels, text and lines scaled alike, the resolution recorded in the
/// file, so the map prints at the same 11 × 7.6 inches with finer pixels. An SVG is drawn at
/// the default size (it scales without loss).
pub fn render_cell_map_at(map: &CellMap, path: &Path, dpi: u32) -> Result<(), ReportError> {
    if !CELL_MAP_DPI_RANGE.contains(&dpi) {
        return Err(ReportError::Plot(format!(
            "a map's resolution must be in {}..={} dpi (got {dpi})",
            CELL_MAP_DPI_RANGE.start(),
            CELL_MAP_DPI_RANGE.end()
        )));
    }
    let scaled = |n: u32| (u64::from(n) * u64::from(dpi) / u64::from(CELL_MAP_DPI)) as u32;
    let size = match crate::figure::ImageFormat::of(path)? {
        crate::figure::ImageFormat::Png => (scaled(CELL_MAP_SIZE.0), scaled(CELL_MAP_SIZE.1)),
        crate::figure::ImageFormat::Svg => CELL_MAP_SIZE,
    };
    write_figure_at(map, path, size, Some(dpi))
}

/// Where the cells of an `nx` × `ny` map lie in the images [`render_cell_map`] writes (it
/// depends on the grid's shape alone, not on the ranges or texts).
#[derive(Clone, Copy, Debug)]
pub struct CellPixels {
    area: PixelRect,
    nx: usize,
    ny: usize,
}

impl CellPixels {
    /// The pixel at the centre of cell (i, j).
    pub fn centre(&self, i: usize, j: usize) -> (u32, u32) {
        let (x0, x1) = span(i, self.nx, self.area.x0, self.area.width());
        let (y0, y1) = span_up(j, self.ny, self.area);
        (((x0 + x1) / 2) as u32, ((y0 + y1) / 2) as u32)
    }
}

impl CellMap<'_> {
    /// Where this map's cells lie in its images (drawn once to find out).
    pub fn cell_pixels(&self) -> Result<CellPixels, ReportError> {
        Ok(CellPixels {
            area: draw_png(self, CELL_MAP_SIZE)?.plot_area,
            nx: self.nx,
            ny: self.ny,
        })
    }
}

fn rgb(category: &Category) -> RGBColor {
    let [r, g, b] = category.colour;
    RGBColor(r, g, b)
}

/// Pixels `[from, to)` of cell `k` of `n` along a side `len` pixels long starting at `origin`.
fn span(k: usize, n: usize, origin: i32, len: i32) -> (i32, i32) {
    let edge = |k: usize| origin + (k as f64 * f64::from(len) / n as f64).round() as i32;
    (edge(k), edge(k + 1))
}

/// [`span`] along y, which counts upward from the bottom of `area`.
fn span_up(k: usize, n: usize, area: PixelRect) -> (i32, i32) {
    let (from, to) = span(k, n, 0, area.height());
    (area.y1 - to, area.y1 - from)
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

impl Figure for CellMap<'_> {
    fn validate(&self) -> Result<(), ReportError> {
        if self.nx == 0 || self.ny == 0 {
            return Err(ReportError::EmptyData("cell map has no cells"));
        }
        if self.nx.checked_mul(self.ny) != Some(self.codes.len()) {
            return Err(ReportError::Plot(format!(
                "cell map of {} x {} cells given {} codes",
                self.nx,
                self.ny,
                self.codes.len()
            )));
        }
        if let Some(&c) = self
            .codes
            .iter()
            .find(|&&c| usize::from(c) >= self.categories.len())
        {
            return Err(ReportError::Plot(format!(
                "cell map code {c} has no category (there are {})",
                self.categories.len()
            )));
        }
        check_range("x range", self.x_range)?;
        check_range("y range", self.y_range)?;
        if let Some(scale) = &self.scale {
            let e = scale.edges;
            let increasing = e.windows(2).all(|w| w[0] < w[1]);
            if e.len() < 2
                || e.len() > self.categories.len() + 1
                || !increasing
                || !e.iter().all(|v| v.is_finite())
            {
                return Err(ReportError::Plot(format!(
                    "a scale needs 2..={} finite increasing edges, got {e:?}",
                    self.categories.len() + 1
                )));
            }
        }
        Ok(())
    }

    fn draw<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
        (width, height): (u32, u32),
    ) -> Result<PixelRect, ReportError> {
        let s = (f64::from(width.min(height)) / 700.0).clamp(0.4, 7.0);
        let px = |v: f64| (v * s).round().max(1.0) as u32;
        let font = |size: f64| (FONT_FAMILY, size * s).into_font().color(&BLACK);
        // The title in a band of fixed height (a caption's would follow its glyphs), so that
        // where the cells lie depends on the image size alone.
        let (title_area, body) = root.split_vertically(px(40.0));
        title_area
            .draw(&Text::new(
                self.title.to_string(),
                ((width / 2) as i32, px(24.0) as i32),
                font(20.0).pos(Pos::new(HPos::Center, VPos::Center)),
            ))
            .map_err(plot_err)?;
        let legend_w = px(250.0).min(width / 3);
        let (map_area, legend_area) = body.split_horizontally(width - legend_w);
        let mut chart = ChartBuilder::on(&map_area)
            .margin(px(14.0))
            .margin_top(0)
            .x_label_area_size(px(55.0))
            .y_label_area_size(px(75.0))
            .build_cartesian_2d(
                self.x_range.0..self.x_range.1,
                self.y_range.0..self.y_range.1,
            )
            .map_err(plot_err)?;
        chart
            .configure_mesh()
            .disable_mesh()
            .x_desc(self.x_label)
            .y_desc(self.y_label)
            .label_style(font(13.0))
            .axis_desc_style(font(17.0))
            .axis_style(BLACK)
            .set_all_tick_mark_size(px(5.0))
            .draw()
            .map_err(plot_err)?;
        let area = PixelRect::from_ranges(chart.plotting_area().get_pixel_range());
        self.paint_cells(root, area)?;
        self.draw_legend(root, &legend_area, area, s)?;
        Ok(area)
    }
}

impl CellMap<'_> {
    fn colour(&self, code: u8) -> RGBColor {
        rgb(&self.categories[usize::from(code)])
    }

    /// Every column of cells as filled rectangles, one per run of equal codes along y. Cells
    /// narrower or lower than a pixel get no rectangle of their own (the neighbour whose span
    /// holds the pixel shows).
    fn paint_cells<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
        area: PixelRect,
    ) -> Result<(), ReportError> {
        for i in 0..self.nx {
            let (x0, x1) = span(i, self.nx, area.x0, area.width());
            if x1 <= x0 {
                continue;
            }
            let column = &self.codes[i * self.ny..(i + 1) * self.ny];
            let mut start = 0;
            while start < self.ny {
                let code = column[start];
                let end = start + column[start..].iter().take_while(|&&c| c == code).count();
                // Cells count upward, pixel rows downward: the run's top row is its last cell's.
                let (row0, row1) = (
                    span_up(end - 1, self.ny, area).0,
                    span_up(start, self.ny, area).1,
                );
                if row1 > row0 {
                    root.draw(&Rectangle::new(
                        // Both backends fill up to, not including, the second corner.
                        [(x0, row0), (x1, row1)],
                        self.colour(code).filled(),
                    ))
                    .map_err(plot_err)?;
                }
                start = end;
            }
        }
        Ok(())
    }

    /// The colour bar of the scale's bands, when there is one, then a swatch and a label per
    /// other category, from the top of the map down.
    fn draw_legend<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
        legend_area: &DrawingArea<DB, Shift>,
        area: PixelRect,
        s: f64,
    ) -> Result<(), ReportError> {
        let (ax, _) = legend_area.get_base_pixel();
        let x = ax + (8.0 * s) as i32;
        let font = |size: f64| (FONT_FAMILY, size * s).into_font().color(&BLACK);
        let mut top = area.y0;
        let mut first = 0;
        if let Some(scale) = &self.scale {
            top = self.draw_colour_bar(root, scale, (x, top), area.height() * 3 / 5, s)?;
            first = scale.edges.len() - 1;
        }
        let side = (16.0 * s) as i32;
        let row_h = (28.0 * s) as i32;
        let style = font(15.0).pos(Pos::new(HPos::Left, VPos::Center));
        for (k, category) in self.categories[first..].iter().enumerate() {
            let y = top + k as i32 * row_h;
            let corners = [(x, y), (x + side, y + side)];
            root.draw(&Rectangle::new(corners, rgb(category).filled()))
                .map_err(plot_err)?;
            root.draw(&Rectangle::new(corners, BLACK.stroke_width(1)))
                .map_err(plot_err)?;
            root.draw(&Text::new(
                category.label.to_string(),
                (x + side + (8.0 * s) as i32, y + side / 2),
                style.clone(),
            ))
            .map_err(plot_err)?;
        }
        Ok(())
    }

    /// The bands as a stepped bar `height` pixels high under its label at `(x, y)`, the edges
    /// as ticks; returns the first free row below it.
    fn draw_colour_bar<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
        scale: &Scale,
        (x, y): (i32, i32),
        height: i32,
        s: f64,
    ) -> Result<i32, ReportError> {
        let font = |size: f64| (FONT_FAMILY, size * s).into_font().color(&BLACK);
        root.draw(&Text::new(
            scale.label.to_string(),
            (x, y),
            font(15.0).pos(Pos::new(HPos::Left, VPos::Top)),
        ))
        .map_err(plot_err)?;
        let bar = PixelRect {
            x0: x,
            y0: y + (28.0 * s) as i32,
            x1: x + (26.0 * s) as i32,
            y1: y + (28.0 * s) as i32 + height,
        };
        let bands = scale.edges.len() - 1;
        let tick = font(13.0).pos(Pos::new(HPos::Left, VPos::Center));
        // Every edge labelled while they stay 18 pixels apart, else every other one, ...
        let every = (18.0 * s * bands as f64 / f64::from(height))
            .ceil()
            .max(1.0) as usize;
        for k in 0..bands {
            let (row0, row1) = span_up(k, bands, bar);
            root.draw(&Rectangle::new(
                [(bar.x0, row0), (bar.x1, row1)],
                rgb(&self.categories[k]).filled(),
            ))
            .map_err(plot_err)?;
        }
        for (k, edge) in scale.edges.iter().enumerate() {
            if k % every != 0 && k != bands {
                continue;
            }
            let row = if k == bands {
                bar.y0
            } else {
                span_up(k, bands, bar).1
            };
            let right = bar.x1 + (5.0 * s) as i32;
            root.draw(&PathElement::new([(bar.x1, row), (right, row)], BLACK))
                .map_err(plot_err)?;
            root.draw(&Text::new(
                value_label(*edge),
                (right + (3.0 * s) as i32, row),
                tick.clone(),
            ))
            .map_err(plot_err)?;
        }
        root.draw(&Rectangle::new(
            [(bar.x0, bar.y0), (bar.x1, bar.y1)],
            BLACK.stroke_width(1),
        ))
        .map_err(plot_err)?;
        Ok(bar.y1 + (24.0 * s) as i32)
    }
}

/// Tick label of a scale's edge: short, without trailing zeros, a minus sign for negatives.
fn value_label(v: f64) -> String {
    let s = format!("{v:.3}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    match s {
        "-0" => "0".to_string(),
        _ => s.replace('-', "−"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::figure::counting::{png_counts, svg_counts};
    use crate::figure::draw_svg;

    const CATEGORIES: [Category; 3] = [
        Category {
            label: "forbidden",
            colour: [220, 220, 220],
        },
        Category {
            label: "regular 50 %",
            colour: [0, 114, 178],
        },
        Category {
            label: "chaotic 50 %",
            colour: [213, 94, 0],
        },
    ];

    /// A 30 × 20 grid: forbidden outside a disc, a regular island in the disc's left half and
    /// a chaotic sea elsewhere in it.
    fn codes() -> Vec<u8> {
        let (nx, ny) = (30, 20);
        let mut codes = vec![0u8; nx * ny];
        for i in 0..nx {
            for j in 0..ny {
                let (x, y) = (i as f64 - 14.5, j as f64 - 9.5);
                if x * x / 225.0 + y * y / 100.0 < 1.0 {
                    codes[i * ny + j] = if x < -3.0 && y.abs() < 4.0 { 1 } else { 2 };
                }
            }
        }
        codes
    }

    fn map(codes: &[u8]) -> CellMap<'_> {
        CellMap {
            codes,
            categories: &CATEGORIES,
            nx: 30,
            ny: 20,
            x_range: (-1.0, 2.0),
            y_range: (-0.5, 0.5),
            title: "classes",
            x_label: "q₂",
            y_label: "p₂",
            scale: None,
        }
    }

    #[test]
    fn each_cell_shows_its_category_colour() {
        let codes = codes();
        let m = map(&codes);
        let canvas = draw_png(&m, CELL_MAP_SIZE).unwrap();
        let pixels = m.cell_pixels().unwrap();
        // The forbidden corner, a cell of the island, a cell of the sea, then every cell.
        for (i, j, code) in [(0, 0, 0u8), (8, 10, 1), (25, 10, 2)] {
            assert_eq!(codes[i * 20 + j], code);
            let (x, y) = pixels.centre(i, j);
            assert_eq!(
                canvas.pixel(x as i32, y as i32),
                CATEGORIES[usize::from(code)].colour
            );
        }
        for i in 0..30 {
            for j in 0..20 {
                let (x, y) = pixels.centre(i, j);
                let want = CATEGORIES[usize::from(codes[i * 20 + j])].colour;
                assert_eq!(canvas.pixel(x as i32, y as i32), want, "cell ({i}, {j})");
            }
        }
    }

    #[test]
    fn the_svg_holds_the_elements_the_png_is_drawn_from() {
        let codes = codes();
        let m = map(&codes);
        let svg = draw_svg(&m, CELL_MAP_SIZE).unwrap();
        let counts = png_counts(&m, CELL_MAP_SIZE);
        assert_eq!(svg_counts(&svg), counts);
        // The background, the runs of cells, two rectangles per legend entry; three legend
        // texts, the title, axis labels and ticks.
        assert!(counts.rects > 1 + 30 + 2 * 3, "{counts:?}");
        assert!(counts.texts >= 3 + 1 + 2, "{counts:?}");
        for c in &CATEGORIES {
            assert!(svg.contains(c.label), "legend {}", c.label);
        }
    }

    #[test]
    fn the_cells_fill_the_plot_area_without_gaps() {
        let codes = codes();
        let canvas = draw_png(&map(&codes), CELL_MAP_SIZE).unwrap();
        let a = canvas.plot_area;
        let colours: Vec<[u8; 3]> = CATEGORIES.iter().map(|c| c.colour).collect();
        for y in a.y0..a.y1 {
            for x in a.x0..a.x1 {
                let p = canvas.pixel(x, y);
                assert!(colours.contains(&p), "pixel ({x}, {y}) is {p:?}");
            }
        }
    }

    /// Bands of a value v = i / 10 (cells 0..9 in band 0, 10..19 in band 1, 20..29 in band
    /// 2), forbidden cells of the disc's outside in a fourth category.
    fn banded() -> (Vec<u8>, [Category<'static>; 4]) {
        let mut codes = codes();
        for i in 0..30 {
            for j in 0..20 {
                if codes[i * 20 + j] != 0 {
                    codes[i * 20 + j] = (i / 10) as u8;
                } else {
                    codes[i * 20 + j] = 3;
                }
            }
        }
        let bands = [
            Category {
                label: "low",
                colour: [40, 20, 0],
            },
            Category {
                label: "mid",
                colour: [240, 228, 66],
            },
            Category {
                label: "high",
                colour: [0, 90, 160],
            },
            Category {
                label: "forbidden",
                colour: [225, 225, 225],
            },
        ];
        (codes, bands)
    }

    #[test]
    fn a_scale_draws_its_bands_as_a_colour_bar_and_the_rest_in_the_legend() {
        let (codes, categories) = banded();
        let edges = [0.0, 1.0, 2.0, 3.0];
        let m = CellMap {
            categories: &categories,
            scale: Some(Scale {
                label: "log₁₀ v",
                edges: &edges,
            }),
            ..map(&codes)
        };
        let canvas = draw_png(&m, CELL_MAP_SIZE).unwrap();
        let pixels = m.cell_pixels().unwrap();
        for (i, j) in [(5, 10), (15, 10), (25, 10), (0, 0)] {
            let (x, y) = pixels.centre(i, j);
            let want = categories[usize::from(codes[i * 20 + j])].colour;
            assert_eq!(canvas.pixel(x as i32, y as i32), want, "cell ({i}, {j})");
        }
        let svg = draw_svg(&m, CELL_MAP_SIZE).unwrap();
        assert_eq!(svg_counts(&svg), png_counts(&m, CELL_MAP_SIZE));
        // The bar's label and its four edges; the bands are not in the legend, "forbidden" is.
        let texts: Vec<&str> = svg
            .split("<text")
            .skip(1)
            .filter_map(|t| t.split('>').nth(1)?.split('<').next())
            .map(str::trim)
            .collect();
        for text in ["log₁₀ v", "0", "1", "2", "3", "forbidden"] {
            assert!(texts.contains(&text), "{text} not in {texts:?}");
        }
        assert!(!texts.contains(&"low"), "a band is not a legend entry");
    }

    #[test]
    fn a_scale_with_bad_edges_is_refused() {
        let (codes, categories) = banded();
        for edges in [
            &[0.0][..],
            &[0.0, 2.0, 1.0],
            &[0.0, 1.0, 2.0, 3.0, 4.0, 5.0],
            &[0.0, f64::NAN],
        ] {
            let m = CellMap {
                categories: &categories,
                scale: Some(Scale { label: "v", edges }),
                ..map(&codes)
            };
            assert!(m.validate().is_err(), "{edges:?}");
        }
    }

    #[test]
    fn edges_are_labelled_shortly_with_a_minus_sign() {
        assert_eq!(value_label(-8.0), "−8");
        assert_eq!(value_label(0.0), "0");
        assert_eq!(value_label(-0.0), "0");
        assert_eq!(value_label(2.5), "2.5");
    }

    #[test]
    fn bad_maps_are_refused() {
        let codes = codes();
        let mut m = map(&codes);
        m.nx = 29;
        assert!(matches!(m.validate(), Err(ReportError::Plot(_))));
        let bad = vec![3u8; 600];
        assert!(map(&bad)
            .validate()
            .unwrap_err()
            .to_string()
            .contains("code 3"));
        let mut m = map(&codes);
        m.y_range = (0.5, -0.5);
        assert!(m.validate().is_err());
        let dir = tempfile::tempdir().unwrap();
        let err = render_cell_map(&map(&codes), &dir.path().join("map.jpg")).unwrap_err();
        assert!(err.to_string().contains(".png or .svg"), "{err}");
    }

    #[test]
    fn both_formats_are_written_by_extension() {
        let codes = codes();
        let dir = tempfile::tempdir().unwrap();
        for name in ["classes.png", "classes.SVG"] {
            render_cell_map(&map(&codes), &dir.path().join(name)).unwrap();
        }
        let png = std::fs::read(dir.path().join("classes.png")).unwrap();
        assert_eq!(&png[1..4], b"PNG");
        let svg = std::fs::read_to_string(dir.path().join("classes.SVG")).unwrap();
        assert!(svg.starts_with("<svg"), "{}", &svg[..40]);
    }
}
