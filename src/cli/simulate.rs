//! `otofit simulate`: prior draws or given rows → a dataset folder.

use crate::dataset::{self, Rows};
use crate::sim::batch::{self, Design, Noise};
use crate::sim::params::{EFFECTS, Effects, N_TISSUE, PARAMS};
use crate::sim::{Model, ModelConfig, Preset};
use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use std::path::PathBuf;

/// Arguments of `otofit simulate`.
#[derive(Args, Debug)]
pub struct SimulateArgs {
    /// Number of prior draws (uniform or log-uniform box of each parameter).
    #[arg(long, conflicts_with = "theta", required_unless_present_any = ["theta", "explain"])]
    pub n: Option<usize>,
    /// Simulate these rows instead: CSV whose header names the 7 tissue parameters
    /// (natural units); the other parameters' columns (canal_length, canal_area,
    /// mic_distance, cavity, tm_viscoelastic, ldv_angle, cochlear_mass) are each optional
    /// and nominal when absent;
    /// extra columns named after effects set that effect per row.
    #[arg(long)]
    pub theta: Option<PathBuf>,
    /// Output folder (theta.csv, x.csv, meta.json).
    #[arg(long, required_unless_present = "explain")]
    pub out: Option<PathBuf>,
    /// Print the nominal ear's responses (or the first --theta row's) against published
    /// norms, with its power budget, instead of writing a dataset.
    #[arg(long, conflicts_with = "n")]
    pub explain: bool,
    /// Seed of the prior draws, the varied effects and the noise (same seed, same dataset).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Effects switched on for every row, e.g. `probe_leak=2e-4,probe_offset=1e-3`.
    #[arg(long, value_delimiter = ',')]
    pub effects: Vec<String>,
    /// Effects drawn from their ranges per row (they become columns of theta.csv).
    #[arg(long, value_delimiter = ',')]
    pub vary: Vec<String>,
    /// Gaussian noise added to x: the noise model × K (0 = none).
    #[arg(long, default_value_t = 0.0)]
    pub noise_scale: f64,
    /// Per-feature STD table (one row, header = feature names) replacing the default
    /// noise model, e.g. reference/std.csv.
    #[arg(long)]
    pub noise_table: Option<PathBuf>,
    /// Air in the canal: temporal-bone (22 °C, the default) or live (37 °C).
    #[arg(long, value_enum, default_value_t = PresetArg::TemporalBone)]
    pub preset: PresetArg,
    /// Replace an existing dataset in --out.
    #[arg(long)]
    pub force: bool,
    /// Table format: csv (theta.csv, x.csv; any tool reads them) or npy (theta.npy,
    /// x.npy, float64; numpy.load reads them; for large tables, written far faster).
    #[arg(long, value_enum, default_value_t = FormatArg::Csv)]
    pub format: FormatArg,
    /// With --explain only: the eardrum variant to report on.
    #[command(flatten)]
    pub drum: super::drum::DrumOpts,
}

/// Table format (--format).
#[derive(Clone, Copy, Debug, ValueEnum)]
#[allow(missing_docs)] // explained in the flag's help, as for PresetArg
pub enum FormatArg {
    Csv,
    Npy,
}

impl From<FormatArg> for dataset::Format {
    fn from(f: FormatArg) -> dataset::Format {
        match f {
            FormatArg::Csv => dataset::Format::Csv,
            FormatArg::Npy => dataset::Format::Npy,
        }
    }
}

/// Air in the canal (--preset).
#[derive(Clone, Copy, Debug, ValueEnum)]
// The values are explained in the flag's help: a doc comment on a value would become clap's
// help for it and switch --help to the long layout.
#[allow(missing_docs)]
pub enum PresetArg {
    TemporalBone,
    Live,
}

impl From<PresetArg> for Preset {
    fn from(p: PresetArg) -> Preset {
        match p {
            PresetArg::TemporalBone => Preset::TemporalBone,
            PresetArg::Live => Preset::Live,
        }
    }
}

/// Parses `name=value,...` into effects, naming the bad item.
pub fn parse_effects(items: &[String]) -> Result<Effects> {
    let mut fx = Effects::default();
    for item in items.iter().filter(|s| !s.is_empty()) {
        let (name, value) = item.split_once('=').with_context(|| format!("--effects: '{item}' is not name=value"))?;
        let value: f64 =
            value.trim().parse().with_context(|| format!("--effects: value of '{name}' is not a number"))?;
        fx.set(name.trim(), value).map_err(|e| anyhow::anyhow!("--effects: {e}"))?;
    }
    Ok(fx)
}

fn effect_index(name: &str, flag: &str) -> Result<usize> {
    Effects::index(name).with_context(|| {
        let known: Vec<_> = EFFECTS.iter().map(|e| e.name).collect();
        format!("{flag}: unknown effect '{name}' (known: {})", known.join(", "))
    })
}

/// Reads given rows and works out which effects vary per row.
fn read_rows(path: &std::path::Path, design: &mut Design) -> Result<Vec<Vec<f64>>> {
    let table = dataset::read_csv(path)?;
    let col = |name: &str| table.header.iter().position(|h| h == name);
    let mut cols = Vec::new();
    for p in &PARAMS[..N_TISSUE] {
        cols.push(col(p.name).with_context(|| format!("{}: missing column '{}'", path.display(), p.name))?);
    }
    // The other parameters (geometry, cavity, drum viscoelasticity, LDV angle, cochlear
    // mass): each optional,
    // nominal when its column is absent.
    let rest: Vec<Option<usize>> = PARAMS[N_TISSUE..].iter().map(|p| col(p.name)).collect();
    for h in &table.header {
        if PARAMS.iter().any(|p| p.name == h) {
            continue;
        }
        let i = effect_index(h, &format!("{}: column", path.display()))?;
        if !design.varied.contains(&i) {
            design.varied.push(i);
        }
    }
    for &i in &design.varied {
        cols.push(
            col(EFFECTS[i].name)
                .with_context(|| format!("{}: missing column '{}' (--vary)", path.display(), EFFECTS[i].name))?,
        );
    }
    Ok(table
        .rows
        .iter()
        .map(|r| {
            let mut row: Vec<f64> = cols[..N_TISSUE].iter().map(|&c| r[c]).collect();
            row.extend(PARAMS[N_TISSUE..].iter().zip(&rest).map(|(p, c)| c.map_or(p.nominal, |c| r[c])));
            row.extend(cols[N_TISSUE..].iter().map(|&c| r[c]));
            row
        })
        .collect())
}

/// Runs `otofit simulate`.
pub fn run(args: SimulateArgs) -> Result<()> {
    if !(args.noise_scale.is_finite() && args.noise_scale >= 0.0) {
        bail!("--noise-scale must be a finite number ≥ 0, got {}", args.noise_scale);
    }
    let mut design = Design { fixed: parse_effects(&args.effects)?, varied: Vec::new() };
    for name in args.vary.iter().filter(|s| !s.is_empty()) {
        design.varied.push(effect_index(name.trim(), "--vary")?);
    }
    let given = match &args.theta {
        Some(p) => Some(read_rows(p, &mut design)?),
        None => None,
    };
    // Datasets are always the default model's simulator (cli::drum says why).
    if !args.explain && args.drum.is_set() {
        bail!("--drum, --drum-loss, --incus-lateral and --joint-pads only apply with --explain");
    }
    let mut config = ModelConfig { preset: args.preset.into(), ..ModelConfig::default() };
    args.drum.apply(&mut config)?;
    if args.explain {
        let (theta, fx) = match &given {
            Some(rows) => design.split(rows.first().context("--theta: no rows")?),
            None => (args.drum.nominal(), design.fixed),
        };
        return super::explain::report(config, &theta, &fx);
    }
    let out = args.out.context("--out is required")?;
    if out.join("meta.json").exists() && !args.force {
        bail!("{} already holds a dataset; pass --force to replace it", out.display());
    }
    let preset = config.preset;
    let model = Model::new(config)?;
    let std = match &args.noise_table {
        Some(p) => dataset::read_noise_table(p, &crate::sim::output::feature_names(model.frequencies()))
            .context("--noise-table")?,
        None => batch::default_noise_std(&model),
    };
    let noise = Noise { std, scale: args.noise_scale, seed: args.seed };
    let rows = match given {
        Some(g) => Rows::Given(g),
        None => Rows::Prior { n: args.n.unwrap_or(0), seed: args.seed },
    };
    let mut bar = super::progress::Progress::new("simulated", "rows", rows.len() as u64);
    let run = dataset::DatasetRun {
        model: &model,
        design: &design,
        rows: &rows,
        noise: &noise,
        preset,
        format: args.format.into(),
    };
    let meta = dataset::simulate_to_dir(&run, &out, &mut |done, _| {
        bar.set(done as u64);
        true
    })?;
    bar.finish();
    for f in &meta.failed {
        eprintln!("row {} failed: {}", f.row, f.reason);
    }
    eprintln!(
        "wrote {} rows ({} failed) to {} in {:.2} s",
        meta.n_rows,
        meta.failed.len(),
        out.display(),
        meta.wall_seconds
    );
    Ok(())
}
