//! A sparse complex system A(ω) = Σ_b κ_b(ω) B_b with a fixed pattern. A small system
//! (the condensed ear has 8–9 unknowns) is solved densely, by Gaussian elimination with
//! partial pivoting: faer's sparse machinery costs more than the arithmetic at that size.
//! A larger one (the uncondensed drum of the tests) goes through faer's sparse LU, whose
//! symbolic factorisation is computed once per pattern and shared by every frequency and
//! every parameter set. Each `Workspace` owns the numeric buffers of one thread.

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
        let symbolic = if self.n <= DENSE_MAX {
            None
        } else {
            let sym = SymbolicSparseColMatRef::new_checked(self.n, self.n, &col_ptr, None, &row_idx);
            Some(Arc::new(factorize_symbolic_lu(sym, Default::default())?))
        };
        Ok(System { n: self.n, col_ptr, row_idx, blocks, symbolic })
    }
}

/// Systems up to this size are solved densely (`bench sim`: the 8-unknown ear's solve
/// takes a fraction of faer's sparse LU time).
const DENSE_MAX: usize = 24;

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
    /// The sparse path's symbolic LU; `None` for a system solved densely.
    symbolic: Option<Arc<SymbolicLu<usize>>>,
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
    /// The dense path's matrix (column-major), overwritten by its LU factors.
    dense: Vec<c64>,
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
        let req = match &self.symbolic {
            Some(sym) => StackReq::any_of(&[
                sym.factorize_numeric_lu_scratch::<c64>(Par::Seq, Default::default()),
                sym.solve_in_place_scratch::<c64>(1, Par::Seq),
            ]),
            None => StackReq::EMPTY,
        };
        let dense = if self.symbolic.is_none() { self.n * self.n } else { 0 };
        Workspace {
            values: vec![c64::new(0.0, 0.0); self.nnz()],
            row_scale: vec![0.0; self.n],
            col_scale: vec![0.0; self.n],
            numeric: NumericLu::new(),
            mem: MemBuffer::new(req),
            dense: vec![c64::new(0.0, 0.0); dense],
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
        ws.x.fill(c64::new(0.0, 0.0));
        for &(r, v) in rhs {
            ws.x[r] += v * ws.row_scale[r];
        }
        match &self.symbolic {
            None => self.solve_dense(ws).ok_or(SolveError::Singular { freq_hz })?,
            Some(symbolic) => {
                let sym = SymbolicSparseColMatRef::new_checked(self.n, self.n, &self.col_ptr, None, &self.row_idx);
                let a = SparseColMatRef::new(sym, &ws.values);
                let lu = symbolic
                    .factorize_numeric_lu(&mut ws.numeric, a, Par::Seq, MemStack::new(&mut ws.mem), Default::default())
                    .map_err(|_| SolveError::Singular { freq_hz })?;
                let rhs_mat = MatMut::from_column_major_slice_mut(&mut ws.x, self.n, 1);
                lu.solve_in_place_with_conj(Conj::No, rhs_mat, Par::Seq, MemStack::new(&mut ws.mem));
            }
        }
        for (xi, s) in ws.x.iter_mut().zip(&ws.col_scale) {
            *xi *= *s;
        }
        if ws.x.iter().any(|v| !v.re.is_finite() || !v.im.is_finite()) {
            return Err(SolveError::NonFinite { freq_hz });
        }
        Ok(())
    }

    /// Solves the equilibrated system in `ws.values` for the right-hand side in `ws.x`
    /// (in place), densely: Gaussian elimination with partial pivoting on the largest
    /// |re| + |im| in the column. `None` on a zero pivot.
    fn solve_dense(&self, ws: &mut Workspace) -> Option<()> {
        let n = self.n;
        let a = &mut ws.dense;
        a.fill(c64::new(0.0, 0.0));
        for c in 0..n {
            for k in self.col_ptr[c]..self.col_ptr[c + 1] {
                a[c * n + self.row_idx[k]] = ws.values[k];
            }
        }
        let x = &mut ws.x;
        for j in 0..n {
            let p = (j..n).max_by(|&r, &s| abs_max(a[j * n + r]).total_cmp(&abs_max(a[j * n + s])))?;
            if a[j * n + p] == c64::new(0.0, 0.0) {
                return None;
            }
            if p != j {
                for c in j..n {
                    a.swap(c * n + p, c * n + j);
                }
                x.swap(p, j);
            }
            let inv = c64::new(1.0, 0.0) / a[j * n + j];
            for r in j + 1..n {
                let l = a[j * n + r] * inv;
                if l == c64::new(0.0, 0.0) {
                    continue;
                }
                for c in j + 1..n {
                    let u = a[c * n + j];
                    a[c * n + r] -= l * u;
                }
                let xj = x[j];
                x[r] -= l * xj;
            }
        }
        for j in (0..n).rev() {
            let mut v = x[j];
            for c in j + 1..n {
                v -= a[c * n + j] * x[c];
            }
            x[j] = v / a[j * n + j];
        }
        Some(())
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

    /// A random sparse complex system of `n` unknowns with zeros on the diagonal of its
    /// first rows (so elimination must pivot), as one block with coefficient 1 plus a
    /// second block scaled by a complex coefficient.
    fn random_system(n: usize, seed: u64) -> (System, Vec<c64>, faer::Mat<c64>) {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut b = SystemBuilder::new(n);
        let (b0, b1) = (b.block(), b.block());
        let coef = vec![c64::new(1.0, 0.0), c64::new(0.3, -2.0)];
        let mut dense = faer::Mat::<c64>::zeros(n, n);
        for r in 0..n {
            for c in 0..n {
                let zero_diagonal = r == c && r < 3;
                if zero_diagonal || (r != c && rng.random::<f64>() < 0.6) {
                    continue;
                }
                // Entries over ten decades, as in the ear (pressures against displacements).
                let (v0, v1) = (rng.random::<f64>() - 0.5, rng.random::<f64>() - 0.5);
                let scale = 10f64.powf(10.0 * rng.random::<f64>() - 5.0);
                b.add(b0, r, c, v0 * scale);
                b.add(b1, r, c, v1 * scale);
                dense[(r, c)] = coef[0] * (v0 * scale) + coef[1] * (v1 * scale);
            }
            // A superdiagonal keeps the zero-diagonal rows regular.
            let c = (r + 1) % n;
            b.add(b0, r, c, 1.0);
            dense[(r, c)] += c64::new(1.0, 0.0);
        }
        (b.build().unwrap(), coef, dense)
    }

    #[test]
    fn the_dense_path_solves_what_faer_solves_and_pivots() {
        use faer::prelude::Solve;
        for (n, seed) in [(5, 1), (9, 2), (DENSE_MAX, 3)] {
            let (sys, coef, dense) = random_system(n, seed);
            assert!(sys.symbolic.is_none(), "{n} unknowns take the dense path");
            let mut ws = sys.workspace();
            sys.solve(&coef, &[(0, c64::new(1.0, 0.0)), (n - 1, c64::new(0.0, 2.0))], &mut ws, 0.0).unwrap();
            let mut rhs = faer::Mat::<c64>::zeros(n, 1);
            rhs[(0, 0)] = c64::new(1.0, 0.0);
            rhs[(n - 1, 0)] += c64::new(0.0, 2.0);
            let want = dense.partial_piv_lu().solve(&rhs);
            let residual = &dense * faer::Mat::from_fn(n, 1, |i, _| ws.x[i]) - &rhs;
            let worst =
                (0..n).map(|i| (ws.x[i] - want[(i, 0)]).norm() / want[(i, 0)].norm().max(1e-300)).fold(0.0, f64::max);
            assert!(worst < 1e-9, "{n} unknowns: worst relative difference from faer's dense LU {worst:.2e}");
            assert!(residual.norm_l2() < 1e-9 * rhs.norm_l2(), "{n} unknowns: residual {}", residual.norm_l2());
        }
    }

    #[test]
    fn a_singular_system_is_an_error_naming_the_frequency_on_either_path() {
        for n in [3, DENSE_MAX + 1] {
            let mut b = SystemBuilder::new(n);
            let k = b.block();
            for i in 0..n {
                b.add(k, i, i, 1.0);
            }
            let sys = b.build().unwrap();
            assert_eq!(sys.symbolic.is_none(), n <= DENSE_MAX);
            let mut ws = sys.workspace();
            let got = sys.solve(&[c64::new(0.0, 0.0)], &[(0, c64::new(1.0, 0.0))], &mut ws, 250.0);
            // faer's sparse LU does not stop on a zero pivot; its infinite answer is caught.
            let named = match got {
                Err(SolveError::Singular { freq_hz }) => freq_hz,
                Err(SolveError::NonFinite { freq_hz }) if n > DENSE_MAX => freq_hz,
                other => panic!("{n} unknowns: {other:?}"),
            };
            assert_eq!(named, 250.0);
        }
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
