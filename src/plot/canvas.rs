//! A minimal SVG canvas: rectangles, polylines, bands, text and axes with ticks.

use std::fmt::Write;

pub struct Canvas {
    w: f64,
    h: f64,
    body: String,
}

/// A plotting area in canvas pixels with its data ranges (x optionally logarithmic).
pub struct Axes {
    pub x: f64,
    pub y: f64,
    pub w: f64,
    pub h: f64,
    pub xr: (f64, f64),
    pub yr: (f64, f64),
    pub log_x: bool,
}

impl Axes {
    pub fn new(x: f64, y: f64, w: f64, h: f64, xr: (f64, f64), yr: (f64, f64), log_x: bool) -> Axes {
        Axes { x, y, w, h, xr, yr, log_x }
    }
    pub fn px(&self, v: f64) -> f64 {
        let t = |v: f64| if self.log_x { v.ln() } else { v };
        self.x + self.w * (t(v) - t(self.xr.0)) / (t(self.xr.1) - t(self.xr.0))
    }
    pub fn py(&self, v: f64) -> f64 {
        self.y + self.h * (1.0 - (v - self.yr.0) / (self.yr.1 - self.yr.0))
    }
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}

/// "Nice" tick values covering [lo, hi].
fn ticks(lo: f64, hi: f64) -> Vec<f64> {
    let span = (hi - lo).abs().max(1e-12);
    let raw = span / 5.0;
    let mag = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0].iter().map(|m| m * mag).find(|s| span / s <= 6.0).unwrap_or(10.0 * mag);
    let mut t = (lo / step).ceil() * step;
    let mut out = Vec::new();
    while t <= hi + 1e-9 * span {
        out.push(if t.abs() < 1e-12 * span { 0.0 } else { t });
        t += step;
    }
    out
}

impl Canvas {
    pub fn new(w: f64, h: f64) -> Canvas {
        Canvas { w, h, body: String::new() }
    }

    pub fn rect(&mut self, x: f64, y: f64, w: f64, h: f64, fill: &str, opacity: f64) {
        let _ = writeln!(
            self.body,
            r#"<rect x="{x:.1}" y="{y:.1}" width="{w:.1}" height="{h:.1}" fill="{fill}" fill-opacity="{opacity:.2}"/>"#
        );
    }

    pub fn frame(&mut self, x: f64, y: f64, w: f64, h: f64) {
        let _ = writeln!(
            self.body,
            r##"<rect x="{x:.1}" y="{y:.1}" width="{w:.1}" height="{h:.1}" fill="none" stroke="#999"/>"##
        );
    }

    pub fn vline(&mut self, x: f64, y0: f64, y1: f64, color: &str) {
        let _ = writeln!(
            self.body,
            r#"<line x1="{x:.1}" y1="{y0:.1}" x2="{x:.1}" y2="{y1:.1}" stroke="{color}" stroke-width="1.5"/>"#
        );
    }

    pub fn dot(&mut self, x: f64, y: f64, r: f64, color: &str) {
        let _ = writeln!(self.body, r#"<circle cx="{x:.1}" cy="{y:.1}" r="{r:.1}" fill="{color}"/>"#);
    }

    pub fn text(&mut self, x: f64, y: f64, size: f64, anchor: &str, s: &str) {
        let _ = writeln!(
            self.body,
            r#"<text x="{x:.1}" y="{y:.1}" font-size="{size}" text-anchor="{anchor}" font-family="sans-serif">{}</text>"#,
            escape(s)
        );
    }

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
        let xt: Vec<f64> = if ax.log_x {
            let mut v = Vec::new();
            let mut d = 10f64.powf(ax.xr.0.log10().floor());
            while d <= ax.xr.1 {
                for m in [1.0, 2.0, 5.0] {
                    let t = m * d;
                    if t >= ax.xr.0 * 0.999 && t <= ax.xr.1 * 1.001 {
                        v.push(t);
                    }
                }
                d *= 10.0;
            }
            v
        } else {
            ticks(ax.xr.0, ax.xr.1)
        };
        for t in xt {
            let x = ax.px(t);
            self.vline(x, ax.y + ax.h, ax.y + ax.h + 4.0, "#444");
            let lab = if t >= 1000.0 { format!("{}k", t / 1000.0) } else { format!("{t}") };
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

    pub fn finish(self) -> String {
        format!(
            "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{:.0}\" height=\"{:.0}\" viewBox=\"0 0 {:.0} {:.0}\">\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n{}</svg>\n",
            self.w, self.h, self.w, self.h, self.body
        )
    }
}
