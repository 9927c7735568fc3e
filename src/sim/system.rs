//! A sparse complex system A(ω) = Σ_b κ_b(ω) B_b with a fixed pattern, solved with
//! faer's sparse LU. The symbolic factorisation is computed once per pattern (one per
//! mesh) and shared by every frequency and every parameter set; each `Workspace` owns
//! the numeric buffers of one thread.

use faer::c64;
use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::sparse::linalg::lu::{NumericLu, SymbolicLu, factorize_symbolic_lu};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Par};
use std::collections::BTreeMap;
use std::sync::Arc;

/// Collects (row, col, value) entries of named real blocks before the pattern is frozen.
#[derive(Default)]
pub struct SystemBuilder {
    n: usize,
    blocks: Vec<Vec<(usize, usize, f64)>>,
}

impl SystemBuilder {
    /// An empty pattern for `n` unknowns.
    pub fn new(n: usize) -> Self {
        SystemBuilder { n, blocks: Vec::new() }
    }

    /// Starts a new block and returns its id; entries are added with [`Self::add`].
    pub fn block(&mut self) -> usize {
        self.blocks.push(Vec::new());
        self.blocks.len() - 1
    }

    /// Adds `value` at (`row`, `col`) to `block`: each block is later scaled by one
    /// coefficient per parameter set and frequency.
    pub fn add(&mut self, block: usize, row: usize, col: usize, value: f64) {
        assert!(row < self.n && col < self.n, "entry ({row}, {col}) outside a {0}×{0} system", self.n);
        self.blocks[block].push((row, col, value));
    }

    /// Adds k·a·aᵀ for a linear form a = Σ coef·q[idx] (a spring on that displacement).
    pub fn add_outer(&mut self, block: usize, form: &[(usize, f64)], k: f64) {
        for &(i, ci) in form {
            for &(j, cj) in form {
                self.add(block, i, j, k * ci * cj);
            }
        }
    }

    /// Freezes the pattern (every structurally possible entry, also those whose value is
    /// zero for some parameters) and computes the symbolic LU.
    pub fn build(self) -> Result<System, faer::sparse::FaerError> {
        let mut slots: BTreeMap<(usize, usize), usize> = BTreeMap::new();
        for (r, c) in (0..self.n).map(|i| (i, i)).chain(self.blocks.iter().flatten().map(|&(r, c, _)| (r, c))) {
            slots.entry((c, r)).or_insert(0);
        }
        let mut col_ptr = vec![0usize; self.n + 1];
        let mut row_idx = Vec::with_capacity(slots.len());
        for (k, (&(c, r), slot)) in slots.iter_mut().enumerate() {
            *slot = k;
            row_idx.push(r);
            col_ptr[c + 1] += 1;
        }
        for c in 0..self.n {
            col_ptr[c + 1] += col_ptr[c];
        }
        let blocks =
            self.blocks.into_iter().map(|b| b.into_iter().map(|(r, c, v)| (slots[&(c, r)], v)).collect()).collect();
        let sym = SymbolicSparseColMatRef::new_checked(self.n, self.n, &col_ptr, None, &row_idx);
        let symbolic = factorize_symbolic_lu(sym, Default::default())?;
        Ok(System { n: self.n, col_ptr, row_idx, blocks, symbolic: Arc::new(symbolic) })
    }
}

/// max(|re|, |im|): a scale within √2 of |z|, without the cost of `hypot`.
fn abs_max(z: c64) -> f64 {
    z.re.abs().max(z.im.abs())
}

/// A frozen pattern with its blocks (entries as value-array slots) and symbolic LU.
pub struct System {
    /// Unknowns.
    pub n: usize,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    blocks: Vec<Vec<(usize, f64)>>,
    symbolic: Arc<SymbolicLu<usize>>,
}

/// Why a solve failed.
#[derive(Debug, thiserror::Error)]
pub enum SolveError {
    /// The numeric LU met a zero pivot.
    #[error("singular system at {freq_hz:.1} Hz")]
    Singular {
        /// The frequency solved, Hz.
        freq_hz: f64,
    },
    /// The solution has a NaN or infinite entry.
    #[error("non-finite solution at {freq_hz:.1} Hz")]
    NonFinite {
        /// The frequency solved, Hz.
        freq_hz: f64,
    },
}

/// Per-thread buffers: matrix values, scalings, LU values, workspace.
pub struct Workspace {
    values: Vec<c64>,
    row_scale: Vec<f64>,
    col_scale: Vec<f64>,
    numeric: NumericLu<usize, c64>,
    mem: MemBuffer,
    /// The last solve's solution.
    pub x: Vec<c64>,
}

impl System {
    /// Blocks, i.e. how many coefficients a solve takes.
    pub fn n_blocks(&self) -> usize {
        self.blocks.len()
    }

    /// Stored entries of the pattern.
    pub fn nnz(&self) -> usize {
        self.row_idx.len()
    }

    /// Buffers for one thread's solves, sized for this pattern (allocated once, reused
    /// for every frequency).
    pub fn workspace(&self) -> Workspace {
        let req = StackReq::any_of(&[
            self.symbolic.factorize_numeric_lu_scratch::<c64>(Par::Seq, Default::default()),
            self.symbolic.solve_in_place_scratch::<c64>(1, Par::Seq),
        ]);
        Workspace {
            values: vec![c64::new(0.0, 0.0); self.nnz()],
            row_scale: vec![0.0; self.n],
            col_scale: vec![0.0; self.n],
            numeric: NumericLu::new(),
            mem: MemBuffer::new(req),
            x: vec![c64::new(0.0, 0.0); self.n],
        }
    }

    /// Quadratic form xᴴ B x of one real block at the last solution in `ws`.
    pub fn quadratic_form(&self, block: usize, ws: &Workspace) -> c64 {
        // The block's entries carry their (row, col) through the slot; recover them.
        let mut acc = c64::new(0.0, 0.0);
        for &(slot, v) in &self.blocks[block] {
            let (r, c) = self.slot_position(slot);
            acc += ws.x[r].conj() * ws.x[c] * v;
        }
        acc
    }

    fn slot_position(&self, slot: usize) -> (usize, usize) {
        let c = self.col_ptr.partition_point(|&p| p <= slot) - 1;
        (self.row_idx[slot], c)
    }

    /// Solves (Σ_b coef[b]·B_b) x = rhs into `ws.x`. `rhs` entries are (row, value).
    pub fn solve(
        &self,
        coef: &[c64],
        rhs: &[(usize, c64)],
        ws: &mut Workspace,
        freq_hz: f64,
    ) -> Result<(), SolveError> {
        assert_eq!(coef.len(), self.blocks.len());
        ws.values.fill(c64::new(0.0, 0.0));
        for (block, &k) in self.blocks.iter().zip(coef) {
            if k == c64::new(0.0, 0.0) {
                continue;
            }
            for &(slot, v) in block {
                ws.values[slot] += k * v;
            }
        }
        // One pass of row then column equilibration: the system mixes pressures (Pa) and
        // displacements (nm), whose raw entries span ~12 decades.
        ws.row_scale.fill(0.0);
        for c in 0..self.n {
            for k in self.col_ptr[c]..self.col_ptr[c + 1] {
                let r = self.row_idx[k];
                ws.row_scale[r] = ws.row_scale[r].max(abs_max(ws.values[k]));
            }
        }
        for s in ws.row_scale.iter_mut() {
            *s = if *s > 0.0 { 1.0 / *s } else { 1.0 };
        }
        for c in 0..self.n {
            let mut m = 0.0f64;
            for k in self.col_ptr[c]..self.col_ptr[c + 1] {
                ws.values[k] *= ws.row_scale[self.row_idx[k]];
                m = m.max(abs_max(ws.values[k]));
            }
            let s = if m > 0.0 { 1.0 / m } else { 1.0 };
            ws.col_scale[c] = s;
            for k in self.col_ptr[c]..self.col_ptr[c + 1] {
                ws.values[k] *= s;
            }
        }
        let sym = SymbolicSparseColMatRef::new_checked(self.n, self.n, &self.col_ptr, None, &self.row_idx);
        let a = SparseColMatRef::new(sym, &ws.values);
        let lu = self
            .symbolic
            .factorize_numeric_lu(&mut ws.numeric, a, Par::Seq, MemStack::new(&mut ws.mem), Default::default())
            .map_err(|_| SolveError::Singular { freq_hz })?;
        ws.x.fill(c64::new(0.0, 0.0));
        for &(r, v) in rhs {
            ws.x[r] += v * ws.row_scale[r];
        }
        let rhs_mat = MatMut::from_column_major_slice_mut(&mut ws.x, self.n, 1);
        lu.solve_in_place_with_conj(Conj::No, rhs_mat, Par::Seq, MemStack::new(&mut ws.mem));
        for (xi, s) in ws.x.iter_mut().zip(&ws.col_scale) {
            *xi *= *s;
        }
        if ws.x.iter().any(|v| !v.re.is_finite() || !v.im.is_finite()) {
            return Err(SolveError::NonFinite { freq_hz });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    /// Spring–mass–dashpot with Rayleigh stiffness damping, through the same sparse
    /// path as the ear: blocks K, M, C with coefficients (1 + jωβ), −ω², jω.
    fn smd(k: f64, m: f64, c: f64, beta: f64, w: f64) -> c64 {
        let mut b = SystemBuilder::new(1);
        let (bk, bm, bc) = (b.block(), b.block(), b.block());
        b.add(bk, 0, 0, k);
        b.add(bm, 0, 0, m);
        b.add(bc, 0, 0, c);
        let sys = b.build().unwrap();
        let mut ws = sys.workspace();
        let coef = [c64::new(1.0, w * beta), c64::new(-w * w, 0.0), c64::new(0.0, w)];
        sys.solve(&coef, &[(0, c64::new(1.0, 0.0))], &mut ws, w / (2.0 * PI)).unwrap();
        ws.x[0]
    }

    #[test]
    fn spring_mass_dashpot_matches_closed_form() {
        let (k, m, c): (f64, f64, f64) = (800.0, 3e-6, 0.2);
        let wn = (k / m).sqrt();
        for w in [0.1 * wn, wn, 3.0 * wn] {
            let x = smd(k, m, c, 0.0, w);
            let exact = c64::new(1.0, 0.0) / c64::new(k - m * w * w, w * c);
            assert!((x - exact).norm() < 1e-12 * exact.norm());
        }
        // Velocity peak exactly at ω_n, height 1/c, phase 0 there.
        let v = c64::new(0.0, wn) * smd(k, m, c, 0.0, wn);
        assert!((v.re - 1.0 / c).abs() < 1e-9 / c && v.im.abs() < 1e-9 / c);
        // Rayleigh β gives ζ = βω_n/2 and a half-power bandwidth Δω/ω_n = 2ζ.
        let beta = 2.0 * 0.05 / wn;
        let peak = (c64::new(0.0, wn) * smd(k, m, 0.0, beta, wn)).norm();
        let expected = 1.0 / (beta * k); // velocity/force at ω_n: 1/(ω_n β k)·ω_n
        assert!((peak / expected - 1.0).abs() < 1e-9, "{peak} vs {expected}");
    }

    #[test]
    fn pattern_keeps_zero_valued_entries_and_solves_a_coupled_pair() {
        // Two masses in series: compare with a hand-solved 2×2.
        let (k1, k2, m1, m2, w) = (1000.0, 500.0, 2e-5, 3e-6, 3000.0);
        let mut b = SystemBuilder::new(2);
        let (bk, bm) = (b.block(), b.block());
        b.add_outer(bk, &[(0, 1.0)], k1);
        b.add_outer(bk, &[(0, 1.0), (1, -1.0)], k2);
        b.add(bm, 0, 0, m1);
        b.add(bm, 1, 1, m2);
        let sys = b.build().unwrap();
        let mut ws = sys.workspace();
        sys.solve(&[c64::new(1.0, 0.0), c64::new(-w * w, 0.0)], &[(1, c64::new(1.0, 0.0))], &mut ws, 0.0).unwrap();
        let (a11, a12, a22) = (k1 + k2 - m1 * w * w, -k2, k2 - m2 * w * w);
        let det = a11 * a22 - a12 * a12;
        assert!((ws.x[0].re - (-a12 / det)).abs() < 1e-12 * (a12 / det).abs());
        assert!((ws.x[1].re - (a11 / det)).abs() < 1e-12 * (a11 / det).abs());
    }
}
