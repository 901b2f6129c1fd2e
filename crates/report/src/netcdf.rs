//! Gridded results as NetCDF-3 classic files (`netcdf3`, pure Rust): two coordinate axes, a
//! variable per quantity on them, attributes that say what each one is. `xarray.open_dataset`
//! reads them with their coordinates.

use std::cell::RefCell;
use std::io::{Seek, SeekFrom, Write};
use std::path::Path;
use std::rc::Rc;

use netcdf3::{DataSet, FileWriter, InvalidDataSet, Version, WriteError};

use crate::error::ReportError;

/// A coordinate axis: its name (also its dimension's), its values and what they are.
#[derive(Clone, Copy, Debug)]
pub struct Axis<'a> {
    /// Name of the axis variable and of its dimension.
    pub name: &'a str,
    /// What the values are (the `long_name` attribute).
    pub long_name: &'a str,
    /// Coordinates along the axis.
    pub values: &'a [f64],
}

/// The values of a variable over the two axes, row-major: `[i * ny + j]` at (x_i, y_j).
#[derive(Clone, Copy, Debug)]
pub enum Values<'a> {
    /// 32-bit integers.
    I32(&'a [i32]),
    /// 64-bit floats.
    F64(&'a [f64]),
}

impl Values<'_> {
    fn len(&self) -> usize {
        match self {
            Values::I32(v) => v.len(),
            Values::F64(v) => v.len(),
        }
    }
}

/// An attribute's value.
#[derive(Clone, Debug, PartialEq)]
pub enum AttrValue {
    /// A string.
    Text(String),
    /// A 64-bit float.
    F64(f64),
    /// Integers: `netcdf3` pads byte attributes with fill bytes where readers expect zeros, so
    /// a list of codes is kept in 32-bit integers.
    I32s(Vec<i32>),
}

/// A variable on the grid, with its attributes (`long_name` is added from the field). NaN in
/// an `F64` variable stays NaN for every reader; no attribute may hold NaN (the writer finds
/// its variables by equality, which NaN defeats).
#[derive(Clone, Debug)]
pub struct GridVar<'a> {
    /// Name of the variable.
    pub name: &'a str,
    /// What the values are (the `long_name` attribute).
    pub long_name: &'a str,
    /// The values, row-major over (x, y).
    pub values: Values<'a>,
    /// Further attributes of the variable.
    pub attrs: Vec<(&'a str, AttrValue)>,
}

/// A whole file: the axes, the variables on them and the global attributes.
#[derive(Clone, Debug)]
pub struct GridFile<'a> {
    /// The x axis (first dimension).
    pub x: Axis<'a>,
    /// The y axis (second dimension).
    pub y: Axis<'a>,
    /// The variables on the two axes.
    pub vars: Vec<GridVar<'a>>,
    /// Global attributes.
    pub attrs: Vec<(&'a str, AttrValue)>,
}

fn invalid(e: InvalidDataSet) -> ReportError {
    ReportError::Plot(format!("NetCDF definition: {e:?}"))
}

fn write_err(e: WriteError) -> ReportError {
    match e {
        WriteError::IOErrorKind(kind) => ReportError::Io(std::io::Error::from(kind)),
        e => ReportError::Plot(format!("NetCDF writing: {e:?}")),
    }
}

fn add_attr(
    ds: &mut DataSet,
    var: Option<&str>,
    name: &str,
    value: &AttrValue,
) -> Result<(), ReportError> {
    let r = match (var, value) {
        (Some(v), AttrValue::Text(t)) => ds.add_var_attr_string(v, name, t),
        (Some(v), AttrValue::F64(x)) => ds.add_var_attr_f64(v, name, vec![*x]),
        (Some(v), AttrValue::I32s(x)) => ds.add_var_attr_i32(v, name, x.clone()),
        (None, AttrValue::Text(t)) => ds.add_global_attr_string(name, t),
        (None, AttrValue::F64(x)) => ds.add_global_attr_f64(name, vec![*x]),
        (None, AttrValue::I32s(x)) => ds.add_global_attr_i32(name, x.clone()),
    };
    r.map_err(invalid)
}

/// The file's definition (dimensions, variables, attributes), checked against the data.
fn definition(file: &GridFile) -> Result<DataSet, ReportError> {
    let cells = file.x.values.len() * file.y.values.len();
    if cells == 0 {
        return Err(ReportError::EmptyData("a NetCDF grid without cells"));
    }
    let nan_attr = file
        .vars
        .iter()
        .flat_map(|v| v.attrs.iter())
        .chain(&file.attrs)
        .find(|(_, value)| matches!(value, AttrValue::F64(x) if x.is_nan()));
    if let Some((name, _)) = nan_attr {
        return Err(ReportError::Plot(format!("NetCDF attribute {name} is NaN")));
    }
    let mut ds = DataSet::new();
    for axis in [&file.x, &file.y] {
        ds.add_fixed_dim(axis.name, axis.values.len())
            .map_err(invalid)?;
        ds.add_var_f64(axis.name, &[axis.name]).map_err(invalid)?;
        add_attr(
            &mut ds,
            Some(axis.name),
            "long_name",
            &AttrValue::Text(axis.long_name.into()),
        )?;
    }
    let dims = [file.x.name, file.y.name];
    for var in &file.vars {
        if var.values.len() != cells {
            return Err(ReportError::Plot(format!(
                "NetCDF variable {} has {} values for {cells} cells",
                var.name,
                var.values.len()
            )));
        }
        match var.values {
            Values::I32(_) => ds.add_var_i32(var.name, &dims),
            Values::F64(_) => ds.add_var_f64(var.name, &dims),
        }
        .map_err(invalid)?;
        add_attr(
            &mut ds,
            Some(var.name),
            "long_name",
            &AttrValue::Text(var.long_name.into()),
        )?;
        for (name, value) in &var.attrs {
            add_attr(&mut ds, Some(var.name), name, value)?;
        }
    }
    for (name, value) in &file.attrs {
        add_attr(&mut ds, None, name, value)?;
    }
    Ok(ds)
}

/// Writes `file` at `path` as NetCDF-3 classic (64-bit offsets not needed below 2 GiB).
pub fn write_netcdf(file: &GridFile, path: &Path) -> Result<(), ReportError> {
    let ds = definition(file)?;
    let failed = Rc::new(RefCell::new(None));
    let out = FlushOnDrop {
        out: std::io::BufWriter::with_capacity(1 << 20, std::fs::File::create(path)?),
        failed: Rc::clone(&failed),
    };
    let mut writer =
        FileWriter::open_seek_write(&path.to_string_lossy(), Box::new(out)).map_err(write_err)?;
    writer
        .set_def(&ds, Version::Classic, 0)
        .map_err(write_err)?;
    for axis in [&file.x, &file.y] {
        writer
            .write_var_f64(axis.name, axis.values)
            .map_err(write_err)?;
    }
    for var in &file.vars {
        match var.values {
            Values::I32(v) => writer.write_var_i32(var.name, v),
            Values::F64(v) => writer.write_var_f64(var.name, v),
        }
        .map_err(write_err)?;
    }
    writer.close().map_err(write_err)?;
    // Closed and dropped: the buffer's last flush has happened.
    let flushed = failed.borrow_mut().take();
    flushed.map_or(Ok(()), |e| Err(ReportError::Io(e)))
}

/// The file buffered (`netcdf3` writes every value on its own: a system call each, a second
/// for a 400×400 grid, unbuffered), flushed when the writer drops it, which `FileWriter::close`
/// does without flushing; a failure of that flush is kept for the caller.
struct FlushOnDrop {
    out: std::io::BufWriter<std::fs::File>,
    failed: Rc<RefCell<Option<std::io::Error>>>,
}

impl Write for FlushOnDrop {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.out.write(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.out.flush()
    }
}

impl Seek for FlushOnDrop {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        self.out.seek(pos)
    }
}

impl Drop for FlushOnDrop {
    fn drop(&mut self) {
        if let Err(e) = self.out.flush() {
            *self.failed.borrow_mut() = Some(e);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use netcdf3::FileReader;

    #[test]
    fn a_file_reads_back_with_its_axes_variables_and_attributes() {
        let (x, y) = ([0.25, 0.75], [-0.5, 0.0, 0.5]);
        let class: Vec<i32> = vec![0, 1, 2, 3, 1, 0];
        let sali = [f64::NAN, 1.0, 1e-6, 1e-9, 0.5, f64::NAN];
        let source = [-1, 1, 2, 3, 1, -1];
        let file = GridFile {
            x: Axis {
                name: "q2",
                long_name: "q₂ at cell centres",
                values: &x,
            },
            y: Axis {
                name: "p2",
                long_name: "p₂ at cell centres",
                values: &y,
            },
            vars: vec![
                GridVar {
                    name: "class",
                    long_name: "class",
                    values: Values::I32(&class),
                    attrs: vec![
                        ("flag_values", AttrValue::I32s(vec![0, 1, 2])),
                        (
                            "flag_meanings",
                            AttrValue::Text("none regular sticky chaotic".into()),
                        ),
                    ],
                },
                GridVar {
                    name: "sali",
                    long_name: "SALI",
                    values: Values::F64(&sali),
                    attrs: vec![("units", AttrValue::Text("1".into()))],
                },
                GridVar {
                    name: "label_source",
                    long_name: "labelling cell",
                    values: Values::I32(&source),
                    attrs: vec![("_FillValue", AttrValue::I32s(vec![-1]))],
                },
            ],
            attrs: vec![
                ("energy", AttrValue::F64(0.125)),
                ("method", AttrValue::Text("tm-sbab2c".into())),
            ],
        };
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.nc");
        write_netcdf(&file, &path).unwrap();
        // Written again over itself: replaced.
        write_netcdf(&file, &path).unwrap();
        let mut reader = FileReader::open(&path).unwrap();
        let ds = reader.data_set();
        assert_eq!(ds.dim_size("q2"), Some(2));
        assert_eq!(ds.dim_size("p2"), Some(3));
        assert_eq!(ds.get_global_attr_as_string("method").unwrap(), "tm-sbab2c");
        assert_eq!(ds.get_global_attr_f64("energy"), Some(&[0.125][..]));
        assert_eq!(
            ds.get_var_attr_as_string("class", "flag_meanings").unwrap(),
            "none regular sticky chaotic"
        );
        assert_eq!(
            ds.get_var_attr_as_string("q2", "long_name").unwrap(),
            "q₂ at cell centres"
        );
        let vars = reader.read_all_vars().unwrap();
        assert_eq!(vars["q2"].get_f64().unwrap(), &x);
        assert_eq!(vars["p2"].get_f64().unwrap(), &y);
        assert_eq!(vars["class"].get_i32().unwrap(), &class[..]);
        assert_eq!(vars["label_source"].get_i32().unwrap(), &source);
        let back = vars["sali"].get_f64().unwrap();
        assert!(back
            .iter()
            .zip(&sali)
            .all(|(a, b)| a == b || (a.is_nan() && b.is_nan())));
    }

    #[test]
    fn variables_must_fill_the_grid() {
        let x = [0.0, 1.0];
        let short = [1.0];
        let file = GridFile {
            x: Axis {
                name: "x",
                long_name: "x",
                values: &x,
            },
            y: Axis {
                name: "y",
                long_name: "y",
                values: &x,
            },
            vars: vec![GridVar {
                name: "v",
                long_name: "v",
                values: Values::F64(&short),
                attrs: vec![],
            }],
            attrs: vec![],
        };
        let dir = tempfile::tempdir().unwrap();
        let err = write_netcdf(&file, &dir.path().join("v.nc")).unwrap_err();
        assert!(err.to_string().contains("1 values for 4 cells"), "{err}");
        assert!(!dir.path().join("v.nc").exists());
        let nan = GridFile {
            vars: vec![],
            attrs: vec![("energy", AttrValue::F64(f64::NAN))],
            ..file
        };
        let err = write_netcdf(&nan, &dir.path().join("v.nc")).unwrap_err();
        assert!(err.to_string().contains("energy is NaN"), "{err}");
    }
}
