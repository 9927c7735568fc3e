//! A disk cache of the default drum's modes. Their eigendecomposition takes seconds (8 s
//! at 20 rings on one core), and every process that simulates needs it: the service at
//! start-up, each CLI run, each test process. The modes depend only on the assembled
//! matrices, so the file is named by a hash of them: any change to the mesh, the
//! materials or the assembly names a new file, and a stale one is never read.
//!
//! The directory is `$OTOFIT_CACHE_DIR`, else `$XDG_CACHE_HOME/otofit`, else
//! `$HOME/.cache/otofit`. A missing, unreadable or unwritable cache only costs time: the
//! modes are then computed, as without it.

use super::drum::DrumError;
use super::drum_mesh::{DrumFe, ManubriumModes};
use std::path::{Path, PathBuf};

/// Bumped when the file layout changes.
const FORMAT: &[u8] = b"otofit-drum-modes-1";

/// The drum's modes, from the cache when it holds them, else computed and stored.
pub fn modes(fe: &DrumFe) -> Result<ManubriumModes, DrumError> {
    let Some(path) = dir().map(|d| d.join(file_name(fe))) else {
        return Ok(ManubriumModes::new(fe)?.0);
    };
    if let Some(m) = std::fs::read(&path).ok().and_then(|b| decode(&b, fe)) {
        return Ok(m);
    }
    let (m, _) = ManubriumModes::new(fe)?;
    store(&path, &encode(&m));
    Ok(m)
}

fn dir() -> Option<PathBuf> {
    let var = |k: &str| std::env::var_os(k).filter(|v| !v.is_empty()).map(PathBuf::from);
    var("OTOFIT_CACHE_DIR")
        .or_else(|| var("XDG_CACHE_HOME").map(|d| d.join("otofit")))
        .or_else(|| var("HOME").map(|d| d.join(".cache").join("otofit")))
}

/// Writes through a temporary file and a rename, so a reader never sees half a file and
/// two processes filling the cache at once both leave a whole one. Failures are ignored.
fn store(path: &Path, bytes: &[u8]) {
    let Some(parent) = path.parent() else { return };
    if std::fs::create_dir_all(parent).is_err() {
        return;
    }
    let tmp = path.with_extension(format!("tmp{}", std::process::id()));
    if std::fs::write(&tmp, bytes).is_ok() && std::fs::rename(&tmp, path).is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
}

/// `drum-modes-<hash>.bin`, the hash (FNV-1a, 64 bit) over the format tag and every
/// matrix the eigendecomposition reads.
pub fn file_name(fe: &DrumFe) -> String {
    let mut h = Fnv::default();
    h.bytes(FORMAT);
    h.bytes(&(fe.n as u64).to_le_bytes());
    for t in [&fe.k_ii, &fe.m_ii] {
        h.bytes(&(t.len() as u64).to_le_bytes());
        for &(i, j, v) in t.iter() {
            h.bytes(&(i as u64).to_le_bytes());
            h.bytes(&(j as u64).to_le_bytes());
            h.bytes(&v.to_le_bytes());
        }
    }
    for v in [&fe.b_i, &fe.k_ib[0], &fe.k_ib[1], &fe.m_ib[0], &fe.m_ib[1]] {
        for x in v.iter() {
            h.bytes(&x.to_le_bytes());
        }
    }
    format!("drum-modes-{:016x}.bin", h.0)
}

/// The format tag, n, then μ and g (6 little-endian f64 per mode).
fn encode(m: &ManubriumModes) -> Vec<u8> {
    let mut out = Vec::with_capacity(FORMAT.len() + 8 + 48 * m.mu.len());
    out.extend_from_slice(FORMAT);
    out.extend_from_slice(&(m.mu.len() as u64).to_le_bytes());
    for (mu, g) in m.mu.iter().zip(&m.g) {
        for x in std::iter::once(mu).chain(g) {
            out.extend_from_slice(&x.to_le_bytes());
        }
    }
    out
}

/// `None` unless the bytes hold exactly `fe.n` finite modes in this format.
fn decode(bytes: &[u8], fe: &DrumFe) -> Option<ManubriumModes> {
    let rest = bytes.strip_prefix(FORMAT)?;
    let (n, rest) = rest.split_at_checked(8)?;
    let n = u64::from_le_bytes(n.try_into().ok()?) as usize;
    if n != fe.n || rest.len() != 48 * n {
        return None;
    }
    let values: Vec<f64> = rest.chunks_exact(8).map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes"))).collect();
    if values.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let mu = values.chunks_exact(6).map(|c| c[0]).collect();
    let g = values.chunks_exact(6).map(|c| [c[1], c[2], c[3], c[4], c[5]]).collect();
    Some(ManubriumModes::from_modes(mu, g, fe))
}

struct Fnv(u64);

impl Default for Fnv {
    fn default() -> Self {
        Fnv(0xcbf2_9ce4_8422_2325)
    }
}

impl Fnv {
    fn bytes(&mut self, b: &[u8]) {
        for &x in b {
            self.0 = (self.0 ^ x as u64).wrapping_mul(0x0100_0000_01b3);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::anatomical_drum::AnatomicalDrum;
    use crate::drum::DrumCoefficients;
    use faer::c64;

    fn small() -> DrumFe {
        AnatomicalDrum { rings: 4, ..AnatomicalDrum::default() }.fe()
    }

    #[test]
    fn a_stored_file_gives_the_computed_condensation() {
        let fe = small();
        let (computed, _) = ManubriumModes::new(&fe).unwrap();
        let read = decode(&encode(&computed), &fe).expect("its own bytes decode");
        let w = 2.0 * std::f64::consts::PI * 3000.0;
        let c = DrumCoefficients { kappa: c64::new(20e6, 4e6), s: -w * w, jw: c64::new(0.0, w), cavity: 1e11 };
        let (a, b) = (computed.block(&c), read.block(&c));
        for (x, y) in a.iter().flatten().zip(b.iter().flatten()) {
            assert_eq!(x, y);
        }
    }

    #[test]
    fn a_damaged_or_foreign_file_is_not_read() {
        let fe = small();
        let bytes = encode(&ManubriumModes::new(&fe).unwrap().0);
        assert!(decode(&bytes[..bytes.len() - 1], &fe).is_none(), "truncated");
        let mut nan = bytes.clone();
        let at = nan.len() - 8;
        nan[at..].copy_from_slice(&f64::NAN.to_le_bytes());
        assert!(decode(&nan, &fe).is_none(), "not finite");
        let other = AnatomicalDrum { rings: 5, ..AnatomicalDrum::default() }.fe();
        assert!(decode(&bytes, &other).is_none(), "another mesh's modes");
    }

    #[test]
    fn the_name_changes_with_any_matrix_entry() {
        let fe = small();
        let mut k = small();
        k.k_ii[7].2 *= 1.0 + 1e-12;
        let mut m = small();
        m.m_ii[3].2 *= 1.0 + 1e-12;
        let mut b = small();
        b.b_i[1] += 1e-20;
        let name = file_name(&fe);
        assert_eq!(name, file_name(&small()), "the same drum, the same file");
        for (what, other) in [("stiffness", k), ("mass", m), ("swept volume", b)] {
            assert_ne!(name, file_name(&other), "{what}");
        }
    }

    #[test]
    fn the_cache_fills_and_is_reused() {
        let dir = std::env::temp_dir().join(format!("otofit-mode-cache-{}", std::process::id()));
        let fe = small();
        let path = dir.join(file_name(&fe));
        let (m, _) = ManubriumModes::new(&fe).unwrap();
        store(&path, &encode(&m));
        let read = std::fs::read(&path).unwrap();
        assert_eq!(read, encode(&m));
        assert!(std::fs::read_dir(&dir).unwrap().count() == 1, "no temporary file left");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
