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
use super::params::{EFFECTS, Effects, N_EFFECTS, N_PARAMS, PARAMS, Theta};
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

/// The last `capacity` distinct entries, most recently used first, and how often one
/// was found.
#[derive(Debug)]
struct Recent<K, V> {
    capacity: usize,
    entries: VecDeque<(K, V)>,
    hits: usize,
}

impl<K: PartialEq, V> Recent<K, V> {
    fn new(capacity: usize) -> Self {
        Recent { capacity, entries: VecDeque::with_capacity(capacity), hits: 0 }
    }

    /// The entry under `key`, moved to the front.
    fn get(&mut self, key: &K) -> Option<&V> {
        let i = self.entries.iter().position(|(k, _)| k == key)?;
        let entry = self.entries.remove(i)?;
        self.entries.push_front(entry);
        self.hits += 1;
        self.entries.front().map(|(_, v)| v)
    }

    fn insert(&mut self, key: K, value: V) {
        if self.capacity == 0 {
            return;
        }
        if self.entries.len() == self.capacity {
            self.entries.pop_back();
        }
        self.entries.push_front((key, value));
    }
}

/// The last `capacity` distinct whole-grid solves, and which inputs act after the solve.
#[derive(Debug)]
pub(crate) struct Memo {
    recent: Recent<SolveKey, Vec<Solved>>,
    params_after: [bool; N_PARAMS],
    effects_after: [bool; N_EFFECTS],
}

impl Memo {
    pub fn new(capacity: usize) -> Memo {
        Memo {
            recent: Recent::new(capacity),
            params_after: PARAMS.map(|p| AFTER_SOLVE_PARAMS.contains(&p.name)),
            effects_after: EFFECTS.map(|e| AFTER_SOLVE_EFFECTS.contains(&e.name)),
        }
    }

    /// What the solve of `theta` with `fx` depends on.
    pub fn key(&self, theta: &Theta, fx: &Effects) -> SolveKey {
        let (mut t, mut e) = (theta.0, fx.0);
        for (v, &after) in t.iter_mut().zip(&self.params_after) {
            if after {
                *v = 0.0;
            }
        }
        for (v, &after) in e.iter_mut().zip(&self.effects_after) {
            if after {
                *v = 0.0;
            }
        }
        SolveKey(t, e)
    }

    pub fn get(&mut self, key: &SolveKey) -> Option<&[Solved]> {
        self.recent.get(key).map(Vec::as_slice)
    }

    pub fn insert(&mut self, key: SolveKey, solved: Vec<Solved>) {
        self.recent.insert(key, solved);
    }

    pub fn hits(&self) -> usize {
        self.recent.hits
    }
}

/// The condensed drum's block at one frequency for its last few distinct coefficient
/// sets. The block depends on the drum's stiffness factor, the frequency and the cavity
/// only, so a Jacobian column of a parameter behind the drum (the ossicular chain's, the
/// damping when the drum's loss is its own, the cochlear load) reuses the base row's:
/// the modal sum is two fifths of a solve.
#[derive(Debug)]
pub(crate) struct DrumMemo(Recent<DrumCoefficients, ([c64; 16], usize)>);

impl DrumMemo {
    pub fn new(capacity: usize) -> DrumMemo {
        DrumMemo(Recent::new(capacity))
    }

    pub fn get(&mut self, c: &DrumCoefficients) -> Option<&[c64]> {
        self.0.get(c).map(|(b, n)| &b[..*n])
    }

    pub fn insert(&mut self, c: DrumCoefficients, block: &[c64]) {
        if block.len() > 16 {
            return;
        }
        let mut b = [c64::new(0.0, 0.0); 16];
        b[..block.len()].copy_from_slice(block);
        self.0.insert(c, (b, block.len()));
    }

    pub fn hits(&self) -> usize {
        self.0.hits
    }
}
