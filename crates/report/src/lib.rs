//! Reports of Salient's results: everything that turns computed numbers into files for people
//! and other programs.
//!
//! By design this crate owns the tables (Markdown, CSV, JSON), the `.npy` array writers, and the
//! maps and plots (PNG and SVG); nothing here integrates or computes indicators. It holds plain
//! tables ([`Table`], Markdown and CSV), NumPy `.npy` arrays ([`write_npy_f64`]) and the plots:
//!
//! * [`render_loglog`] draws lines on log-log axes (SALI/GALI against time, work-precision
//!   diagrams), with dashed reference lines and a legend, and [`render_panels`] several of
//!   them stacked in one image;
//! * [`render_lines`] draws lines on linear axes (percentages against energy);
//! * [`render_cell_map`] draws a field of categories over a 2-D grid (the class of each cell
//!   with a legend, or a quantity in bands with a stepped colour bar), as PNG or SVG from the
//!   same drawing;
//! * [`write_netcdf`] writes gridded results as NetCDF-3 classic, with coordinates and
//!   attributes.
//!
//! Text is set in DejaVu Sans, embedded in the library (`assets/DejaVuSans.ttf`, licence in
//! `assets/DejaVuSans-LICENSE.txt`), so plots render the same on headless machines without any
//! system fonts.

mod canvas;
mod cellmap;
mod error;
mod figure;
mod lines;
mod loglog;
mod netcdf;
mod npy;
mod table;

pub use cellmap::{
    render_cell_map, render_cell_map_at, Category, CellMap, CellPixels, Scale, CELL_MAP_DPI,
    CELL_MAP_DPI_RANGE, CELL_MAP_SIZE,
};
pub use error::ReportError;
pub use figure::ImageFormat;
pub use lines::{render_lines, LinePlot};
pub use loglog::{render_loglog, render_panels, HLine, Line, LogLogPlot, Panels};
pub use netcdf::{write_netcdf, AttrValue, Axis, GridFile, GridVar, Values};
pub use npy::{npy_bytes_f64, read_npy_u8, write_npy_f64, write_npy_u8};
pub use table::Table;
pub use table::NOTHING;
