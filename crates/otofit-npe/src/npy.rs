//! NumPy `.npy` tables (format version 1.0): little-endian f64, C order, shape
//! (rows, columns). A binary table is written at memory speed and read by numpy,
//! pandas and polars directly (`numpy.load`), where a CSV of a million rows costs
//! minutes of number formatting. The row count is not known until a streamed table is
//! finished, so the header reserves room for it and is written again at the end.

use std::io::{Read, Seek, SeekFrom, Write};

/// The magic string and version 1.0 that open every file.
const MAGIC: &[u8] = b"\x93NUMPY\x01\x00";

/// Width reserved for the row count in the header (u64's 20 digits).
const ROWS_WIDTH: usize = 20;

/// The header (magic, length and dictionary, padded to a multiple of 64 bytes as the
/// format asks) of a table of `rows` × `cols`; always the same length for a given
/// `cols`, so a finished table's header overwrites its placeholder exactly.
pub fn header(rows: u64, cols: usize) -> Vec<u8> {
    let dict = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({rows:>ROWS_WIDTH$}, {cols}), }}");
    let unpadded = MAGIC.len() + 2 + dict.len() + 1;
    let total = unpadded.div_ceil(64) * 64;
    let mut h = Vec::with_capacity(total);
    h.extend_from_slice(MAGIC);
    h.extend_from_slice(&((total - MAGIC.len() - 2) as u16).to_le_bytes());
    h.extend_from_slice(dict.as_bytes());
    h.resize(total - 1, b' ');
    h.push(b'\n');
    h
}

/// Appends `values` (whole rows) as little-endian f64.
pub fn write_values(w: &mut impl Write, values: &[f64]) -> std::io::Result<()> {
    let mut bytes = Vec::with_capacity(8 * values.len());
    for v in values {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    w.write_all(&bytes)
}

/// Writes the header of the finished table over its placeholder at the file's start.
pub fn finish(f: &mut (impl Write + Seek), rows: u64, cols: usize) -> std::io::Result<()> {
    let end = f.stream_position()?;
    f.seek(SeekFrom::Start(0))?;
    f.write_all(&header(rows, cols))?;
    f.seek(SeekFrom::Start(end))?;
    f.flush()
}

/// Why a file is not a table this module reads.
#[derive(Debug, thiserror::Error)]
pub enum NpyError {
    /// Reading failed.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// The file is not a 2-D little-endian f64 C-order .npy table.
    #[error("{0}")]
    Format(String),
}

/// Reads a 2-D little-endian f64 C-order table: (rows, columns, values row by row).
pub fn read(r: &mut impl Read) -> Result<(usize, usize, Vec<f64>), NpyError> {
    let bad = |why: &str| NpyError::Format(format!("not a 2-D float64 .npy table: {why}"));
    let mut lead = [0u8; 10];
    r.read_exact(&mut lead)?;
    if &lead[..6] != b"\x93NUMPY" {
        return Err(bad("no NUMPY magic"));
    }
    let len = match lead[6] {
        1 => u16::from_le_bytes([lead[8], lead[9]]) as usize,
        2 | 3 => {
            let mut more = [0u8; 2];
            r.read_exact(&mut more)?;
            u32::from_le_bytes([lead[8], lead[9], more[0], more[1]]) as usize
        }
        v => return Err(bad(&format!("format version {v}"))),
    };
    if len > 1 << 20 {
        return Err(bad("header longer than 1 MiB"));
    }
    let mut dict = vec![0u8; len];
    r.read_exact(&mut dict)?;
    let dict = String::from_utf8(dict).map_err(|_| bad("header is not text"))?;
    let squeezed: String = dict.chars().filter(|c| !c.is_whitespace()).collect();
    if !squeezed.contains("'descr':'<f8'") {
        return Err(bad("dtype is not '<f8'"));
    }
    if !squeezed.contains("'fortran_order':False") {
        return Err(bad("Fortran order"));
    }
    let shape = squeezed.split("'shape':(").nth(1).and_then(|s| s.split(')').next()).ok_or_else(|| bad("no shape"))?;
    let dims: Vec<usize> = shape
        .split(',')
        .filter(|s| !s.is_empty())
        .map(|s| s.parse().map_err(|_| bad(&format!("shape ({shape})"))))
        .collect::<Result<_, _>>()?;
    let [rows, cols] = dims[..] else { return Err(bad(&format!("shape ({shape}) is not 2-D"))) };
    let n = rows.checked_mul(cols).filter(|n| *n <= usize::MAX / 8).ok_or_else(|| bad("shape too large"))?;
    let mut bytes = Vec::new();
    r.take(8 * n as u64).read_to_end(&mut bytes)?;
    if bytes.len() != 8 * n {
        return Err(bad(&format!("{} bytes of data for shape ({rows}, {cols})", bytes.len())));
    }
    let values = bytes.chunks_exact(8).map(|b| f64::from_le_bytes(b.try_into().expect("8 bytes"))).collect();
    Ok((rows, cols, values))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Cursor;

    #[test]
    fn headers_are_padded_to_64_bytes_and_keep_their_length() {
        for cols in [1, 14, 350] {
            let (a, b) = (header(0, cols), header(1_000_000, cols));
            assert_eq!(a.len() % 64, 0);
            assert_eq!(a.len(), b.len(), "cols {cols}");
            assert_eq!(*a.last().unwrap(), b'\n');
        }
    }

    #[test]
    fn a_streamed_table_reads_back_exactly() {
        let mut f = Cursor::new(Vec::new());
        f.write_all(&header(0, 3)).unwrap();
        let values = [1.5, -2.0, 1e-300, f64::MAX, 0.1, 3.0];
        write_values(&mut f, &values[..3]).unwrap();
        write_values(&mut f, &values[3..]).unwrap();
        finish(&mut f, 2, 3).unwrap();
        let (rows, cols, back) = read(&mut Cursor::new(f.into_inner())).unwrap();
        assert_eq!((rows, cols), (2, 3));
        assert_eq!(back, values);
    }

    #[test]
    fn other_layouts_are_refused_naming_why() {
        let mut bytes = header(2, 3);
        let at = bytes.windows(5).position(|w| w == b"False").unwrap();
        bytes[at..at + 5].copy_from_slice(b"True ");
        bytes.extend_from_slice(&[0u8; 48]);
        let e = read(&mut Cursor::new(bytes)).unwrap_err().to_string();
        assert!(e.contains("Fortran"), "{e}");
        let mut short = header(2, 3);
        short.extend_from_slice(&[0u8; 40]);
        let e = read(&mut Cursor::new(short)).unwrap_err().to_string();
        assert!(e.contains("40 bytes"), "{e}");
        let e = read(&mut Cursor::new(b"col1,col2\n1,2\n".to_vec())).unwrap_err().to_string();
        assert!(e.contains("magic"), "{e}");
    }
}
