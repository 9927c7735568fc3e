//! Recent middle-ear solves of whole-grid runs, for callers that ask for them again.
//!
//! One solve per frequency gives the drum's loading and every velocity per unit flow
//! into the drum; the residual canal, the microphone's place, the LDV beam's angle and
//! the probe's effects act only after it (`model` module docs). A finite-difference
//! Jacobian moves one column at a time from the same row, so its columns for those
//! nuisances ask for the base row's solve again: kept here, they cost a few complex
//! numbers a frequency instead of a solve. Entries are the solve's outputs bit for bit,
//! so an answer from here equals a fresh run's.

use super::drum::DrumCoefficients;
use super::params::{EFFECTS, Effects, N_EFFECTS, N_PARAMS, Theta};
use faer::c64;
use std::collections::VecDeque;

/// The unknowns a response is read from, at one frequency.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Solved {
    pub p_drum: c64,
    pub x_stapes: c64,
    pub phi_stapes: c64,
    pub umbo: c64,
}

/// What a solve depends on: θ and the effects with the after-solve ones zeroed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct SolveKey([f64; N_PARAMS], [f64; N_EFFECTS]);

/// θ entries read only after the solve (`model::Runner::response_at`).
const AFTER_SOLVE_PARAMS: [&str; 4] = ["canal_length", "canal_area", "mic_distance", "ldv_angle"];
/// Effects applied only to the responses (at the probe).
const AFTER_SOLVE_EFFECTS: [&str; 2] = ["probe_offset", "probe_leak"];

impl SolveKey {
    pub fn of(theta: &Theta, fx: &Effects) -> SolveKey {
        let mut t = theta.0;
        for (v, p) in t.iter_mut().zip(super::params::PARAMS.iter()) {
            if AFTER_SOLVE_PARAMS.contains(&p.name) {
                *v = 0.0;
            }
        }
        let mut e = fx.0;
        for (v, s) in e.iter_mut().zip(EFFECTS.iter()) {
            if AFTER_SOLVE_EFFECTS.contains(&s.name) {
                *v = 0.0;
            }
        }
        SolveKey(t, e)
    }
}

/// The last `capacity` distinct solves, most recently used first.
#[derive(Debug, Default)]
pub(crate) struct Memo {
    capacity: usize,
    entries: VecDeque<(SolveKey, Vec<Solved>)>,
    hits: usize,
}

impl Memo {
    pub fn new(capacity: usize) -> Memo {
        Memo { capacity, entries: VecDeque::with_capacity(capacity), hits: 0 }
    }

    /// The solves under `key`, moved to the front.
    pub fn get(&mut self, key: &SolveKey) -> Option<&[Solved]> {
        let i = self.entries.iter().position(|(k, _)| k == key)?;
        let entry = self.entries.remove(i)?;
        self.entries.push_front(entry);
        self.hits += 1;
        self.entries.front().map(|(_, s)| s.as_slice())
    }

    pub fn insert(&mut self, key: SolveKey, solved: Vec<Solved>) {
        if self.capacity == 0 {
            return;
        }
        if self.entries.len() == self.capacity {
            self.entries.pop_back();
        }
        self.entries.push_front((key, solved));
    }

    pub fn hits(&self) -> usize {
        self.hits
    }
}

/// The condensed drum's block at one frequency for its last few distinct coefficient
/// sets, most recently used first. The block depends on the drum's stiffness factor, the
/// frequency and the cavity only, so a Jacobian column of a parameter behind the drum
/// (the ossicular chain's, the damping when the drum's loss is its own, the cochlear
/// load) reuses the base row's: the modal sum is two fifths of a solve.
#[derive(Debug)]
pub(crate) struct DrumMemo {
    capacity: usize,
    entries: VecDeque<(DrumCoefficients, [c64; 16], usize)>,
    hits: usize,
}

impl DrumMemo {
    pub fn new(capacity: usize) -> DrumMemo {
        DrumMemo { capacity, entries: VecDeque::with_capacity(capacity), hits: 0 }
    }

    pub fn get(&mut self, c: &DrumCoefficients) -> Option<&[c64]> {
        let i = self.entries.iter().position(|(k, _, _)| k == c)?;
        let entry = self.entries.remove(i)?;
        self.entries.push_front(entry);
        self.hits += 1;
        self.entries.front().map(|(_, b, n)| &b[..*n])
    }

    pub fn insert(&mut self, c: DrumCoefficients, block: &[c64]) {
        if self.capacity == 0 || block.len() > 16 {
            return;
        }
        if self.entries.len() == self.capacity {
            self.entries.pop_back();
        }
        let mut b = [c64::new(0.0, 0.0); 16];
        b[..block.len()].copy_from_slice(block);
        self.entries.push_front((c, b, block.len()));
    }

    pub fn hits(&self) -> usize {
        self.hits
    }
}
