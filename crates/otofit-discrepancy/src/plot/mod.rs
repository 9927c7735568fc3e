//! SVG figures written by hand (no plotting dependency to build): spectra with bands,
//! residual maps and corner plots. Each function returns a complete SVG document.

mod canvas;
pub mod diagnosis;
pub mod html;
mod pages;
mod posterior;
pub use canvas::{Axes, Canvas};
pub use pages::{Resimulation, resimulation};
pub use posterior::posterior_corner;

use crate::sim::output::MEASURES;

/// Colours: observation, MAP, draws, predictive band, truth.
pub const OBS: &str = "#222222";
/// Colour of the MAP estimate.
pub const MAP: &str = "#d62728";
/// Colour of posterior draws.
pub const DRAW: &str = "#1f77b4";
/// Colour of the predictive band.
pub const BAND: &str = "#1f77b4";
/// Colour of the true value (simulated cases).
pub const TRUTH: &str = "#2ca02c";
/// The observation's noise band.
pub const NOISE: &str = "#777777";

/// x ± s, elementwise (e.g. an observation and its test–retest STD).
pub fn plus_minus(x: &[f64], s: &[f64]) -> (Vec<f64>, Vec<f64>) {
    (x.iter().zip(s).map(|(v, e)| v - e).collect(), x.iter().zip(s).map(|(v, e)| v + e).collect())
}

/// How each measure is shown: its label and the map from feature value to plotted value.
fn display(measure: usize, v: f64) -> f64 {
    match MEASURES[measure].name {
        "vst_mag" | "vu_mag" => 20.0 * (v + 3.0), // log10(m/s/Pa) → dB re 1 mm/s/Pa
        "zec_mag" => v,                           // log10(Pa·s/m³)
        "vst_phase" | "zec_phase" | "vu_phase" => v.to_degrees(),
        _ => v,
    }
}

fn label(measure: usize) -> &'static str {
    match MEASURES[measure].name {
        "vst_mag" => "|Vst/P| (dB re 1 mm/s/Pa)",
        "vst_phase" => "Vst/P phase (deg)",
        "zec_mag" => "log10 |Zec| (Pa·s/m³)",
        "zec_phase" => "Zec phase (deg)",
        "vu_mag" => "|Vumbo/P| (dB re 1 mm/s/Pa)",
        "vu_phase" => "Vumbo/P phase (deg)",
        _ => "absorbance",
    }
}

/// One spectrum to draw, as features (measure-major on `freqs`, `MEASURES` order).
pub struct Series<'a> {
    /// The features to draw.
    pub x: &'a [f64],
    /// Stroke colour.
    pub color: &'a str,
    /// Stroke width in pixels.
    pub width: f64,
    /// Stroke opacity, 0 to 1.
    pub opacity: f64,
    /// Legend entry; `None` for no entry (e.g. one of many draws).
    pub label: Option<&'a str>,
}

/// A shaded band between two spectra (e.g. a 90 % predictive band).
pub struct Band<'a> {
    /// The lower spectrum, as features.
    pub lo: &'a [f64],
    /// The upper spectrum, as features.
    pub hi: &'a [f64],
    /// Fill colour.
    pub color: &'a str,
    /// Legend entry.
    pub label: &'a str,
}

/// One panel per measure (as many as the shortest series holds): optional bands under
/// the series; non-finite values (an absent measure) are not drawn.
pub fn spectra(title: &str, freqs: &[f64], bands: &[Band<'_>], series: &[Series<'_>]) -> String {
    let n = freqs.len().max(1);
    let measures = series.iter().map(|s| s.x.len() / n).min().unwrap_or(0).min(MEASURES.len());
    let rows = measures.div_ceil(2).max(1) + usize::from(measures % 2 == 0);
    let (pw, ph) = (420.0, 240.0);
    let mut c = Canvas::new(2.0 * pw + 40.0, rows as f64 * ph + 60.0);
    c.text(20.0, 28.0, 16.0, "start", title);
    for m in 0..measures {
        let (col, row) = (m % 2, m / 2);
        let (x0, y0) = (20.0 + col as f64 * pw, 40.0 + row as f64 * ph);
        let shown = |x: &[f64]| -> Vec<f64> { x[m * n..(m + 1) * n].iter().map(|&v| display(m, v)).collect() };
        let mut lo = f64::INFINITY;
        let mut hi = f64::NEG_INFINITY;
        let all = series
            .iter()
            .flat_map(|s| shown(s.x))
            .chain(bands.iter().flat_map(|b| shown(b.lo).into_iter().chain(shown(b.hi))));
        for v in all.filter(|v| v.is_finite()) {
            lo = lo.min(v);
            hi = hi.max(v);
        }
        if lo > hi {
            (lo, hi) = (0.0, 1.0);
        }
        let pad = 0.05 * (hi - lo).max(1e-6);
        let ax =
            Axes::new(x0 + 60.0, y0 + 10.0, pw - 80.0, ph - 60.0, (freqs[0], freqs[n - 1]), (lo - pad, hi + pad), true);
        c.axes(&ax, "frequency (Hz)", label(m));
        for b in bands.iter().filter(|b| shown(b.lo).iter().chain(&shown(b.hi)).all(|v| v.is_finite())) {
            c.band(&ax, freqs, &shown(b.lo), &shown(b.hi), b.color, 0.2);
        }
        for s in series {
            c.line(&ax, freqs, &shown(s.x), s.color, s.width, s.opacity);
        }
    }
    // Legend in the panel after the last measure.
    let (lx, mut ly) = (40.0 + (measures % 2) as f64 * pw, 80.0 + (measures / 2) as f64 * ph);
    for s in series.iter().filter(|s| s.label.is_some()) {
        c.rect(lx, ly - 8.0, 24.0, 3.0, s.color, 1.0);
        c.text(lx + 32.0, ly - 2.0, 12.0, "start", s.label.unwrap_or(""));
        ly += 20.0;
    }
    for b in bands {
        c.rect(lx, ly - 10.0, 24.0, 10.0, b.color, 0.2);
        c.text(lx + 32.0, ly - 2.0, 12.0, "start", b.label);
        ly += 20.0;
    }
    c.finish()
}

/// Residual map: measures × frequencies, colour = standardised residual clipped at ±4.
pub fn residual_map(title: &str, freqs: &[f64], z: &[f64]) -> String {
    let n = freqs.len();
    let (cw, chh) = (12.0, 28.0);
    let (left, top) = (150.0, 50.0);
    let rows = (z.len() / n.max(1)).min(MEASURES.len());
    let bottom = top + chh * rows as f64;
    let mut c = Canvas::new(left + cw * n as f64 + 120.0, bottom + 70.0);
    c.text(20.0, 28.0, 16.0, "start", title);
    for m in 0..rows {
        c.text(left - 8.0, top + chh * (m as f64 + 0.65), 12.0, "end", MEASURES[m].name);
        for i in 0..n {
            c.rect(left + cw * i as f64, top + chh * m as f64, cw, chh, &diverging(z[m * n + i] / 4.0), 1.0);
        }
    }
    for &f in &[200.0, 500.0, 1000.0, 2000.0, 4000.0, 8000.0] {
        let i = freqs.iter().position(|&g| g >= f * 0.999).unwrap_or(n - 1);
        c.text(left + cw * (i as f64 + 0.5), bottom + 16.0, 11.0, "middle", &format!("{f:.0}"));
    }
    c.text(left + cw * n as f64 / 2.0, bottom + 36.0, 12.0, "middle", "frequency (Hz)");
    // Colour bar.
    let bx = left + cw * n as f64 + 30.0;
    for k in 0..20 {
        let v = 1.0 - k as f64 / 9.5;
        c.rect(bx, top + 7.0 * k as f64, 16.0, 7.0, &diverging(v), 1.0);
    }
    c.text(bx + 20.0, top + 8.0, 11.0, "start", "z ≥ +4");
    c.text(bx + 20.0, top + 140.0, 11.0, "start", "z ≤ −4");
    c.finish()
}

/// Blue (−1) – white (0) – red (+1).
fn diverging(t: f64) -> String {
    let t = t.clamp(-1.0, 1.0);
    let (r, g, b) = if t >= 0.0 { (1.0, 1.0 - t, 1.0 - t) } else { (1.0 + t, 1.0 + t, 1.0) };
    format!("#{:02x}{:02x}{:02x}", (r * 255.0) as u8, (g * 255.0) as u8, (b * 255.0) as u8)
}

/// One parameter of a corner plot.
pub struct Dim<'a> {
    /// The parameter's name, as the axis label.
    pub name: &'a str,
    /// Its unit, shown after the name.
    pub unit: &'a str,
    /// Lower end of the axis (the prior's bound).
    pub low: f64,
    /// Upper end of the axis.
    pub high: f64,
    /// Whether the axis is logarithmic.
    pub log: bool,
    /// The true value to mark, for simulated cases.
    pub truth: Option<f64>,
    /// The MAP estimate to mark.
    pub map: Option<f64>,
}

/// Tick positions and labels for one corner-plot axis: decades (every second one when
/// there are more than four) on log axes, "nice" steps on linear ones.
fn dim_ticks(dim: &Dim<'_>) -> Vec<(f64, String)> {
    if dim.log {
        if !(dim.low > 0.0 && dim.high > dim.low && dim.high.is_finite()) {
            return Vec::new();
        }
        let (a, b) = (dim.low.log10().ceil() as i32, dim.high.log10().floor() as i32);
        let step = if b - a > 4 { 2 } else { 1 };
        (a..=b).step_by(step as usize).take(12).map(|k| (10f64.powi(k), format!("1e{k}"))).collect()
    } else {
        canvas::ticks(dim.low, dim.high).into_iter().map(|t| (t, format!("{}", (t * 1e6).round() / 1e6))).collect()
    }
}

/// Corner plot: 1D histograms on the diagonal, 2D histograms below it, the true value
/// (green) and MAP (red) marked; log axes for log-scale parameters.
pub fn corner(title: &str, dims: &[Dim<'_>], samples: &[Vec<f64>]) -> String {
    let d = dims.len();
    let g = Corner { dims, cell: 110.0, left: 60.0, top: 50.0, bins: 24 };
    let (cell, left, top) = (g.cell, g.left, g.top);
    let mut c = Canvas::new(left + cell * d as f64 + 20.0, top + cell * d as f64 + 70.0);
    c.text(20.0, 28.0, 16.0, "start", title);
    for i in 0..d {
        for j in 0..=i {
            let (x0, y0) = (left + cell * j as f64, top + cell * i as f64);
            c.frame(x0 + 2.0, y0 + 2.0, cell - 4.0, cell - 4.0);
            if i == j {
                g.diagonal(&mut c, samples, i);
            } else {
                g.pair(&mut c, samples, i, j);
            }
        }
        g.axis(&mut c, i);
    }
    c.text(left, top + cell * d as f64 + 56.0, 11.0, "start", "green: true value · red: MAP · axes span the prior box");
    c.finish()
}

/// A corner plot's layout: square cells of `cell` px from (`left`, `top`), histograms
/// of `bins` bins per axis.
struct Corner<'a> {
    dims: &'a [Dim<'a>],
    cell: f64,
    left: f64,
    top: f64,
    bins: usize,
}

impl Corner<'_> {
    /// Where `v` lies on parameter `k`'s axis, 0–1. Clamped below 1 so that the upper
    /// edge falls in the last bin, not past it.
    fn unit(&self, k: usize, v: f64) -> f64 {
        let dim = &self.dims[k];
        let t = |v: f64| if dim.log { v.log10() } else { v };
        ((t(v) - t(dim.low)) / (t(dim.high) - t(dim.low))).clamp(0.0, 1.0 - 1e-12)
    }

    /// Cell (i, i): parameter i's histogram and its true and MAP values.
    fn diagonal(&self, c: &mut Canvas, samples: &[Vec<f64>], i: usize) {
        let (cell, bins) = (self.cell, self.bins);
        let (x0, y0) = (self.left + cell * i as f64, self.top + cell * i as f64);
        let mut h = vec![0usize; bins];
        for s in samples {
            h[(self.unit(i, s[i]) * bins as f64) as usize] += 1;
        }
        let top_count = *h.iter().max().unwrap_or(&1) as f64;
        for (b, &cnt) in h.iter().enumerate() {
            let bh = (cell - 10.0) * cnt as f64 / top_count.max(1.0);
            let bw = (cell - 4.0) / bins as f64;
            c.rect(x0 + 2.0 + bw * b as f64, y0 + cell - 2.0 - bh, bw, bh, DRAW, 0.7);
        }
        for (v, color) in [(self.dims[i].truth, TRUTH), (self.dims[i].map, MAP)] {
            if let Some(v) = v {
                let x = x0 + 2.0 + (cell - 4.0) * self.unit(i, v);
                c.vline(x, y0 + 2.0, y0 + cell - 2.0, color);
            }
        }
    }

    /// Cell (i, j), j < i: the joint histogram of parameters j (x) and i (y), shaded by
    /// the square root of the count so that the tails stay visible.
    fn pair(&self, c: &mut Canvas, samples: &[Vec<f64>], i: usize, j: usize) {
        let (cell, bins, dims) = (self.cell, self.bins, self.dims);
        let (x0, y0) = (self.left + cell * j as f64, self.top + cell * i as f64);
        let mut h = vec![0usize; bins * bins];
        for s in samples {
            let (a, b) = ((self.unit(j, s[j]) * bins as f64) as usize, (self.unit(i, s[i]) * bins as f64) as usize);
            h[b * bins + a] += 1;
        }
        let top_count = *h.iter().max().unwrap_or(&1) as f64;
        let bw = (cell - 4.0) / bins as f64;
        for (k, &cnt) in h.iter().enumerate().filter(|(_, c)| **c > 0) {
            let (a, b) = (k % bins, k / bins);
            let op = (cnt as f64 / top_count).sqrt();
            c.rect(x0 + 2.0 + bw * a as f64, y0 + cell - 2.0 - bw * (b + 1) as f64, bw, bw, DRAW, op);
        }
        for (vx, vy, color) in [(dims[j].truth, dims[i].truth, TRUTH), (dims[j].map, dims[i].map, MAP)] {
            if let (Some(vx), Some(vy)) = (vx, vy) {
                c.dot(
                    x0 + 2.0 + (cell - 4.0) * self.unit(j, vx),
                    y0 + cell - 2.0 - (cell - 4.0) * self.unit(i, vy),
                    3.5,
                    color,
                );
            }
        }
    }

    /// Parameter i's tick values in its unit (under the bottom row, left of the first
    /// column) and its name.
    fn axis(&self, c: &mut Canvas, i: usize) {
        let (cell, left, top, dim) = (self.cell, self.left, self.top, &self.dims[i]);
        let bottom = top + cell * self.dims.len() as f64;
        // Ticks at the very edges would run into the neighbouring cell's labels.
        for (v, lab) in dim_ticks(dim).into_iter().filter(|(v, _)| (0.04..0.96).contains(&self.unit(i, *v))) {
            let x = left + cell * i as f64 + 2.0 + (cell - 4.0) * self.unit(i, v);
            c.vline(x, bottom - 2.0, bottom + 2.0, "#444");
            c.text(x, bottom + 11.0, 8.0, "middle", &lab);
            if i > 0 {
                let y = top + cell * (i as f64 + 1.0) - 2.0 - (cell - 4.0) * self.unit(i, v);
                c.text(left - 3.0, y + 3.0, 8.0, "end", &lab);
            }
        }
        let x = left + cell * (i as f64 + 0.5);
        c.text(x, bottom + 26.0, 10.0, "middle", dim.name);
        c.text(x, bottom + 38.0, 9.0, "middle", &format!("{}{}", if dim.log { "log axis, " } else { "" }, dim.unit));
    }
}

/// Colours for runs compared side by side (noise levels, training sizes).
pub const RUNS: [&str; 4] = ["#9467bd", "#1f77b4", "#ff7f0e", "#8c564b"];

/// Posterior intervals per parameter for several runs (rows = parameters, one line per
/// run: 90 % interval with the median as a dot), over the prior box; truth in green.
pub fn intervals(title: &str, dims: &[Dim<'_>], runs: &[(&str, Vec<[f64; 3]>)]) -> String {
    let (left, top, w, row) = (150.0, 50.0, 520.0, 26.0 + 8.0 * runs.len() as f64);
    let mut c = Canvas::new(left + w + 40.0, top + row * dims.len() as f64 + 40.0 + 18.0 * runs.len() as f64);
    c.text(20.0, 28.0, 16.0, "start", title);
    for (k, d) in dims.iter().enumerate() {
        let y0 = top + row * k as f64;
        let t = |v: f64| if d.log { v.log10() } else { v };
        let px = |v: f64| left + w * ((t(v) - t(d.low)) / (t(d.high) - t(d.low))).clamp(0.0, 1.0);
        c.frame(left, y0, w, row - 4.0);
        c.text(left - 8.0, y0 + row / 2.0, 11.0, "end", d.name);
        c.text(left + w + 4.0, y0 + row / 2.0, 9.0, "start", if d.log { "log" } else { "" });
        c.text(left + 3.0, y0 + row - 7.0, 8.0, "start", &format!("{:.2e}", d.low));
        c.text(left + w - 3.0, y0 + row - 7.0, 8.0, "end", &format!("{:.2e} {}", d.high, d.unit));
        if let Some(v) = d.truth {
            c.vline(px(v), y0, y0 + row - 4.0, TRUTH);
        }
        for (r, (_, q)) in runs.iter().enumerate() {
            let y = y0 + 8.0 + 8.0 * r as f64;
            let [lo, mid, hi] = q[k];
            c.rect(px(lo), y - 1.5, (px(hi) - px(lo)).max(1.0), 3.0, RUNS[r % RUNS.len()], 1.0);
            c.dot(px(mid), y, 3.0, RUNS[r % RUNS.len()]);
        }
    }
    let mut ly = top + row * dims.len() as f64 + 20.0;
    for (r, (label, _)) in runs.iter().enumerate() {
        c.rect(left, ly - 6.0, 24.0, 3.0, RUNS[r % RUNS.len()], 1.0);
        c.text(left + 32.0, ly - 2.0, 12.0, "start", label);
        ly += 18.0;
    }
    c.text(left + w, ly - 2.0, 11.0, "end", "90 % interval and median · green: true value · axes span the prior box");
    c.finish()
}

/// Calibration figure: the joint expected-coverage curve against the diagonal, and one
/// SBC rank histogram per parameter (counts in `bins` equal bins of rank/(samples + 1),
/// with the 99 % band of a uniform histogram).
pub fn calibration(
    title: &str,
    levels: &[f64],
    coverage: &[f64],
    ranks: &[(&str, Vec<usize>)],
    samples: usize,
) -> String {
    let bins = 10usize;
    let cols = 4usize;
    let rows = 1 + ranks.len().div_ceil(cols);
    let (pw, ph) = (220.0, 180.0);
    let mut c = Canvas::new(cols as f64 * pw + 40.0, rows as f64 * ph + 50.0);
    c.text(20.0, 28.0, 16.0, "start", title);
    let ax = Axes::new(80.0, 50.0, pw - 60.0, ph - 60.0, (0.0, 1.0), (0.0, 1.0), false);
    c.axes(&ax, "credible level", "coverage");
    c.line(&ax, &[0.0, 1.0], &[0.0, 1.0], OBS, 1.0, 0.5);
    c.line(&ax, levels, coverage, MAP, 2.0, 1.0);
    c.text(ax.x + ax.w + 20.0, ax.y + 12.0, 12.0, "start", "joint HPD coverage on held-out simulations");
    c.text(ax.x + ax.w + 20.0, ax.y + 30.0, 12.0, "start", "below the diagonal: overconfident");
    for (k, (name, r)) in ranks.iter().enumerate() {
        let (col, row) = (k % cols, 1 + k / cols);
        let (x0, y0) = (20.0 + col as f64 * pw, 40.0 + row as f64 * ph);
        let mut counts = vec![0.0; bins];
        for &v in r {
            let b = ((v as f64 / (samples + 1) as f64) * bins as f64) as usize;
            counts[b.min(bins - 1)] += 1.0;
        }
        let n = r.len().max(1) as f64;
        let expect = n / bins as f64;
        let spread = 2.576 * (expect * (1.0 - 1.0 / bins as f64)).sqrt();
        let top = counts.iter().copied().fold(expect + spread, f64::max) * 1.1;
        let ax = Axes::new(x0 + 50.0, y0 + 10.0, pw - 70.0, ph - 60.0, (0.0, 1.0), (0.0, top), false);
        c.axes(&ax, name, "rows");
        let lo = vec![(expect - spread).max(0.0); 2];
        c.band(&ax, &[0.0, 1.0], &lo, &[expect + spread; 2], NOISE, 0.25);
        for (b, &h) in counts.iter().enumerate() {
            let (x, w) = (ax.px(b as f64 / bins as f64), ax.px(1.0 / bins as f64) - ax.px(0.0));
            c.rect(x + 1.0, ax.py(h), w - 2.0, ax.py(0.0) - ax.py(h), DRAW, 0.7);
        }
    }
    c.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn well_formed(svg: &str) {
        assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
        assert!(!svg.contains("NaN") && !svg.contains("inf"), "non-finite coordinates");
    }

    #[test]
    fn figures_are_well_formed_svg() {
        let freqs = crate::sim::log_grid(200.0, 8000.0, 50);
        let x: Vec<f64> = (0..250).map(|i| (i as f64 * 0.1).sin()).collect();
        let lo: Vec<f64> = x.iter().map(|v| v - 0.1).collect();
        let hi: Vec<f64> = x.iter().map(|v| v + 0.1).collect();
        let s = spectra(
            "t",
            &freqs,
            &[Band { lo: &lo, hi: &hi, color: BAND, label: "band" }],
            &[Series { x: &x, color: OBS, width: 2.0, opacity: 1.0, label: Some("observation") }],
        );
        well_formed(&s);
        assert_eq!(s.matches("<polyline").count(), 5);
        // Seven measures, the umbo's absent from the observation: seven panels, no NaN.
        let mut x7: Vec<f64> = (0..350).map(|i| (i as f64 * 0.1).sin()).collect();
        let sim = x7.clone();
        x7[250..].fill(f64::NAN);
        let s = spectra(
            "t",
            &freqs,
            &[],
            &[
                Series { x: &x7, color: OBS, width: 2.0, opacity: 1.0, label: Some("observation") },
                Series { x: &sim, color: MAP, width: 1.0, opacity: 1.0, label: Some("MAP") },
            ],
        );
        well_formed(&s);
        assert_eq!(s.matches("Vumbo/P phase").count(), 1, "the seventh panel is drawn");
        well_formed(&residual_map("r", &freqs, &sim));
        well_formed(&residual_map("r", &freqs, &x));
        let dims = [
            Dim { name: "a", unit: "Pa", low: 1.0, high: 100.0, log: true, truth: Some(10.0), map: Some(12.0) },
            Dim { name: "b", unit: "s", low: 0.0, high: 1.0, log: false, truth: None, map: Some(0.5) },
        ];
        let samples: Vec<Vec<f64>> = (0..200).map(|i| vec![1.0 + i as f64 / 3.0, (i as f64 / 200.0)]).collect();
        well_formed(&corner("c", &dims, &samples));
        let runs = [("a", vec![[2.0, 5.0, 9.0], [0.1, 0.5, 0.9]]), ("b", vec![[4.0, 5.0, 6.0], [0.4, 0.5, 0.6]])];
        let s = intervals("i", &dims, &runs);
        well_formed(&s);
        assert_eq!(s.matches("<circle").count(), 4, "one median dot per run and parameter");
    }

    #[test]
    fn diverging_colours_span_blue_white_red() {
        assert_eq!(diverging(-1.0), "#0000ff");
        assert_eq!(diverging(0.0), "#ffffff");
        assert_eq!(diverging(2.0), "#ff0000");
    }
}
