//! Reports of Salient's results: everything that turns computed numbers into files for people
//! and other programs.
//!
//! By design this crate owns the tables (Markdown, CSV, JSON), the `.npy` array writers, and the
//! PNG maps and plots; nothing here integrates or computes indicators. So far the plots and
//! plain tables ([`Table`], Markdown and CSV) and NumPy `.npy` arrays ([`write_npy_f64`]) exist:
//!
//! * [`render_loglog_png`] draws lines on log-log axes (SALI/GALI against time, work-precision
//!   diagrams), with dashed reference lines and a legend;
//! * [`render_lines_png`] draws lines on linear axes (percentages against energy);
//! * [`render_grey_map_png`] draws a scalar field over a 2-D grid in grey levels, with a colour
//!   bar.
//!
//! Text is set in DejaVu Sans, embedded in the library (`assets/DejaVuSans.ttf`, licence in
//! `assets/DejaVuSans-LICENSE.txt`), so plots render the same on headless machines without any
//! system fonts.

mod canvas;
mod error;
mod greymap;
mod lines;
mod loglog;
mod npy;
mod table;

pub use error::ReportError;
pub use greymap::{render_grey_map_png, GREY_MAP_SIZE, NAN_COLOUR};
pub use lines::{render_lines_png, LinePlot};
pub use loglog::{render_loglog_png, HLine, Line, LogLogPlot};
pub use npy::{npy_bytes_f64, read_npy_u8, write_npy_f64, write_npy_u8};
pub use table::Table;
pub use table::NOTHING;
