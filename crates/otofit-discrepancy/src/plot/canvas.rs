//! A minimal SVG canvas: rectangles, polylines, bands, text and axes with ticks.

use std::fmt::Write;

/// An SVG document being drawn: its size and the elements so far.
pub struct Canvas {
    w: f64,
    h: f64,
    body: String,
}

/// A plotting area in canvas pixels with its data ranges (x optionally logarithmic).
pub struct Axes {
    /// Left edge of the plotting area.
    pub x: f64,
    /// Top edge.
    pub y: f64,
    /// Width.
    pub w: f64,
    /// Height.
    pub h: f64,
    /// Data range shown along x.
    pub xr: (f64, f64),
    /// Data range shown along y.
    pub yr: (f64, f64),
    /// Whether x is on a log scale (frequency axes).
    pub log_x: bool,
}

impl Axes {
    /// A plotting area at (`x`, `y`) of size `w`×`h` showing `xr`×`yr`.
    pub fn new(x: f64, y: f64, w: f64, h: f64, xr: (f64, f64), yr: (f64, f64), log_x: bool) -> Axes {
        Axes { x, y, w, h, xr, yr, log_x }
    }
    /// The pixel column of data value `v`.
    pub fn px(&self, v: f64) -> f64 {
        let t = |v: f64| if self.log_x { v.ln() } else { v };
        self.x + self.w * (t(v) - t(self.xr.0)) / (t(self.xr.1) - t(self.xr.0))
    }
    /// The pixel row of data value `v`.
    pub fn py(&self, v: f64) -> f64 {
        self.y + self.h * (1.0 - (v - self.yr.0) / (self.yr.1 - self.yr.0))
    }
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}

/// Most ticks an axis gets; a guard, not a layout choice.
const MAX_TICKS: usize = 12;

/// "Nice" tick values covering [lo, hi]. Degenerate ranges (non-finite, or a span below
/// the resolution of the numbers themselves) get their end points only: stepping by a
/// step smaller than one ulp of `t` would never advance.
pub(crate) fn ticks(lo: f64, hi: f64) -> Vec<f64> {
    if !lo.is_finite() || !hi.is_finite() || hi < lo {
        return Vec::new();
    }
    let span = hi - lo;
    let scale = lo.abs().max(hi.abs());
    if span <= 1e-9 * scale || span < f64::MIN_POSITIVE * 1e6 {
        return if span == 0.0 { vec![lo] } else { vec![lo, hi] };
    }
    let mag = 10f64.powf((span / 5.0).log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0].iter().map(|m| m * mag).find(|s| span / s <= 6.0).unwrap_or(10.0 * mag);
    let first = (lo / step).ceil();
    (0..MAX_TICKS)
        .map(|i| (first + i as f64) * step)
        .take_while(|t| *t <= hi + 1e-9 * span)
        .map(|t| if t.abs() < 1e-12 * span { 0.0 } else { t })
        .collect()
}

/// 1-2-5 ticks per decade over [lo, hi] (positive, finite; at most `MAX_TICKS` decades).
fn log_ticks(lo: f64, hi: f64) -> Vec<f64> {
    if !(lo > 0.0 && hi >= lo && hi.is_finite()) {
        return Vec::new();
    }
    let first = 10f64.powf(lo.log10().floor());
    (0..MAX_TICKS as i32)
        .map(|k| first * 10f64.powi(k))
        .take_while(|d| *d <= hi)
        .flat_map(|d| [1.0, 2.0, 5.0].map(|m| m * d))
        .filter(|t| *t >= lo * 0.999 && *t <= hi * 1.001)
        .collect()
}

impl Canvas {
    /// An empty `w`×`h` canvas.
    pub fn new(w: f64, h: f64) -> Canvas {
        Canvas { w, h, body: String::new() }
    }

    /// A filled rectangle, in pixels.
    pub fn rect(&mut self, x: f64, y: f64, w: f64, h: f64, fill: &str, opacity: f64) {
        let _ = writeln!(
            self.body,
            r#"<rect x="{x:.1}" y="{y:.1}" width="{w:.1}" height="{h:.1}" fill="{fill}" fill-opacity="{opacity:.2}"/>"#
        );
    }

    /// An unfilled grey rectangle (a panel's border), in pixels.
    pub fn frame(&mut self, x: f64, y: f64, w: f64, h: f64) {
        let _ = writeln!(
            self.body,
            r##"<rect x="{x:.1}" y="{y:.1}" width="{w:.1}" height="{h:.1}" fill="none" stroke="#999"/>"##
        );
    }

    /// A vertical line from `y0` to `y1` at column `x`, in pixels.
    pub fn vline(&mut self, x: f64, y0: f64, y1: f64, color: &str) {
        let _ = writeln!(
            self.body,
            r#"<line x1="{x:.1}" y1="{y0:.1}" x2="{x:.1}" y2="{y1:.1}" stroke="{color}" stroke-width="1.5"/>"#
        );
    }

    /// A filled circle of radius `r`, in pixels.
    pub fn dot(&mut self, x: f64, y: f64, r: f64, color: &str) {
        let _ = writeln!(self.body, r#"<circle cx="{x:.1}" cy="{y:.1}" r="{r:.1}" fill="{color}"/>"#);
    }

    /// Text at (`x`, `y`) in pixels; `anchor` is SVG's text-anchor (start, middle, end).
    pub fn text(&mut self, x: f64, y: f64, size: f64, anchor: &str, s: &str) {
        let _ = writeln!(
            self.body,
            r#"<text x="{x:.1}" y="{y:.1}" font-size="{size}" text-anchor="{anchor}" font-family="sans-serif">{}</text>"#,
            escape(s)
        );
    }

    /// A polyline through the data points (`xs`, `ys`) on `ax`, skipping non-finite values.
    pub fn line(&mut self, ax: &Axes, xs: &[f64], ys: &[f64], color: &str, width: f64, opacity: f64) {
        let pts: Vec<String> = xs
            .iter()
            .zip(ys)
            .filter(|(_, y)| y.is_finite())
            .map(|(&x, &y)| format!("{:.1},{:.1}", ax.px(x), ax.py(y)))
            .collect();
        let _ = writeln!(
            self.body,
            r#"<polyline points="{}" fill="none" stroke="{color}" stroke-width="{width}" stroke-opacity="{opacity:.2}"/>"#,
            pts.join(" ")
        );
    }

    /// A filled region between `lo` and `hi` over `xs` on `ax`.
    pub fn band(&mut self, ax: &Axes, xs: &[f64], lo: &[f64], hi: &[f64], color: &str, opacity: f64) {
        let mut pts: Vec<String> =
            xs.iter().zip(hi).map(|(&x, &y)| format!("{:.1},{:.1}", ax.px(x), ax.py(y))).collect();
        pts.extend(xs.iter().zip(lo).rev().map(|(&x, &y)| format!("{:.1},{:.1}", ax.px(x), ax.py(y))));
        let _ = writeln!(
            self.body,
            r#"<polygon points="{}" fill="{color}" fill-opacity="{opacity:.2}" stroke="none"/>"#,
            pts.join(" ")
        );
    }

    /// Frame, ticks and labels (log-x ticks at 1-2-5 decades).
    pub fn axes(&mut self, ax: &Axes, xlabel: &str, ylabel: &str) {
        self.frame(ax.x, ax.y, ax.w, ax.h);
        let xt: Vec<f64> = if ax.log_x { log_ticks(ax.xr.0, ax.xr.1) } else { ticks(ax.xr.0, ax.xr.1) };
        for t in xt {
            let x = ax.px(t);
            self.vline(x, ax.y + ax.h, ax.y + ax.h + 4.0, "#444");
            // Rounded to 6 decimals: 3 × 0.2 prints as 0.6, not 0.6000000000000001.
            let t6 = (t * 1e6).round() / 1e6;
            let lab = if t >= 1000.0 { format!("{}k", t / 1000.0) } else { format!("{t6}") };
            self.text(x, ax.y + ax.h + 16.0, 10.0, "middle", &lab);
        }
        for t in ticks(ax.yr.0, ax.yr.1) {
            let y = ax.py(t);
            let _ = writeln!(
                self.body,
                r##"<line x1="{:.1}" y1="{y:.1}" x2="{:.1}" y2="{y:.1}" stroke="#444"/>"##,
                ax.x - 4.0,
                ax.x
            );
            self.text(ax.x - 6.0, y + 3.5, 10.0, "end", &format!("{}", (t * 1e6).round() / 1e6));
        }
        self.text(ax.x + ax.w / 2.0, ax.y + ax.h + 32.0, 11.0, "middle", xlabel);
        let (lx, ly) = (ax.x - 44.0, ax.y + ax.h / 2.0);
        let _ = writeln!(
            self.body,
            r#"<text x="{lx:.1}" y="{ly:.1}" font-size="11" text-anchor="middle" font-family="sans-serif" transform="rotate(-90 {lx:.1} {ly:.1})">{}</text>"#,
            escape(ylabel)
        );
    }

    /// The SVG document, with a white background.
    pub fn finish(self) -> String {
        format!(
            "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{:.0}\" height=\"{:.0}\" viewBox=\"0 0 {:.0} {:.0}\">\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n{}</svg>\n",
            self.w, self.h, self.w, self.h, self.body
        )
    }
}

#[cfg(test)]
mod tests {
    use super::{log_ticks, ticks};

    #[test]
    fn ticks_end_for_ranges_below_the_resolution_of_their_values() {
        // The poison pill found by fuzzing: t + step == t never advanced the old loop.
        for (lo, hi) in [(1e20, 1e20 + 32768.0), (1e300, 1e300 * (1.0 + 1e-15)), (1e-308, 2e-308), (0.0, 0.0)] {
            let t = ticks(lo, hi);
            assert!(t.len() <= 2, "{lo}..{hi}: {t:?}");
        }
        assert!(ticks(f64::NAN, 1.0).is_empty());
        assert!(ticks(0.0, f64::INFINITY).is_empty());
        assert!(ticks(1.0, 0.0).is_empty());
        assert!(log_ticks(0.0, 1.0).is_empty());
        assert!(log_ticks(1.0, f64::INFINITY).is_empty());
        assert!(log_ticks(1e-300, 1e300).len() <= 3 * 12);
    }

    #[test]
    fn ticks_cover_ordinary_ranges_with_nice_steps() {
        assert_eq!(ticks(0.0, 1.0), vec![0.0, 0.2, 0.4, 0.6000000000000001, 0.8, 1.0]);
        assert_eq!(ticks(-40.0, 10.0), vec![-40.0, -30.0, -20.0, -10.0, 0.0, 10.0]);
        assert!(ticks(3.0, 1e6).len() <= 12);
        assert_eq!(log_ticks(200.0, 8000.0), vec![200.0, 500.0, 1000.0, 2000.0, 5000.0]);
    }
}
