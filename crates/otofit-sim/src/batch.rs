//! Many parameter sets at once: prior draws, the row layout of a dataset (the seven
//! parameters plus any effects that vary per row), and chunked parallel runs on rayon
//! with one [`Runner`] per thread. Results come back in input order, so callers can
//! stream them to disk chunk by chunk and keep memory flat.

use super::model::{Model, Runner, SimError};
use super::output;
use super::params::{EFFECTS, Effects, N_PARAMS, PARAMS, ParamSpec, Theta};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

/// What a dataset's rows hold: the seven parameters, then one column per varied effect;
/// `fixed` sets the effects that are the same for every row.
#[derive(Clone, Debug, Default)]
pub struct Design {
    /// Effects held at one value for every row (the rest are off unless varied).
    pub fixed: Effects,
    /// Indices into [`EFFECTS`] of the effects drawn per row (their ranges join the prior).
    pub varied: Vec<usize>,
}

impl Design {
    /// Column specs in row order.
    pub fn columns(&self) -> Vec<ParamSpec> {
        PARAMS.iter().copied().chain(self.varied.iter().map(|&i| EFFECTS[i].as_param())).collect()
    }

    /// Columns per row: the parameters, then the varied effects.
    pub fn width(&self) -> usize {
        N_PARAMS + self.varied.len()
    }

    /// Splits one row into parameters and effects.
    pub fn split(&self, row: &[f64]) -> (Theta, Effects) {
        let theta = Theta(std::array::from_fn(|i| row[i]));
        let mut fx = self.fixed;
        for (k, &i) in self.varied.iter().enumerate() {
            fx.0[i] = row[N_PARAMS + k];
        }
        (theta, fx)
    }

    /// `n` prior draws, deterministic for `seed` (row i is the same whatever `n` is).
    pub fn draw(&self, seed: u64, first: usize, n: usize) -> Vec<Vec<f64>> {
        let cols = self.columns();
        (first..first + n)
            .map(|row| {
                let mut rng = row_rng(seed, row, 0);
                cols.iter().map(|c| c.from_unit(rng.random())).collect()
            })
            .collect()
    }
}

/// Gaussian measurement noise added to simulated features: `std` per feature × `scale`.
#[derive(Clone, Debug)]
pub struct Noise {
    /// The 1× noise model: test–retest standard deviation per feature.
    pub std: Vec<f64>,
    /// Multiplies `std` (0: noise-free features).
    pub scale: f64,
    /// Seeds every row's own noise stream, so a row's noise does not depend on the thread
    /// or chunk that simulated it.
    pub seed: u64,
}

impl Noise {
    /// `x` plus this noise, with row `row`'s stream (the same draw `run_rows` adds).
    pub fn apply(&self, x: &[f64], row: usize) -> Vec<f64> {
        let mut rng = row_rng(self.seed, row, 1);
        x.iter()
            .zip(&self.std)
            .map(|(v, s)| {
                let z: f64 = StandardNormal.sample(&mut rng);
                v + self.scale * s * z
            })
            .collect()
    }
}

/// Independent random stream per (seed, row, purpose): reproducible in any thread order.
fn row_rng(seed: u64, row: usize, purpose: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream((row as u64) << 2 | purpose);
    rng
}

/// Simulates `rows` (numbered from `first`, for the noise streams) in parallel.
pub fn run_rows(
    model: &Model,
    design: &Design,
    rows: &[Vec<f64>],
    first: usize,
    noise: Option<&Noise>,
) -> Vec<Result<Vec<f64>, SimError>> {
    rows.par_iter()
        .enumerate()
        .map_init(
            || model.runner(),
            |runner: &mut Runner<'_>, (k, row)| {
                if row.len() < design.width() {
                    return Err(SimError::RowWidth { expected: design.width(), got: row.len() });
                }
                let (theta, fx) = design.split(row);
                let x = super::simulate(runner, &theta, &fx)?;
                Ok(match noise.filter(|n| n.scale > 0.0) {
                    Some(n) => n.apply(&x, first + k),
                    None => x,
                })
            },
        )
        .collect()
}

/// The default noise model for a model's grid.
pub fn default_noise_std(model: &Model) -> Vec<f64> {
    output::noise_std(model.frequencies())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ModelConfig;

    #[test]
    fn draws_are_reproducible_and_inside_the_prior() {
        let d = Design { fixed: Effects::default(), varied: vec![0] };
        let a = d.draw(5, 0, 20);
        let b = d.draw(5, 10, 10);
        assert_eq!(&a[10..], &b[..], "row i must not depend on where the chunk starts");
        for row in &a {
            for (v, c) in row.iter().zip(d.columns()) {
                assert!(c.contains(*v), "{} = {v}", c.name);
            }
        }
        assert_ne!(d.draw(6, 0, 1), a[..1]);
    }

    #[test]
    fn a_row_shorter_than_the_parameters_is_an_error_not_a_panic() {
        // A model trained on an older simulator's parameter list (v4: 12) asks for
        // rows of that width.
        let model = Model::new(ModelConfig::default()).unwrap();
        let d = Design::default();
        let mut rows = d.draw(1, 0, 2);
        rows[1].truncate(12);
        let out = run_rows(&model, &d, &rows, 0, None);
        assert!(out[0].is_ok());
        let err = out[1].as_ref().unwrap_err();
        assert!(matches!(err, SimError::RowWidth { got: 12, .. }), "{err:?}");
        assert!(err.to_string().contains("12 columns"), "{err}");
    }

    #[test]
    fn parallel_runs_match_serial_runs_and_noise_is_seeded() {
        let model = Model::new(ModelConfig::default()).unwrap();
        let d = Design::default();
        let rows = d.draw(1, 0, 6);
        let par = run_rows(&model, &d, &rows, 0, None);
        let mut r = model.runner();
        for (row, x) in rows.iter().zip(&par) {
            let (t, fx) = d.split(row);
            assert_eq!(x.as_ref().unwrap(), &crate::simulate(&mut r, &t, &fx).unwrap());
        }
        let noise = Noise { std: default_noise_std(&model), scale: 1.0, seed: 3 };
        let n1 = run_rows(&model, &d, &rows, 0, Some(&noise));
        let n2 = run_rows(&model, &d, &rows[2..], 2, Some(&noise));
        assert_eq!(n1[2].as_ref().unwrap(), n2[0].as_ref().unwrap());
        let dev: f64 =
            n1[0].as_ref().unwrap().iter().zip(par[0].as_ref().unwrap()).map(|(a, b)| a - b).map(|d| d * d).sum();
        assert!(dev > 0.0);
    }
}
