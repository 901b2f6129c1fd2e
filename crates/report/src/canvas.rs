//! The in-memory RGB canvas every plot is drawn on, the embedded font, and PNG output.
//!
//! Plots are first painted into a plain `Vec<u8>` (RGB, row-major, 3 bytes a pixel) through
//! `BitMapBackend::with_buffer`; only then is the finished buffer encoded as PNG (the `png`
//! crate, without plotters' image-codec stack). The split lets the unit tests inspect the pixels
//! without an image decoder.

use std::path::Path;
use std::sync::OnceLock;

use plotters::style::{register_font, FontStyle};

use crate::error::{plot_err, ReportError};

/// DejaVu Sans (Bitstream Vera licence, see `assets/DejaVuSans-LICENSE.txt`). Embedded so that
/// plots render identically on machines without any system fonts.
static FONT_BYTES: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

/// Family name every text style in this crate uses; plotters' default mesh labels use it too.
pub(crate) const FONT_FAMILY: &str = "sans-serif";

/// Registers the embedded font with plotters (once per process).
pub(crate) fn ensure_font() -> Result<(), ReportError> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED
        .get_or_init(|| register_font(FONT_FAMILY, FontStyle::Normal, FONT_BYTES).is_ok());
    if ok {
        Ok(())
    } else {
        Err(ReportError::Plot(
            "the embedded DejaVu Sans font could not be parsed".to_string(),
        ))
    }
}

/// Smallest image side lengths the layouts are designed for.
pub(crate) const MIN_WIDTH: u32 = 160;
pub(crate) const MIN_HEIGHT: u32 = 120;
/// Largest accepted side length (keeps the buffer allocation sane).
pub(crate) const MAX_SIDE: u32 = 16_384;

/// A pixel rectangle in image coordinates, half-open: `x0..x1`, `y0..y1` (y grows downward).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct PixelRect {
    pub x0: i32,
    pub y0: i32,
    pub x1: i32,
    pub y1: i32,
}

impl PixelRect {
    pub(crate) fn from_ranges((xs, ys): (std::ops::Range<i32>, std::ops::Range<i32>)) -> Self {
        PixelRect {
            x0: xs.start,
            y0: ys.start,
            x1: xs.end,
            y1: ys.end,
        }
    }

    pub(crate) fn width(&self) -> i32 {
        self.x1 - self.x0
    }

    pub(crate) fn height(&self) -> i32 {
        self.y1 - self.y0
    }
}

/// A finished plot: RGB pixels plus where the data area ended up (used by tests and to find a
/// cell map's cells).
pub(crate) struct Canvas {
    pub rgb: Vec<u8>,
    pub width: u32,
    pub height: u32,
    /// The plotting (data) area of the main chart.
    #[cfg_attr(not(test), allow(dead_code))]
    pub plot_area: PixelRect,
}

/// Refuses image sizes outside the range the layouts are designed for.
pub(crate) fn check_size(width: u32, height: u32) -> Result<(), ReportError> {
    if width < MIN_WIDTH || height < MIN_HEIGHT || width > MAX_SIDE || height > MAX_SIDE {
        return Err(ReportError::Plot(format!(
            "image size {width}x{height} is outside the supported range \
             {MIN_WIDTH}x{MIN_HEIGHT} ..= {MAX_SIDE}x{MAX_SIDE}"
        )));
    }
    Ok(())
}

/// Checks the requested size and returns a white RGB buffer for it.
pub(crate) fn white_buffer(width: u32, height: u32) -> Result<Vec<u8>, ReportError> {
    check_size(width, height)?;
    Ok(vec![255u8; width as usize * height as usize * 3])
}

impl Canvas {
    /// The RGB value of pixel `(x, y)`.
    #[cfg(test)]
    pub(crate) fn pixel(&self, x: i32, y: i32) -> [u8; 3] {
        assert!(x >= 0 && y >= 0 && (x as u32) < self.width && (y as u32) < self.height);
        let k = 3 * (y as usize * self.width as usize + x as usize);
        [self.rgb[k], self.rgb[k + 1], self.rgb[k + 2]]
    }

    /// Encodes the canvas as a PNG file at `path`, which must end in `.png`.
    /// With `dpi`, the resolution is recorded in the file (its pHYs chunk), so that documents
    /// place the image at its intended physical size.
    pub(crate) fn write_png(&self, path: &Path, dpi: Option<u32>) -> Result<(), ReportError> {
        let is_png = path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| e.eq_ignore_ascii_case("png"));
        if !is_png {
            return Err(ReportError::Plot(format!(
                "PNG output path must end in .png: {}",
                path.display()
            )));
        }
        // Create the file ourselves first so that a missing directory or a permission problem
        // surfaces as a proper `ReportError::Io` (the encoder would wrap it opaquely).
        let file = std::io::BufWriter::new(std::fs::File::create(path)?);
        let mut encoder = png::Encoder::new(file, self.width, self.height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        // Per-row filter choice: plots of flat colour areas compress to about a third.
        encoder.set_adaptive_filter(png::AdaptiveFilterType::Adaptive);
        if let Some(dpi) = dpi {
            let per_metre = (f64::from(dpi) / 0.0254).round() as u32;
            encoder.set_pixel_dims(Some(png::PixelDimensions {
                xppu: per_metre,
                yppu: per_metre,
                unit: png::Unit::Meter,
            }));
        }
        let mut writer = encoder.write_header().map_err(plot_err)?;
        writer.write_image_data(&self.rgb).map_err(plot_err)?;
        writer.finish().map_err(plot_err)?;
        Ok(())
    }
}
