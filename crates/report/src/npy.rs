//! NumPy `.npy` files (format version 1.0): a magic string, a Python-dict header padded with
//! spaces to a multiple of 64 bytes, then the C-order little-endian data.

use crate::error::ReportError;
use std::path::Path;

fn header(descr: &str, shape: &[usize]) -> Vec<u8> {
    let dims = match shape {
        [n] => format!("({n},)"),
        _ => format!(
            "({})",
            shape
                .iter()
                .map(|d| d.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let mut dict = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {dims}, }}");
    // magic (6) + version (2) + header length (2) + dict + padding + '\n' ≡ 0 (mod 64)
    let unpadded = 10 + dict.len() + 1;
    dict.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    dict.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    out
}

fn check(shape: &[usize], len: usize) -> Result<(), ReportError> {
    let n: usize = shape.iter().product();
    if n != len {
        return Err(ReportError::Plot(format!(
            "npy: shape {shape:?} holds {n} values, data has {len}"
        )));
    }
    Ok(())
}

/// The bytes of an f64 array ('<f8') in C order, as [`write_npy_f64`] writes them.
///
/// # Panics
///
/// If `shape` does not hold exactly `data.len()` values.
pub fn npy_bytes_f64(shape: &[usize], data: &[f64]) -> Vec<u8> {
    if let Err(e) = check(shape, data.len()) {
        panic!("{e}");
    }
    let mut out = header("<f8", shape);
    out.reserve(8 * data.len());
    for x in data {
        out.extend_from_slice(&x.to_le_bytes());
    }
    out
}

/// Writes an f64 array in C order.
pub fn write_npy_f64(path: &Path, shape: &[usize], data: &[f64]) -> Result<(), ReportError> {
    check(shape, data.len())?;
    std::fs::write(path, npy_bytes_f64(shape, data)).map_err(ReportError::Io)
}

/// Writes a u8 array ('|u1') in C order.
pub fn write_npy_u8(path: &Path, shape: &[usize], data: &[u8]) -> Result<(), ReportError> {
    check(shape, data.len())?;
    let mut out = header("|u1", shape);
    out.extend_from_slice(data);
    std::fs::write(path, out).map_err(ReportError::Io)
}

/// Reads a u8 array ('|u1', C order) as [`write_npy_u8`] writes it: its shape and data.
pub fn read_npy_u8(path: &Path) -> Result<(Vec<usize>, Vec<u8>), ReportError> {
    let bytes = std::fs::read(path).map_err(ReportError::Io)?;
    let bad = |why: &str| ReportError::Plot(format!("{}: {why}", path.display()));
    if bytes.len() < 10 || &bytes[..8] != b"\x93NUMPY\x01\x00" {
        return Err(bad("not a NumPy .npy file of format 1.0"));
    }
    let len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let dict = bytes
        .get(10..10 + len)
        .and_then(|d| std::str::from_utf8(d).ok())
        .ok_or_else(|| bad("truncated header"))?;
    if !dict.contains("'descr': '|u1'") || !dict.contains("'fortran_order': False") {
        return Err(bad("not a C-order array of u8"));
    }
    let dims = dict
        .split_once("'shape': (")
        .and_then(|(_, rest)| rest.split_once(')'))
        .map(|(dims, _)| dims)
        .ok_or_else(|| bad("no shape in the header"))?;
    let shape = dims
        .split(',')
        .map(str::trim)
        .filter(|d| !d.is_empty())
        .map(|d| {
            d.parse::<usize>()
                .map_err(|_| bad("a dimension is not a number"))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let data = bytes[10 + len..].to_vec();
    if shape.iter().product::<usize>() != data.len() {
        return Err(bad("the data does not fill the shape"));
    }
    Ok((shape, data))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The header NumPy (format 1.0) writes: the dict, spaces, '\n', 64-byte aligned.
    fn numpy_header(dict: &str) -> Vec<u8> {
        let total = (10 + dict.len() + 1).div_ceil(64) * 64;
        let mut h = b"\x93NUMPY\x01\x00".to_vec();
        h.extend_from_slice(&((total - 10) as u16).to_le_bytes());
        h.extend_from_slice(dict.as_bytes());
        h.resize(total - 1, b' ');
        h.push(b'\n');
        h
    }

    #[test]
    fn header_is_what_numpy_writes() {
        let data = [1.0, 2.0, 3.0, 4.0, 5.0, -0.5];
        let b = npy_bytes_f64(&[2, 3], &data);
        let want = numpy_header("{'descr': '<f8', 'fortran_order': False, 'shape': (2, 3), }");
        assert_eq!(want.len(), 128);
        // 60 bytes of dict, 57 spaces and '\n' after the 10-byte preamble.
        assert_eq!(&want[8..10], &[118, 0]);
        assert_eq!(&b[..128], &want[..]);
        assert_eq!(b.len(), 128 + 48);
        for (k, x) in data.iter().enumerate() {
            let at = 128 + 8 * k;
            assert_eq!(&b[at..at + 8], &x.to_le_bytes());
        }
        // Little-endian, whatever the host.
        assert_eq!(&b[128..136], &[0, 0, 0, 0, 0, 0, 0xf0, 0x3f]);
    }

    #[test]
    fn one_d_and_zero_d_shapes_are_python_tuples() {
        let b = npy_bytes_f64(&[5], &[0.0; 5]);
        let want = numpy_header("{'descr': '<f8', 'fortran_order': False, 'shape': (5,), }");
        assert_eq!(&b[..want.len()], &want[..]);
        assert_eq!(b.len(), want.len() + 40);
        let b = npy_bytes_f64(&[], &[2.5]);
        let want = numpy_header("{'descr': '<f8', 'fortran_order': False, 'shape': (), }");
        assert_eq!(&b[..want.len()], &want[..]);
        assert_eq!(&b[want.len()..], &2.5f64.to_le_bytes());
    }

    #[test]
    fn u8_arrays_and_files() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("class.npy");
        write_npy_u8(&path, &[2, 2], &[1, 2, 3, 4]).unwrap();
        let b = std::fs::read(&path).unwrap();
        let want = numpy_header("{'descr': '|u1', 'fortran_order': False, 'shape': (2, 2), }");
        assert_eq!(&b[..want.len()], &want[..]);
        assert_eq!(&b[want.len()..], &[1, 2, 3, 4]);

        assert_eq!(
            read_npy_u8(&dir.path().join("class.npy")).unwrap(),
            (vec![2, 2], vec![1, 2, 3, 4])
        );
        std::fs::write(dir.path().join("bad.npy"), b"not numpy").unwrap();
        assert!(read_npy_u8(&dir.path().join("bad.npy")).is_err());

        let path = dir.path().join("sali.npy");
        write_npy_f64(&path, &[1, 3], &[0.1, 0.2, 0.3]).unwrap();
        assert_eq!(
            std::fs::read(&path).unwrap(),
            npy_bytes_f64(&[1, 3], &[0.1, 0.2, 0.3])
        );
    }

    #[test]
    fn shape_must_match_the_data() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.npy");
        match write_npy_u8(&path, &[2, 2], &[1, 2, 3]) {
            Err(ReportError::Plot(msg)) => assert!(msg.contains("[2, 2]"), "{msg}"),
            other => panic!("{other:?}"),
        }
        assert!(matches!(
            write_npy_f64(&path, &[4], &[1.0]),
            Err(ReportError::Plot(_))
        ));
        assert!(!path.exists(), "nothing is written on a mismatch");
        // A folder that does not exist is an I/O error.
        assert!(matches!(
            write_npy_f64(&dir.path().join("no/such/a.npy"), &[1], &[1.0]),
            Err(ReportError::Io(_))
        ));
    }

    #[test]
    #[should_panic(expected = "holds 6 values, data has 5")]
    fn in_memory_bytes_refuse_a_mismatched_shape() {
        npy_bytes_f64(&[2, 3], &[0.0; 5]);
    }
}
