//! Process counters and histograms, rendered for GET /metrics in the Prometheus text
//! exposition format (version 0.0.4), written by hand. Kept below the job layer, which
//! records into it.
//!
//! A few counters and histograms do not need the `metrics` + `metrics-exporter-prometheus`
//! stack (a registry, recorders, a second HTTP listener and their dependency trees); the
//! format is short. Job-table gauges are read from the database at each scrape, so with
//! PostgreSQL every server reports the whole cluster's queue; counters and histograms are
//! this process's own (sum them over processes in PromQL).

use std::collections::BTreeMap;
use std::fmt::Write;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};

/// Upper bounds of the job-duration buckets, seconds.
const JOB_BUCKETS: [f64; 10] = [0.1, 0.5, 1.0, 5.0, 10.0, 30.0, 60.0, 300.0, 900.0, 3600.0];
/// Upper bounds of the /infer latency buckets, seconds.
const INFER_BUCKETS: [f64; 11] = [0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0];

/// One histogram series: cumulative counts per bucket (then +Inf), sum and count.
#[derive(Clone, Default)]
struct Series {
    buckets: Vec<u64>,
    sum: f64,
    count: u64,
}

/// A histogram with labels: series keyed by their rendered label set.
struct Histogram {
    bounds: &'static [f64],
    series: Mutex<BTreeMap<String, Series>>,
}

impl Histogram {
    const fn new(bounds: &'static [f64]) -> Histogram {
        Histogram { bounds, series: Mutex::new(BTreeMap::new()) }
    }

    fn observe(&self, labels: &[(&str, &str)], seconds: f64) {
        let key = render_labels(labels);
        let mut map = self.series.lock().unwrap_or_else(|e| e.into_inner());
        let s = map.entry(key).or_insert_with(|| Series { buckets: vec![0; self.bounds.len()], ..Series::default() });
        for (b, le) in s.buckets.iter_mut().zip(self.bounds) {
            if seconds <= *le {
                *b += 1;
            }
        }
        s.sum += seconds;
        s.count += 1;
    }

    fn render(&self, out: &mut String, name: &str, help: &str) {
        let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} histogram");
        let map = self.series.lock().unwrap_or_else(|e| e.into_inner()).clone();
        for (labels, s) in map {
            let sep = if labels.is_empty() { "" } else { "," };
            for (b, le) in s.buckets.iter().zip(self.bounds) {
                let _ = writeln!(out, "{name}_bucket{{{labels}{sep}le=\"{le}\"}} {b}");
            }
            let _ = writeln!(out, "{name}_bucket{{{labels}{sep}le=\"+Inf\"}} {}", s.count);
            let braces = if labels.is_empty() { String::new() } else { format!("{{{labels}}}") };
            let _ = writeln!(out, "{name}_sum{braces} {}", s.sum);
            let _ = writeln!(out, "{name}_count{braces} {}", s.count);
        }
    }
}

/// `a="x",b="y"` with label values escaped as the format asks (`\\`, `\"`, `\n`).
fn render_labels(labels: &[(&str, &str)]) -> String {
    let esc = |v: &str| v.replace('\\', "\\\\").replace('"', "\\\"").replace('\n', "\\n");
    labels.iter().map(|(k, v)| format!("{k}=\"{}\"", esc(v))).collect::<Vec<_>>().join(",")
}

/// This process's counters and histograms.
pub struct Metrics {
    job_seconds: Histogram,
    infer_seconds: Histogram,
    claims: AtomicU64,
    chunks: AtomicU64,
    leases_lost: AtomicU64,
    reaped: AtomicU64,
    rows: AtomicU64,
}

impl Default for Metrics {
    fn default() -> Self {
        Metrics {
            job_seconds: Histogram::new(&JOB_BUCKETS),
            infer_seconds: Histogram::new(&INFER_BUCKETS),
            claims: AtomicU64::new(0),
            chunks: AtomicU64::new(0),
            leases_lost: AtomicU64::new(0),
            reaped: AtomicU64::new(0),
            rows: AtomicU64::new(0),
        }
    }
}

impl Metrics {
    /// A job this process ran ended (`outcome`: its final state, or `lease_lost`, `requeued`).
    pub fn job_ended(&self, kind: &str, outcome: &str, seconds: f64) {
        self.job_seconds.observe(&[("kind", kind), ("outcome", outcome)], seconds);
    }

    /// A POST /infer answered with `status` after `seconds`.
    pub fn inferred(&self, status: u16, seconds: f64) {
        self.infer_seconds.observe(&[("code", &status.to_string())], seconds);
    }

    /// A job was claimed by this process.
    pub fn claimed(&self) {
        self.claims.fetch_add(1, Ordering::Relaxed);
    }

    /// A chunk of a simulate job was claimed and run by this process (its own job's or,
    /// as an idle worker, another's).
    pub fn chunk_run(&self) {
        self.chunks.fetch_add(1, Ordering::Relaxed);
    }

    /// A running job's lease was lost (another worker may have taken it).
    pub fn lease_lost(&self) {
        self.leases_lost.fetch_add(1, Ordering::Relaxed);
    }

    /// `jobs` jobs whose lease expired were taken back.
    pub fn reaped(&self, jobs: u64) {
        self.reaped.fetch_add(jobs, Ordering::Relaxed);
    }

    /// `rows` more rows simulated by simulate jobs.
    pub fn simulated(&self, rows: u64) {
        self.rows.fetch_add(rows, Ordering::Relaxed);
    }

    /// The exposition: the job table's `queue` counts (kind, state, count) for every job
    /// kind of `kinds`, and this process's series.
    ///
    /// `process`: with this process's counters and histograms, which count every
    /// tenant's work (for admins and a worker's metrics port, not for a tenant's key).
    pub fn render(&self, kinds: &[&str], queue: &[crate::store::QueueCount], process: bool) -> String {
        let mut out = String::new();
        let _ = writeln!(
            out,
            "# HELP otofit_jobs Jobs in the job table by kind and state (every process sharing the database).\n\
             # TYPE otofit_jobs gauge"
        );
        const STATES: [&str; 5] = ["queued", "running", "succeeded", "failed", "cancelled"];
        for &kind in kinds {
            for state in STATES {
                let n: i64 = queue.iter().filter(|c| c.kind == kind && c.state == state).map(|c| c.count).sum();
                let _ = writeln!(out, "otofit_jobs{{kind=\"{kind}\",state=\"{state}\"}} {n}");
            }
        }
        if !process {
            return out;
        }
        let counters = [
            ("otofit_job_claims_total", "Jobs claimed by this process.", &self.claims),
            (
                "otofit_chunk_runs_total",
                "Chunks of simulate jobs this process claimed and ran (its own jobs' and others').",
                &self.chunks,
            ),
            ("otofit_job_leases_lost_total", "Running jobs this process lost to an expired lease.", &self.leases_lost),
            (
                "otofit_jobs_reaped_total",
                "Jobs with an expired lease that this process took back (re-queued or failed).",
                &self.reaped,
            ),
            (
                "otofit_simulated_rows_total",
                "Rows simulated by this process's simulate jobs (rate() = simulations per second).",
                &self.rows,
            ),
        ];
        for (name, help, v) in counters {
            let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} counter\n{name} {}", v.load(Ordering::Relaxed));
        }
        self.job_seconds.render(
            &mut out,
            "otofit_job_duration_seconds",
            "Wall time of the jobs this process ran, by kind and outcome.",
        );
        self.infer_seconds.render(
            &mut out,
            "otofit_infer_duration_seconds",
            "Latency of POST /infer in this process (waiting for a slot included), by status code.",
        );
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn histograms_are_cumulative_and_labelled() {
        let m = Metrics::default();
        m.inferred(200, 0.003);
        m.inferred(200, 0.2);
        m.inferred(503, 12.0);
        m.simulated(1024);
        m.chunk_run();
        let text = m.render(
            &crate::jobs::KINDS,
            &[crate::store::QueueCount { kind: "train".into(), state: "queued".into(), count: 2 }],
            true,
        );
        assert!(text.contains("otofit_jobs{kind=\"train\",state=\"queued\"} 2\n"), "{text}");
        assert!(text.contains("otofit_jobs{kind=\"simulate\",state=\"running\"} 0\n"));
        assert!(text.contains("otofit_infer_duration_seconds_bucket{code=\"200\",le=\"0.005\"} 1\n"), "{text}");
        assert!(text.contains("otofit_infer_duration_seconds_bucket{code=\"200\",le=\"0.25\"} 2\n"));
        assert!(text.contains("otofit_infer_duration_seconds_bucket{code=\"503\",le=\"10\"} 0\n"));
        assert!(text.contains("otofit_infer_duration_seconds_bucket{code=\"503\",le=\"+Inf\"} 1\n"));
        assert!(text.contains("otofit_infer_duration_seconds_count{code=\"200\"} 2\n"));
        assert!(text.contains("otofit_simulated_rows_total 1024\n"));
        assert!(text.contains("otofit_chunk_runs_total 1\n"), "{text}");
        // Every sample line is `name{labels} value` or `name value` with a numeric value.
        for line in text.lines().filter(|l| !l.starts_with('#')) {
            let value = line.rsplit(' ').next().unwrap();
            assert!(value.parse::<f64>().is_ok(), "{line}");
        }
        assert_eq!(render_labels(&[("k", "a\"b\\c\nd")]), "k=\"a\\\"b\\\\c\\nd\"");
    }
}
