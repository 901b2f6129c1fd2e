//! One drawing, two formats: a [`Figure`] draws itself on any plotters backend, so its PNG (an
//! RGB buffer encoded by `canvas.rs`) and its SVG come from the same code, element for element.

use std::path::Path;

use plotters::backend::{BitMapBackend, SVGBackend};
use plotters::coord::Shift;
use plotters::prelude::*;

use crate::canvas::{check_size, ensure_font, white_buffer, Canvas, PixelRect};
use crate::error::{plot_err, ReportError};

/// A drawing that can be rendered on any backend.
pub(crate) trait Figure {
    /// Checks the data before anything is drawn.
    fn validate(&self) -> Result<(), ReportError>;

    /// Draws on `root`, already filled white, of `size` pixels; returns the data area.
    fn draw<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
        size: (u32, u32),
    ) -> Result<PixelRect, ReportError>;
}

/// The output formats a figure is written in, by the path's extension.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageFormat {
    /// PNG bitmap (`.png`).
    Png,
    /// SVG vector image (`.svg`).
    Svg,
}

impl ImageFormat {
    /// The format a path's extension names (`.png` or `.svg`, any case).
    pub fn of(path: &Path) -> Result<Self, ReportError> {
        match path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .as_deref()
        {
            Some("png") => Ok(ImageFormat::Png),
            Some("svg") => Ok(ImageFormat::Svg),
            _ => Err(ReportError::Plot(format!(
                "a figure is written as .png or .svg, not {}",
                path.display()
            ))),
        }
    }
}

/// The figure on a white RGB canvas of `size` pixels.
pub(crate) fn draw_png<F: Figure>(fig: &F, size: (u32, u32)) -> Result<Canvas, ReportError> {
    ensure_font()?;
    fig.validate()?;
    let mut rgb = white_buffer(size.0, size.1)?;
    let plot_area = {
        let root = BitMapBackend::with_buffer(&mut rgb, size).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        let plot_area = fig.draw(&root, size)?;
        root.present().map_err(plot_err)?;
        plot_area
    };
    Ok(Canvas {
        rgb,
        width: size.0,
        height: size.1,
        plot_area,
    })
}

/// The figure as an SVG document of `size` pixels.
pub(crate) fn draw_svg<F: Figure>(fig: &F, size: (u32, u32)) -> Result<String, ReportError> {
    ensure_font()?;
    fig.validate()?;
    check_size(size.0, size.1)?;
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, size).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        fig.draw(&root, size)?;
        root.present().map_err(plot_err)?;
    }
    Ok(svg)
}

/// Writes the figure at `path` as PNG or SVG, by its extension.
pub(crate) fn write_figure<F: Figure>(
    fig: &F,
    path: &Path,
    size: (u32, u32),
) -> Result<(), ReportError> {
    write_figure_at(fig, path, size, None)
}

/// [`write_figure`] with the PNG's resolution `dpi` recorded in it.
pub(crate) fn write_figure_at<F: Figure>(
    fig: &F,
    path: &Path,
    size: (u32, u32),
    dpi: Option<u32>,
) -> Result<(), ReportError> {
    match ImageFormat::of(path)? {
        ImageFormat::Png => draw_png(fig, size)?.write_png(path, dpi),
        ImageFormat::Svg => Ok(std::fs::write(path, draw_svg(fig, size)?)?),
    }
}

#[cfg(test)]
pub(crate) mod counting {
    //! A backend that counts the elements drawn through it, to show that a PNG and an SVG of
    //! one figure hold the same elements.

    use plotters::prelude::*;
    use plotters_backend::{
        BackendColor, BackendCoord, BackendStyle, BackendTextStyle, DrawingErrorKind,
    };

    use super::*;

    /// Elements drawn, by kind (a single pixel is a rectangle in SVG); invisible ones (alpha 0),
    /// which the SVG backend leaves out, are not counted.
    #[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
    pub struct Counts {
        pub rects: usize,
        pub texts: usize,
        pub lines: usize,
        pub paths: usize,
        pub circles: usize,
        pub polygons: usize,
    }

    pub struct Counting<'a, DB> {
        pub inner: DB,
        pub counts: &'a mut Counts,
    }

    fn visible(c: BackendColor) -> usize {
        usize::from(c.alpha != 0.0)
    }

    impl<DB: DrawingBackend> DrawingBackend for Counting<'_, DB> {
        type ErrorType = DB::ErrorType;

        fn get_size(&self) -> (u32, u32) {
            self.inner.get_size()
        }
        fn ensure_prepared(&mut self) -> Result<(), DrawingErrorKind<DB::ErrorType>> {
            self.inner.ensure_prepared()
        }
        fn present(&mut self) -> Result<(), DrawingErrorKind<DB::ErrorType>> {
            self.inner.present()
        }
        fn draw_pixel(
            &mut self,
            point: BackendCoord,
            color: BackendColor,
        ) -> Result<(), DrawingErrorKind<DB::ErrorType>> {
            self.counts.rects += visible(color);
            self.inner.draw_pixel(point, color)
        }
        fn draw_line<S: BackendStyle>(
            &mut self,
            from: BackendCoord,
            to: BackendCoord,
            style: &S,
        ) -> Result<(), DrawingErrorKind<DB::ErrorType>> {
            self.counts.lines += visible(style.color());
            self.inner.draw_line(from, to, style)
        }
        fn draw_rect<S: BackendStyle>(
            &mut self,
            upper_left: BackendCoord,
            bottom_right: BackendCoord,
            style: &S,
            fill: bool,
        ) -> Result<(), DrawingErrorKind<DB::ErrorType>> {
            self.counts.rects += visible(style.color());
            self.inner.draw_rect(upper_left, bottom_right, style, fill)
        }
        fn draw_path<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(
            &mut self,
            path: I,
            style: &S,
        ) -> Result<(), DrawingErrorKind<DB::ErrorType>> {
            self.counts.paths += visible(style.color());
            self.inner.draw_path(path, style)
        }
        fn draw_circle<S: BackendStyle>(
            &mut self,
            center: BackendCoord,
            radius: u32,
            style: &S,
            fill: bool,
        ) -> Result<(), DrawingErrorKind<DB::ErrorType>> {
            self.counts.circles += visible(style.color());
            self.inner.draw_circle(center, radius, style, fill)
        }
        fn fill_polygon<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(
            &mut self,
            vert: I,
            style: &S,
        ) -> Result<(), DrawingErrorKind<DB::ErrorType>> {
            self.counts.polygons += visible(style.color());
            self.inner.fill_polygon(vert, style)
        }
        fn draw_text<TStyle: BackendTextStyle>(
            &mut self,
            text: &str,
            style: &TStyle,
            pos: BackendCoord,
        ) -> Result<(), DrawingErrorKind<DB::ErrorType>> {
            self.counts.texts += visible(style.color());
            self.inner.draw_text(text, style, pos)
        }
        fn estimate_text_size<TStyle: BackendTextStyle>(
            &self,
            text: &str,
            style: &TStyle,
        ) -> Result<(u32, u32), DrawingErrorKind<DB::ErrorType>> {
            self.inner.estimate_text_size(text, style)
        }
    }

    /// The elements of `fig` drawn as a PNG.
    pub fn png_counts<F: Figure>(fig: &F, size: (u32, u32)) -> Counts {
        let mut counts = Counts::default();
        let mut rgb = white_buffer(size.0, size.1).unwrap();
        {
            let inner = BitMapBackend::with_buffer(&mut rgb, size);
            let root = Counting {
                inner,
                counts: &mut counts,
            }
            .into_drawing_area();
            root.fill(&WHITE).unwrap();
            fig.draw(&root, size).unwrap();
            root.present().unwrap();
        }
        counts
    }

    /// The elements of an SVG document.
    pub fn svg_counts(svg: &str) -> Counts {
        Counts {
            rects: svg.matches("<rect").count(),
            texts: svg.matches("<text").count(),
            lines: svg.matches("<line ").count(),
            paths: svg.matches("<polyline").count(),
            circles: svg.matches("<circle").count(),
            polygons: svg.matches("<polygon").count(),
        }
    }
}
