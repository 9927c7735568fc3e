//! `otofit bench exact`: POST /infer's exact posterior (short chains) on held-out
//! simulated ears, against the truth (coverage) and the long chain (C2ST).

use anyhow::{Context, Result};
use clap::Args;
use std::path::PathBuf;
use std::time::Instant;

/// `otofit bench exact`'s arguments.
#[derive(Args, Debug)]
pub struct ExactArgs {
    /// Held-out ears (1..=10000): the first half prior draws, the rest near degeneracies.
    #[arg(long, default_value_t = 40)]
    pub ears: usize,
    /// Of those, the first this many also get the long chain (about 10 s each) and a C2ST.
    #[arg(long, default_value_t = 10)]
    pub reference: usize,
    /// Steps of the long chain (4000..=200000; 100000 is the length measured calibrated).
    #[arg(long, default_value_t = crate::bench::posterior::DEFAULT_STEPS)]
    pub steps: usize,
    /// Seed of the ears, their noise, the flow's draws and the chains.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Feature groups given, comma-separated (e.g. stapes_velocity,impedance,absorbance:
    /// no umbo velocity, answered by the flow for any subset); all if empty.
    #[arg(long, default_value = "")]
    pub measures: String,
    /// Folder for exact.json (every ear and the pooled scores); none if absent.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// The model whose flow starts the chains (its simulator and noise make the ears).
    #[arg(long, default_value = "models/default.otofit")]
    pub model: PathBuf,
}

/// Runs it: progress per ear on stderr, the table on stdout.
pub fn run(a: ExactArgs) -> Result<()> {
    use crate::bench::exact_fast::{self, FastParams};
    let measures = super::bench::groups(&a.measures);
    let p = FastParams { ears: a.ears, reference: a.reference, steps: a.steps, seed: a.seed, measures };
    p.check()?;
    if let Some(out) = &a.out {
        std::fs::create_dir_all(out).with_context(|| format!("--out {}: cannot create it", out.display()))?;
    }
    let npe = crate::npe::Npe::load(&a.model).with_context(|| format!("--model {}", a.model.display()))?;
    let t = Instant::now();
    let report = exact_fast::run(&npe, &p, &mut |outcome| match outcome {
        Ok(e) => eprintln!(
            "ear {} ({}): {:.2} s, exact {} by {}{}{}{}{}{} ({:.0} s)",
            e.ear,
            e.kind,
            e.seconds,
            e.exact,
            e.method,
            match (e.importance_ess, e.pareto_k) {
                (Some(ess), Some(k)) => format!(", importance ESS {ess:.0}, Pareto k {k:.2}"),
                _ => String::new(),
            },
            match (e.rhat, e.ess_bulk, e.ess_tail) {
                (Some(r), Some(b), Some(t)) => format!(", R-hat {r:.3}, ESS {b:.0}/{t:.0}"),
                _ => String::new(),
            },
            e.c2st.map_or(String::new(), |c| format!(", C2ST {c:.3}")),
            e.c2st_flow.map_or(String::new(), |c| format!(" (flow {c:.3})")),
            e.long_rhat.map_or(String::new(), |r| format!(", long chain's R-hat {r:.3}")),
            t.elapsed().as_secs_f64()
        ),
        Err((i, why)) => eprintln!("ear {i}: skipped: {why}"),
    })?;
    let seconds = t.elapsed().as_secs_f64();
    print!("{}", exact_fast::table(&report));
    println!("wall time {seconds:.0} s");
    if let Some(out) = &a.out {
        let mut doc = serde_json::to_value(&report)?;
        doc["model"] = a.model.display().to_string().into();
        doc["seconds"] = seconds.into();
        std::fs::write(out.join("exact.json"), serde_json::to_vec_pretty(&doc)?)?;
    }
    Ok(())
}
