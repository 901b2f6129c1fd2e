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

/// The bytes of an f64 array ('<f8').
pub fn npy_bytes_f64(shape: &[usize], data: &[f64]) -> Vec<u8> {
    let mut out = header("<f8", shape);
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_is_what_numpy_writes() {
        let b = npy_bytes_f64(&[2, 3], &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        assert_eq!(&b[..8], b"\x93NUMPY\x01\x00");
        let hlen = u16::from_le_bytes([b[8], b[9]]) as usize;
        assert_eq!((10 + hlen) % 64, 0);
        let dict = std::str::from_utf8(&b[10..10 + hlen]).unwrap();
        assert!(dict.starts_with("{'descr': '<f8', 'fortran_order': False, 'shape': (2, 3), }"));
        assert!(dict.ends_with(" \n"));
        assert_eq!(b.len(), 10 + hlen + 48);
        assert_eq!(&b[10 + hlen..10 + hlen + 8], &1.0f64.to_le_bytes());
        let one_d = npy_bytes_f64(&[5], &[0.0; 5]);
        assert!(std::str::from_utf8(&one_d[10..70])
            .unwrap()
            .contains("'shape': (5,)"));
    }

    #[test]
    fn shape_must_match_the_data() {
        let dir = tempfile::tempdir().unwrap();
        assert!(write_npy_u8(&dir.path().join("a.npy"), &[2, 2], &[1, 2, 3]).is_err());
        write_npy_u8(&dir.path().join("b.npy"), &[2, 2], &[1, 2, 3, 4]).unwrap();
        let b = std::fs::read(dir.path().join("b.npy")).unwrap();
        assert_eq!(&b[b.len() - 4..], &[1, 2, 3, 4]);
        assert!(std::str::from_utf8(&b[10..30]).unwrap().contains("'|u1'"));
    }
}
