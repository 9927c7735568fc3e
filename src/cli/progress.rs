//! Progress of long commands on stderr: a bar with rate and ETA (indicatif) when stderr
//! is a terminal; otherwise (a log file, CI) a plain line at most every few seconds and
//! at the end, so that logs stay readable.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::io::IsTerminal;
use std::time::{Duration, Instant};

/// Seconds between plain lines when stderr is not a terminal.
const PLAIN_EVERY: f64 = 5.0;

/// Progress of `len` units of work called `unit` (e.g. "rows").
pub struct Progress {
    bar: Option<ProgressBar>,
    what: String,
    unit: &'static str,
    len: u64,
    start: Instant,
    last: Option<Instant>,
}

impl Progress {
    /// A bar on a terminal, plain lines otherwise.
    pub fn new(what: &str, unit: &'static str, len: u64) -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar = ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::stderr());
            let style = ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} {prefix} ({per_sec}, ETA {eta})")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> ");
            bar.set_style(style);
            bar.set_message(what.to_string());
            bar.set_prefix(unit);
            bar.enable_steady_tick(Duration::from_millis(200));
            bar
        });
        Progress { bar, what: what.to_string(), unit, len, start: Instant::now(), last: None }
    }

    /// Stages of unknown length (`diagnose`): a spinner with the stage and the time
    /// spent on a terminal; otherwise each stage's message as a plain line.
    pub fn stages(what: &str) -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar = ProgressBar::with_draw_target(None, ProgressDrawTarget::stderr());
            let style = ProgressStyle::with_template("{spinner} {prefix}: {msg} ({elapsed})")
                .unwrap_or_else(|_| ProgressStyle::default_spinner());
            bar.set_style(style);
            bar.set_prefix(what.to_string());
            bar.enable_steady_tick(Duration::from_millis(200));
            bar
        });
        Progress { bar, what: what.to_string(), unit: "", len: 0, start: Instant::now(), last: None }
    }

    /// Whether a bar is drawn (a terminal); callers then leave out their plain lines.
    pub fn is_bar(&self) -> bool {
        self.bar.is_some()
    }

    /// The bar's message (e.g. the current losses), or a plain line without a bar.
    pub fn message(&self, m: &str) {
        match &self.bar {
            Some(bar) => bar.set_message(m.to_string()),
            None => eprintln!("{m}"),
        }
    }

    /// `done` units finished.
    pub fn set(&mut self, done: u64) {
        if let Some(bar) = &self.bar {
            bar.set_position(done);
            return;
        }
        let due = self.last.is_none_or(|t| t.elapsed().as_secs_f64() >= PLAIN_EVERY);
        if due || done >= self.len {
            eprintln!("{}", self.line(done));
            self.last = Some(Instant::now());
        }
    }

    /// Ends the bar (a terminal keeps its last state).
    pub fn finish(&self) {
        if let Some(bar) = &self.bar {
            bar.finish();
        }
    }

    /// "what done/len unit (rate/s, ETA …)" for the plain output.
    fn line(&self, done: u64) -> String {
        let secs = self.start.elapsed().as_secs_f64();
        let rate = done as f64 / secs.max(1e-9);
        let eta = if done >= self.len {
            format!("{secs:.1} s")
        } else if done == 0 {
            "ETA unknown".to_string()
        } else {
            format!("ETA {:.0} s", (self.len - done) as f64 / rate)
        };
        format!("{} {done}/{} {} ({rate:.1}/s, {eta})", self.what, self.len, self.unit)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plain_lines_give_the_rate_and_the_time_left() {
        let mut p =
            Progress { bar: None, what: "simulated".into(), unit: "rows", len: 100, start: Instant::now(), last: None };
        p.start -= Duration::from_secs(10);
        assert_eq!(p.line(25), "simulated 25/100 rows (2.5/s, ETA 30 s)");
        assert_eq!(p.line(0), "simulated 0/100 rows (0.0/s, ETA unknown)");
        assert!(p.line(100).starts_with("simulated 100/100 rows (10.0/s, 10.0 s)"), "{}", p.line(100));
        p.set(10);
        assert!(p.last.is_some(), "the first update is printed");
    }
}
