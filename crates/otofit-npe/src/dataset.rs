//! Dataset folders on disk: theta.csv, x.csv (header rows, aligned) and meta.json.
//! Files are written under temporary names and renamed at the end, so a crash never
//! leaves a folder that looks complete.

use crate::sim::batch::{Design, Noise};
use crate::sim::output::{GROUPS, MEASURES, feature_names};
use crate::sim::params::{EFFECTS, EffectSpec, ParamSpec};
use serde::Serialize;
use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter, Write};
use std::path::{Path, PathBuf};

/// Results of this module.
pub type Result<T, E = DatasetError> = std::result::Result<T, E>;

/// Errors of reading tables and writing dataset folders: a table at fault (bad input,
/// [`DatasetError::is_input`]), a cancelled run, or the file system.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DatasetError {
    /// A table's content is not usable; the message names the file, line and column.
    #[error("{}: {why}", path.display())]
    Table {
        /// The file.
        path: PathBuf,
        /// Where and what.
        why: String,
    },
    /// A run stopped by its progress callback.
    #[error(transparent)]
    Cancelled(#[from] Cancelled),
    /// Reading or writing failed.
    #[error(transparent)]
    Io(#[from] FileError),
    /// meta.json could not be encoded (internal).
    #[error("cannot encode meta.json")]
    Encode(#[source] serde_json::Error),
}

impl DatasetError {
    /// Whether the table given is at fault (as opposed to the file system or a bug).
    pub fn is_input(&self) -> bool {
        matches!(self, DatasetError::Table { .. })
    }

    fn table(path: &Path, why: String) -> DatasetError {
        DatasetError::Table { path: path.to_path_buf(), why }
    }
}

/// A file operation that failed, naming the operation and the file (shared by the
/// layers that read and write files).
#[derive(Debug, thiserror::Error)]
#[error("cannot {action} {}", path.display())]
pub struct FileError {
    /// `open`, `read`, `write`, `create` or `rename`.
    pub action: &'static str,
    /// The file or folder.
    pub path: PathBuf,
    /// The operating system's error.
    #[source]
    pub source: std::io::Error,
}

impl FileError {
    /// For `map_err`: an I/O error of `action` on `path`.
    pub fn on(action: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> FileError + use<> {
        let path = path.to_path_buf();
        move |source| FileError { action, path, source }
    }
}

/// An I/O error on `path` as this module's error, for `map_err`.
fn io(action: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> DatasetError + use<> {
    let on = FileError::on(action, path);
    move |source| DatasetError::Io(on(source))
}

/// A dataset's meta.json: how it was made, so a training run or a reader can check what x.csv and theta.csv hold.
#[derive(Serialize)]
pub struct Meta {
    /// The otofit version that wrote it.
    pub otofit_version: &'static str,
    /// The seed of the prior draws; `None` for rows given by the caller.
    pub seed: Option<u64>,
    /// Rows written (failed rows excluded).
    pub n_rows: usize,
    /// How the tables are stored (theta.csv/x.csv or theta.npy/x.npy).
    pub format: Format,
    /// The model preset the rows were simulated with.
    pub preset: crate::sim::Preset,
    /// The columns of theta.csv: each parameter's name, unit, range and scale.
    pub parameters: Vec<ParamSpec>,
    /// The frequencies every measure is simulated at.
    pub frequencies_hz: Vec<f64>,
    /// The columns of x.csv, in order.
    pub features: Vec<Feature>,
    /// Which features belong to which measure group (for embeddings and diagnostics).
    pub groups: Vec<Group>,
    /// The noise model that was added to x.csv.
    pub noise: NoiseMeta,
    /// The modelling effects and how each was set.
    pub effects: Vec<EffectMeta>,
    /// Rows whose simulation failed, and why.
    pub failed: Vec<Failed>,
    /// Time taken to simulate the dataset.
    pub wall_seconds: f64,
}

/// One column of x.csv: a measure at one frequency.
#[derive(Serialize)]
pub struct Feature {
    /// The column header.
    pub name: String,
    /// The measure the column belongs to.
    pub measure: &'static str,
    /// The frequency of this column.
    pub frequency_hz: f64,
    /// The column's unit.
    pub unit: &'static str,
}

/// A measure group: the measures whose features are read together.
#[derive(Serialize)]
pub struct Group {
    /// The group's name.
    pub name: &'static str,
    /// The measures in the group.
    pub measures: Vec<&'static str>,
}

/// `std` is the 1× noise model (for training); `scale` is what was added to x.csv.
#[derive(Serialize)]
pub struct NoiseMeta {
    /// Noise standard deviation of each feature at 1×.
    pub std: Vec<f64>,
    /// The multiple of `std` actually added to x.csv.
    pub scale: f64,
}

/// A modelling effect as set for this dataset.
#[derive(Serialize)]
pub struct EffectMeta {
    /// The effect's name and range.
    #[serde(flatten)]
    pub spec: EffectSpec,
    /// "fixed", "varied" (a column of theta.csv) or "off".
    pub mode: &'static str,
    /// Its fixed value when `mode` is "fixed" ("inf" in JSON when infinite).
    #[serde(serialize_with = "finite_or_str")]
    pub value: f64,
}

fn finite_or_str<S: serde::Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
    if v.is_finite() { s.serialize_f64(*v) } else { s.serialize_str("inf") }
}

/// A row whose simulation failed (the dataset goes on without it).
#[derive(Serialize, serde::Deserialize, Clone, Debug)]
pub struct Failed {
    /// The row's index in the design.
    pub row: usize,
    /// Why it failed.
    pub reason: String,
}

impl Meta {
    /// The meta of a dataset drawn from `design` with `preset` at `freqs`, before any row is written.
    pub fn new(design: &Design, preset: crate::sim::Preset, freqs: &[f64], noise: &Noise, seed: Option<u64>) -> Meta {
        let features = feature_names(freqs)
            .into_iter()
            .enumerate()
            .map(|(i, name)| {
                let m = &MEASURES[i / freqs.len()];
                Feature { name, measure: m.name, frequency_hz: freqs[i % freqs.len()], unit: m.unit }
            })
            .collect();
        let effects = EFFECTS
            .iter()
            .enumerate()
            .map(|(i, e)| {
                let (mode, value) = if design.varied.contains(&i) {
                    ("varied", f64::NAN)
                } else if design.fixed.0[i] != e.off {
                    ("fixed", design.fixed.0[i])
                } else {
                    ("off", e.off)
                };
                EffectMeta { spec: *e, mode, value: if value.is_nan() { e.off } else { value } }
            })
            .collect();
        Meta {
            otofit_version: env!("CARGO_PKG_VERSION"),
            seed,
            n_rows: 0,
            format: Format::Csv,
            preset,
            parameters: design.columns(),
            frequencies_hz: freqs.to_vec(),
            features,
            groups: GROUPS.iter().map(|(name, ms)| Group { name, measures: ms.to_vec() }).collect(),
            noise: NoiseMeta { std: noise.std.clone(), scale: noise.scale },
            effects,
            failed: Vec::new(),
            wall_seconds: 0.0,
        }
    }
}

/// How a dataset's two tables are stored.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    /// theta.csv and x.csv with header rows: any tool reads them; the service serves them.
    #[default]
    Csv,
    /// theta.npy and x.npy, float64 (rows, columns), their columns named in meta.json:
    /// for large tables, written and read at memory speed (`numpy.load`).
    Npy,
}

impl Format {
    /// The names of the θ table, the x table and meta.json.
    pub fn files(self) -> [&'static str; 3] {
        match self {
            Format::Csv => FILES,
            Format::Npy => ["theta.npy", "x.npy", "meta.json"],
        }
    }
}

/// Streams rows into `dir` under temporary names; [`Self::finish`] renames them.
pub struct Writer {
    dir: PathBuf,
    format: Format,
    theta: BufWriter<File>,
    x: BufWriter<File>,
    /// Columns of the θ and x tables.
    cols: (usize, usize),
    /// Rows written so far.
    pub rows: usize,
}

/// The files of a CSV dataset folder (the service's datasets).
pub const FILES: [&str; 3] = ["theta.csv", "x.csv", "meta.json"];

fn tmp(dir: &Path, name: &str) -> PathBuf {
    dir.join(format!("{name}.tmp"))
}

impl Writer {
    /// Opens the temporary table files in `dir` (created if needed) and writes their
    /// headers (the column names for CSV, a placeholder for .npy).
    pub fn create(dir: &Path, meta: &Meta, format: Format) -> Result<Writer> {
        std::fs::create_dir_all(dir).map_err(io("create", dir))?;
        let names = format.files();
        let open = |name: &str| -> Result<BufWriter<File>> {
            let p = tmp(dir, name);
            Ok(BufWriter::with_capacity(1 << 20, File::create(&p).map_err(io("write", &p))?))
        };
        let mut theta = open(names[0])?;
        let mut x = open(names[1])?;
        let cols = (meta.parameters.len(), meta.features.len());
        let (head_t, head_x) = match format {
            Format::Csv => (
                format!("{}\n", meta.parameters.iter().map(|p| p.name).collect::<Vec<_>>().join(",")).into_bytes(),
                format!("{}\n", meta.features.iter().map(|f| f.name.as_str()).collect::<Vec<_>>().join(","))
                    .into_bytes(),
            ),
            Format::Npy => (crate::npy::header(0, cols.0), crate::npy::header(0, cols.1)),
        };
        theta.write_all(&head_t).map_err(io("write", &tmp(dir, names[0])))?;
        x.write_all(&head_x).map_err(io("write", &tmp(dir, names[1])))?;
        Ok(Writer { dir: dir.to_path_buf(), format, theta, x, cols, rows: 0 })
    }

    /// Appends a block of rows: `theta` and `x` hold whole rows, one after the other.
    pub fn push_block(&mut self, block: &Block) -> Result<()> {
        let names = self.format.files();
        let (pt, px) = (tmp(&self.dir, names[0]), tmp(&self.dir, names[1]));
        match self.format {
            Format::Csv => {
                write_csv_rows(&mut self.theta, &block.theta, block.rows).map_err(io("write", &pt))?;
                write_csv_rows(&mut self.x, &block.x, block.rows).map_err(io("write", &px))?;
            }
            Format::Npy => {
                crate::npy::write_values(&mut self.theta, &block.theta).map_err(io("write", &pt))?;
                crate::npy::write_values(&mut self.x, &block.x).map_err(io("write", &px))?;
            }
        }
        self.rows += block.rows;
        Ok(())
    }

    /// Removes the temporary files (a cancelled run leaves nothing behind).
    pub fn abandon(self) {
        for name in self.format.files() {
            let _ = std::fs::remove_file(tmp(&self.dir, name));
        }
    }

    /// Flushes, writes meta.json and renames all three files into place.
    pub fn finish(mut self, meta: &mut Meta) -> Result<()> {
        meta.n_rows = self.rows;
        meta.format = self.format;
        let names = self.format.files();
        for (w, name, cols) in [(&mut self.theta, names[0], self.cols.0), (&mut self.x, names[1], self.cols.1)] {
            let done = match self.format {
                Format::Csv => w.flush(),
                Format::Npy => w.flush().and_then(|_| crate::npy::finish(w.get_mut(), self.rows as u64, cols)),
            };
            done.map_err(io("write", &tmp(&self.dir, name)))?;
        }
        drop(self.theta);
        drop(self.x);
        let p = tmp(&self.dir, names[2]);
        std::fs::write(&p, serde_json::to_vec_pretty(meta).map_err(DatasetError::Encode)?).map_err(io("write", &p))?;
        for name in names {
            std::fs::rename(tmp(&self.dir, name), self.dir.join(name)).map_err(io("rename", &self.dir.join(name)))?;
        }
        Ok(())
    }
}

/// Finished rows of one sub-batch, θ and x each flattened row after row.
#[derive(Default)]
pub struct Block {
    /// θ rows, one after the other.
    pub theta: Vec<f64>,
    /// x rows, one after the other.
    pub x: Vec<f64>,
    /// How many rows.
    pub rows: usize,
}

/// Writes `rows` rows (`values` holds them one after the other) to `w` as CSV lines.
/// Formatting the shortest round-tripping decimal of each number is most of the cost of
/// writing a CSV table, so blocks of rows are formatted on rayon's threads and written
/// in order, each as it is (joining them first was a serial copy on the writing
/// thread): the bytes are the same whatever the thread count.
fn write_csv_rows(w: &mut impl Write, values: &[f64], rows: usize) -> std::io::Result<()> {
    use rayon::prelude::*;
    const ROWS_PER_TASK: usize = 64;
    if rows == 0 {
        return Ok(());
    }
    let cols = values.len() / rows;
    let parts: Vec<Vec<u8>> = values
        .par_chunks(cols.max(1) * ROWS_PER_TASK)
        .map(|chunk| {
            let mut out = Vec::with_capacity(chunk.len() * 24);
            for row in chunk.chunks(cols.max(1)) {
                write_row(&mut out, row).expect("writing to memory");
            }
            out
        })
        .collect();
    parts.iter().try_for_each(|p| w.write_all(p))
}

fn write_row(w: &mut impl Write, v: &[f64]) -> std::io::Result<()> {
    let mut first = true;
    for x in v {
        if !first {
            w.write_all(b",")?;
        }
        first = false;
        // Shortest representation that round-trips exactly.
        write!(w, "{x:e}")?;
    }
    w.write_all(b"\n")
}

/// Where a dataset's rows come from.
pub enum Rows {
    /// `n` rows drawn from the design's prior with `seed`.
    Prior {
        /// How many rows.
        n: usize,
        /// The seed of the draws.
        seed: u64,
    },
    /// These rows of θ (in the design's parameter order).
    Given(Vec<Vec<f64>>),
}

/// Why a dataset run stopped early.
#[derive(Debug, thiserror::Error)]
#[error("cancelled after {done} of {total} rows")]
pub struct Cancelled {
    /// Rows finished before the cancel.
    pub done: usize,
    /// Rows the run was to write.
    pub total: usize,
}

/// What a dataset run simulates and how it is stored.
pub struct DatasetRun<'a> {
    /// The simulator.
    pub model: &'a crate::sim::Model,
    /// The parameters and their prior.
    pub design: &'a Design,
    /// Where the rows come from.
    pub rows: &'a Rows,
    /// The noise added to x.
    pub noise: &'a Noise,
    /// The model preset (recorded in meta.json).
    pub preset: crate::sim::Preset,
    /// The tables' format.
    pub format: Format,
}

/// Simulates `run.rows` into `dir` (chunks of 1024 on rayon, each written while the next
/// is simulated; rows streamed to disk).
/// `progress(done, total)` is called after each chunk; returning `false` cancels, and
/// the temporary files are removed.
pub fn simulate_to_dir(
    run: &DatasetRun<'_>,
    dir: &Path,
    progress: &mut dyn FnMut(usize, usize) -> bool,
) -> Result<Meta> {
    let start = std::time::Instant::now();
    let DatasetRun { model, design, rows, noise, preset, format } = *run;
    let n = rows.len();
    let mut meta = Meta::new(design, preset, model.frequencies(), noise, rows.seed());
    let mut writer = Writer::create(dir, &meta, format)?;
    let batch = Batch { model, design, rows, noise };
    let mut done = 0;
    let finished = batch.run(0, n, &mut meta.failed, &mut |b| writer.push_block(b), &mut |d| {
        done = d;
        progress(d, n)
    });
    match finished {
        Ok(true) => {}
        Ok(false) => {
            writer.abandon();
            return Err(DatasetError::Cancelled(Cancelled { done, total: n }));
        }
        Err(e) => {
            writer.abandon();
            return Err(e);
        }
    }
    meta.wall_seconds = start.elapsed().as_secs_f64();
    writer.finish(&mut meta)?;
    Ok(meta)
}

impl Rows {
    /// How many rows.
    pub fn len(&self) -> usize {
        match self {
            Rows::Prior { n, .. } => *n,
            Rows::Given(g) => g.len(),
        }
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The seed of prior draws (`None` for given rows).
    pub fn seed(&self) -> Option<u64> {
        match self {
            Rows::Prior { seed, .. } => Some(*seed),
            Rows::Given(_) => None,
        }
    }
}

/// Where each sub-batch's finished rows go. `Send`, because it runs on a pool thread
/// beside the next sub-batch's simulation ([`Batch::run`]).
type RowSink<'a> = dyn FnMut(&Block) -> Result<()> + Send + 'a;

/// Rows through the simulator: what one dataset run needs.
struct Batch<'a> {
    model: &'a crate::sim::Model,
    design: &'a Design,
    rows: &'a Rows,
    noise: &'a Noise,
}

/// One simulated sub-batch: its first row, its rows and each row's outcome.
struct Simulated {
    from: usize,
    rows: Vec<Vec<f64>>,
    results: Vec<std::result::Result<Vec<f64>, crate::sim::SimError>>,
}

impl Batch<'_> {
    /// Sub-batches of this many rows: a progress step, and what is simulated in
    /// parallel while the sub-batch before is written.
    const SUB: usize = 1024;

    /// Simulates rows `first .. first + len` in sub-batches of [`Self::SUB`] on rayon:
    /// finite outputs go to `push`, failed rows to `failed` (by their row number in the
    /// whole dataset). Every row's draw and noise come from its own stream (seed, row),
    /// so the rows are the same whatever the split. `progress(rows done of these)`
    /// after each sub-batch is pushed; `false` stops: `Ok(false)` unless it was the last.
    ///
    /// Sub-batch k + 1 is simulated while sub-batch k is sorted and pushed (formatted
    /// and written): on many threads the writing, done between sub-batches, left every
    /// thread but one idle while it ran. The pushes keep their order.
    fn run(
        &self,
        first: usize,
        len: usize,
        failed: &mut Vec<Failed>,
        push: &mut RowSink<'_>,
        progress: &mut dyn FnMut(usize) -> bool,
    ) -> Result<bool> {
        let end = first + len;
        let sub_batch = |from: usize| (from < end).then(|| self.simulate(from, Self::SUB.min(end - from)));
        let mut next = sub_batch(first);
        while let Some(done) = next {
            let from = done.from + done.rows.len();
            let (simulated, pushed) = rayon::join(|| sub_batch(from), || self.sort(done, failed, push));
            pushed?;
            if !progress(from - first) && from < end {
                return Ok(false);
            }
            next = simulated;
        }
        Ok(true)
    }

    /// Draws (or takes) rows `from .. from + k` and simulates them on rayon.
    fn simulate(&self, from: usize, k: usize) -> Simulated {
        let rows = match self.rows {
            Rows::Given(g) => g[from..from + k].to_vec(),
            Rows::Prior { seed, .. } => self.design.draw(*seed, from, k),
        };
        let results = crate::sim::batch::run_rows(self.model, self.design, &rows, from, Some(self.noise));
        Simulated { from, rows, results }
    }

    /// Sorts a simulated sub-batch into finished rows, pushed as one block, and failed ones.
    fn sort(&self, s: Simulated, failed: &mut Vec<Failed>, push: &mut RowSink<'_>) -> Result<()> {
        let mut block = Block::default();
        for (i, (row, res)) in s.rows.iter().zip(s.results).enumerate() {
            let (_, fx) = self.design.split(row);
            let bad_effect = EFFECTS.iter().zip(fx.0).find(|(e, v)| !e.accepts(*v));
            let fail = |reason: String| Failed { row: s.from + i, reason };
            match (res, bad_effect) {
                (_, Some((e, v))) => failed.push(fail(format!("{} = {v} outside [{}, {}]", e.name, e.low, e.high))),
                (Ok(x), None) if x.iter().all(|v| v.is_finite()) => {
                    block.theta.extend_from_slice(row);
                    block.x.extend_from_slice(&x);
                    block.rows += 1;
                }
                (Ok(_), None) => failed.push(fail("non-finite output".into())),
                (Err(e), None) => failed.push(fail(e.to_string())),
            }
        }
        push(&block)
    }
}

/// The folder of a dataset's parts, `DIR/parts`: one part per chunk of rows, written
/// by whichever worker ran the chunk.
pub const PARTS: &str = "parts";

/// A finished part: rows `first .. first + len` of a dataset, in `part-NNNNN.theta.csv`
/// and `part-NNNNN.x.csv` (rows without a header) and `part-NNNNN.json` (this, written
/// last: a part is finished when its JSON is in place).
#[derive(Serialize, serde::Deserialize, Clone, Debug)]
pub struct Part {
    /// The part's first row in the dataset.
    pub first: usize,
    /// Rows the part covers (written and failed).
    pub len: usize,
    /// Rows written (`len` less the failed ones).
    pub rows: usize,
    /// The part's failed rows.
    pub failed: Vec<Failed>,
    /// Time taken to simulate the part.
    pub wall_seconds: f64,
}

/// The file `file` (`theta.csv`, `x.csv`, `json`) of part `idx` in `parts`.
pub fn part_file(parts: &Path, idx: usize, file: &str) -> PathBuf {
    parts.join(format!("part-{idx:05}.{file}"))
}

/// Part `idx` of `parts` if it is finished (its JSON reads and its tables exist).
pub fn read_part(parts: &Path, idx: usize) -> Option<Part> {
    let part: Part = serde_json::from_slice(&std::fs::read(part_file(parts, idx, "json")).ok()?).ok()?;
    let tables = [FILES[0], FILES[1]].iter().all(|f| part_file(parts, idx, f).is_file());
    tables.then_some(part)
}

/// The parts of a dataset run: the rows to simulate and how.
pub struct PartRun<'a> {
    /// The simulator.
    pub model: &'a crate::sim::Model,
    /// The parameters and their prior.
    pub design: &'a Design,
    /// Where the rows come from.
    pub rows: &'a Rows,
    /// The noise added to x.
    pub noise: &'a Noise,
    /// The parts folder (`DIR/parts`); it must exist (a job that ended removed it, and a
    /// late worker must not bring it back).
    pub parts: &'a Path,
}

impl PartRun<'_> {
    /// Simulates rows `first .. first + len` as part `idx`, under temporary names that
    /// carry `tag` (the claim's, so two workers on one chunk never share a file), then
    /// renamed into place, the JSON last. The part is the same bytes whoever runs it.
    /// `progress(rows done)` after each sub-batch; `false` stops (`Cancelled`), and
    /// the temporary files are removed, as after any error.
    pub fn simulate(
        &self,
        idx: usize,
        first: usize,
        len: usize,
        tag: &str,
        progress: &mut dyn FnMut(usize) -> bool,
    ) -> Result<Part> {
        let start = std::time::Instant::now();
        let tmp = |file: &str| self.parts.join(format!("part-{idx:05}.{file}.{tag}.tmp"));
        let names = [FILES[0], FILES[1], "json"];
        let out = (|| {
            let open = |f: &str| File::create(tmp(f)).map(BufWriter::new).map_err(io("write", &tmp(f)));
            let (mut theta, mut x) = (open(FILES[0])?, open(FILES[1])?);
            let mut part = Part { first, len, rows: 0, failed: vec![], wall_seconds: 0.0 };
            let batch = Batch { model: self.model, design: self.design, rows: self.rows, noise: self.noise };
            let mut push = |b: &Block| {
                write_csv_rows(&mut theta, &b.theta, b.rows).map_err(io("write", &tmp(FILES[0])))?;
                write_csv_rows(&mut x, &b.x, b.rows).map_err(io("write", &tmp(FILES[1])))?;
                part.rows += b.rows;
                Ok(())
            };
            if !batch.run(first, len, &mut part.failed, &mut push, progress)? {
                return Err(DatasetError::Cancelled(Cancelled { done: 0, total: len }));
            }
            theta.flush().map_err(io("write", &tmp(FILES[0])))?;
            x.flush().map_err(io("write", &tmp(FILES[1])))?;
            part.wall_seconds = start.elapsed().as_secs_f64();
            let json = serde_json::to_vec(&part).map_err(DatasetError::Encode)?;
            std::fs::write(tmp("json"), json).map_err(io("write", &tmp("json")))?;
            for f in names {
                let to = part_file(self.parts, idx, f);
                std::fs::rename(tmp(f), &to).map_err(io("rename", &to))?;
            }
            Ok(part)
        })();
        if out.is_err() {
            for f in names {
                let _ = std::fs::remove_file(tmp(f));
            }
        }
        out
    }
}

/// Joins finished parts `0..n_parts` of `parts` into a dataset of `n_rows` rows in
/// `dir` (theta.csv, x.csv with their headers, meta.json; renamed into place like
/// [`Writer::finish`]): the same bytes as [`simulate_to_dir`] with the same rows. The
/// parts must cover rows `0..n_rows` in order, once each: anything else is an error,
/// not a short dataset. `meta` is [`Meta::new`]'s; its counts, failures and time (the
/// parts' compute) are filled in.
pub fn merge_parts(parts: &Path, n_parts: usize, n_rows: usize, dir: &Path, meta: &mut Meta) -> Result<()> {
    PartJoiner::create(parts, dir, meta)?.finish(n_parts, n_rows, meta)
}

/// Joins a dataset's parts in order as they finish, so that a chunked run copies its
/// table while other chunks still run and only the last parts are left at its end
/// ([`merge_parts`] all at once). Its tables are temporary files in `dir` until
/// [`PartJoiner::finish`]; [`PartJoiner::abandon`] removes them.
pub struct PartJoiner<'a> {
    parts: &'a Path,
    writer: Writer,
    /// The next part to append, and the first row it must hold.
    next: (usize, usize),
    failed: Vec<Failed>,
    wall: f64,
}

impl<'a> PartJoiner<'a> {
    /// Opens the dataset's temporary tables in `dir` with their headers.
    pub fn create(parts: &'a Path, dir: &Path, meta: &Meta) -> Result<PartJoiner<'a>> {
        let writer = Writer::create(dir, meta, Format::Csv)?;
        Ok(PartJoiner { parts, writer, next: (0, 0), failed: vec![], wall: 0.0 })
    }

    /// Parts appended so far.
    pub fn appended(&self) -> usize {
        self.next.0
    }

    /// Appends parts up to (not including) `upto`, which must be finished.
    pub fn append_upto(&mut self, upto: usize) -> Result<()> {
        while self.next.0 < upto {
            self.append_next()?;
        }
        Ok(())
    }

    fn append_next(&mut self) -> Result<()> {
        let (idx, first) = self.next;
        let unusable = |why: String| {
            let e = std::io::Error::new(std::io::ErrorKind::InvalidData, why);
            DatasetError::Io(FileError { action: "read", path: part_file(self.parts, idx, "json"), source: e })
        };
        let part = read_part(self.parts, idx).ok_or_else(|| unusable("part not finished".into()))?;
        if part.first != first || part.len == 0 {
            let why = format!("part holds rows {}..{}, expected from row {first}", part.first, part.first + part.len);
            return Err(unusable(why));
        }
        for (f, w) in [(FILES[0], &mut self.writer.theta), (FILES[1], &mut self.writer.x)] {
            let from = part_file(self.parts, idx, f);
            File::open(&from).and_then(|mut r| std::io::copy(&mut r, w)).map_err(io("read", &from))?;
        }
        self.writer.rows += part.rows;
        self.wall += part.wall_seconds;
        self.failed.extend(part.failed);
        self.next = (idx + 1, first + part.len);
        Ok(())
    }

    /// Appends the parts left of `0..n_parts` and renames the dataset into place, if
    /// the parts cover rows `0..n_rows`; `meta` gets the counts, failures and compute
    /// time. On an error the temporary tables are removed.
    pub fn finish(mut self, n_parts: usize, n_rows: usize, meta: &mut Meta) -> Result<()> {
        if let Err(e) = self.append_upto(n_parts) {
            self.abandon();
            return Err(e);
        }
        if self.next.1 != n_rows {
            let e = std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                format!("parts cover {} of {n_rows} rows", self.next.1),
            );
            let path = self.parts.to_path_buf();
            self.abandon();
            return Err(DatasetError::Io(FileError { action: "read", path, source: e }));
        }
        meta.failed.extend(self.failed);
        meta.wall_seconds = self.wall;
        self.writer.finish(meta)
    }

    /// Removes the temporary tables.
    pub fn abandon(self) {
        self.writer.abandon();
    }
}

/// A numeric CSV table with a header row.
pub struct Table {
    /// The column names.
    pub header: Vec<String>,
    /// The rows, each as long as the header.
    pub rows: Vec<Vec<f64>>,
}

/// Reads a numeric CSV; errors name the file, line and column.
pub fn read_csv(path: &Path) -> Result<Table> {
    let f = File::open(path).map_err(io("open", path))?;
    let mut lines = BufReader::new(f).lines();
    let bad = |why: String| DatasetError::table(path, why);
    let header: Vec<String> = match lines.next() {
        Some(l) => l.map_err(io("read", path))?.split(',').map(|s| s.trim().to_string()).collect(),
        None => return Err(bad("empty file (expected a header row)".into())),
    };
    let mut rows = Vec::new();
    for (i, line) in lines.enumerate() {
        let line = line.map_err(io("read", path))?;
        if line.trim().is_empty() {
            continue;
        }
        let cells: Vec<&str> = line.split(',').collect();
        if cells.len() != header.len() {
            return Err(bad(format!("line {} has {} values, the header has {}", i + 2, cells.len(), header.len())));
        }
        let row = cells
            .iter()
            .zip(&header)
            .map(|(c, h)| {
                c.trim().parse::<f64>().map_err(|_| bad(format!("line {}, column '{h}': '{c}' is not a number", i + 2)))
            })
            .collect::<Result<Vec<f64>>>()?;
        rows.push(row);
    }
    Ok(Table { header, rows })
}

/// Reads a .npy table whose columns are `header` (from the dataset's meta.json);
/// errors name the file.
pub fn read_npy(path: &Path, header: Vec<String>) -> Result<Table> {
    let f = File::open(path).map_err(io("open", path))?;
    let (rows, cols, values) = crate::npy::read(&mut BufReader::new(f)).map_err(|e| match e {
        crate::npy::NpyError::Io(e) => {
            DatasetError::Io(FileError { action: "read", path: path.to_path_buf(), source: e })
        }
        crate::npy::NpyError::Format(why) => DatasetError::table(path, why),
    })?;
    if cols != header.len() {
        let why = format!("{cols} columns, but meta.json names {}", header.len());
        return Err(DatasetError::table(path, why));
    }
    let rows = if cols == 0 { vec![vec![]; rows] } else { values.chunks_exact(cols).map(<[f64]>::to_vec).collect() };
    Ok(Table { header, rows })
}

/// A noise table: one row of per-feature test–retest STDs under a header of feature
/// names (e.g. reference/std.csv), in the order of `names`.
pub fn read_noise_table(path: &Path, names: &[String]) -> Result<Vec<f64>> {
    let t = read_csv(path)?;
    let bad = |why: String| DatasetError::table(path, why);
    if t.rows.len() != 1 {
        return Err(bad(format!("a noise table has exactly one row of STDs, found {}", t.rows.len())));
    }
    names
        .iter()
        .map(|n| {
            let i = t
                .header
                .iter()
                .position(|h| h == n)
                .ok_or_else(|| bad(format!("column '{n}' missing (the table needs every feature)")))?;
            let v = t.rows[0][i];
            if !(v.is_finite() && v >= 0.0) {
                return Err(bad(format!("column '{n}': STD must be finite and ≥ 0, got {v}")));
            }
            Ok(v)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::batch::{self, Design, Noise};

    /// Sub-batches simulated beside the pushing of the one before still arrive in row
    /// order, each row the simulator's own output for its draw; progress counts the
    /// pushed rows, and a stop after the first sub-batch pushes no other.
    #[test]
    fn sub_batches_are_pushed_in_row_order_and_a_stop_pushes_no_more() {
        let model = crate::sim::Model::new(crate::sim::ModelConfig::default()).unwrap();
        let design = Design::default();
        let noise = Noise { std: batch::default_noise_std(&model), scale: 1.0, seed: 2 };
        let (first, n) = (7, 2 * Batch::SUB + 50);
        let rows = Rows::Prior { n: first + n, seed: 9 };
        let run = Batch { model: &model, design: &design, rows: &rows, noise: &noise };
        let pool = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        let go = |stop_after: usize| {
            let (mut theta, mut x, mut pushes, mut seen, mut failed) = (vec![], vec![], 0, vec![], vec![]);
            let finished = pool.install(|| {
                let mut push = |b: &Block| {
                    theta.extend_from_slice(&b.theta);
                    x.extend_from_slice(&b.x);
                    pushes += 1;
                    Ok(())
                };
                run.run(first, n, &mut failed, &mut push, &mut |d| {
                    seen.push(d);
                    seen.len() < stop_after
                })
            });
            assert!(failed.is_empty(), "{failed:?}");
            (finished.unwrap(), theta, x, pushes, seen)
        };
        let (finished, theta, x, pushes, seen) = go(usize::MAX);
        assert!(finished);
        assert_eq!((pushes, seen), (3, vec![Batch::SUB, 2 * Batch::SUB, n]));
        let draws = design.draw(9, first, n);
        let direct = batch::run_rows(&model, &design, &draws, first, Some(&noise));
        assert!(theta == draws.concat(), "θ rows out of order");
        assert!(x == direct.into_iter().map(|r| r.unwrap()).collect::<Vec<_>>().concat(), "x rows out of order");
        let (finished, theta, _, pushes, seen) = go(1);
        assert!(!finished, "a stop before the last sub-batch is reported");
        assert_eq!((pushes, seen, theta.len()), (1, vec![Batch::SUB], Batch::SUB * design.width()));
    }
}
