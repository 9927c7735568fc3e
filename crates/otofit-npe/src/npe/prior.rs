//! The prior box and its bijection to the unbounded space the flow works in:
//! θ → t (scale) → u = logit((t − lo)/(hi − lo)). Samples mapped back land inside the
//! box by construction; densities carry the log-Jacobian.

use serde::{Deserialize, Serialize};

/// The one sampling scale (the simulator's; the lower layer owns it).
pub use crate::sim::params::Scale;

/// The parameter-space maps shared by every layer above the simulator: a value's scale
/// coordinate (log10 on a log scale), its position in a box, and the logit of that
/// position (the unbounded space the flow and the least-squares fit work in).
pub mod space {
    use super::Scale;

    /// θ → its scale coordinate t (log10 θ on a log scale).
    pub fn coord(scale: Scale, v: f64) -> f64 {
        match scale {
            Scale::Linear => v,
            Scale::Log10 => v.log10(),
        }
    }

    /// t → θ (not clamped).
    pub fn value(scale: Scale, t: f64) -> f64 {
        match scale {
            Scale::Linear => t,
            Scale::Log10 => 10f64.powf(t),
        }
    }

    /// Position of `v` in [low, high] on the scale: 0 at `low`, 1 at `high`.
    pub fn position(scale: Scale, low: f64, high: f64, v: f64) -> f64 {
        (coord(scale, v) - coord(scale, low)) / (coord(scale, high) - coord(scale, low))
    }

    /// θ → u = logit(position), the position first clamped into [eps, 1 − eps] so that
    /// values on or outside the bounds map to finite u. Callers choose `eps`: the flow's
    /// standardisation uses [`super::FLOW_EDGE`], the least-squares fit [`super::FIT_EDGE`].
    pub fn to_logit(scale: Scale, low: f64, high: f64, v: f64, eps: f64) -> f64 {
        let q = position(scale, low, high, v).clamp(eps, 1.0 - eps);
        (q / (1.0 - q)).ln()
    }

    /// u → θ through the sigmoid, clamped into the box.
    pub fn from_logit(scale: Scale, low: f64, high: f64, u: f64) -> f64 {
        let q = 1.0 / (1.0 + (-u).exp());
        let t = coord(scale, low) + q * (coord(scale, high) - coord(scale, low));
        value(scale, t).clamp(low, high)
    }
}

/// How far inside the box the flow's logit pulls a value on a bound (1e-6 of the box:
/// checkpoints were trained with it, so it stays).
pub const FLOW_EDGE: f64 = 1e-6;

/// How far inside the box the least-squares fit's logit pulls a value on a bound (1e-9:
/// the fit's Laplace intervals were measured with it, so it stays).
pub const FIT_EDGE: f64 = 1e-9;

/// A prior box whose bounds cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("parameter '{name}': bounds [{low}, {high}] are not a valid {scale:?} box")]
pub struct PriorError {
    /// The parameter.
    pub name: String,
    /// Its lower bound.
    pub low: f64,
    /// Its upper bound.
    pub high: f64,
    /// Its scale.
    pub scale: Scale,
}

/// One prior dimension: a named box on a scale.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Param {
    /// Column name (theta.csv) and summary name.
    pub name: String,
    /// Unit, for reports.
    #[serde(default)]
    pub unit: String,
    /// Sampling scale.
    pub scale: Scale,
    /// Lower bound.
    pub low: f64,
    /// Upper bound.
    pub high: f64,
}

impl From<&crate::sim::params::ParamSpec> for Param {
    /// The simulator's parameter as a prior dimension (one definition for every caller).
    fn from(p: &crate::sim::params::ParamSpec) -> Param {
        Param { name: p.name.into(), unit: p.unit.into(), scale: p.scale, low: p.low, high: p.high }
    }
}

impl Param {
    fn t(&self, v: f64) -> f64 {
        space::coord(self.scale, v)
    }

    /// Checks the box: finite, ordered, and positive on a log scale.
    pub fn validate(&self) -> Result<(), PriorError> {
        let ok = self.low.is_finite() && self.high.is_finite() && self.low < self.high;
        if !ok || (self.scale == Scale::Log10 && self.low <= 0.0) {
            return Err(PriorError { name: self.name.clone(), low: self.low, high: self.high, scale: self.scale });
        }
        Ok(())
    }

    /// Position of `v` in the box on the parameter's scale: 0 at `low`, 1 at `high`.
    pub fn position(&self, v: f64) -> f64 {
        space::position(self.scale, self.low, self.high, v)
    }

    /// θ → u. Values on or outside the bounds are pulled in by 1e-6 of the box.
    pub fn to_u(&self, v: f64) -> f64 {
        space::to_logit(self.scale, self.low, self.high, v, FLOW_EDGE)
    }

    /// u → θ, inside the box.
    pub fn from_u(&self, u: f64) -> f64 {
        space::from_logit(self.scale, self.low, self.high, u)
    }

    /// log |du/dθ| at θ (so that log p(θ) = log p(u) + this).
    pub fn log_jacobian(&self, v: f64) -> f64 {
        let span = self.t(self.high) - self.t(self.low);
        let q = ((self.t(v) - self.t(self.low)) / span).clamp(1e-12, 1.0 - 1e-12);
        let dt_dv = match self.scale {
            Scale::Linear => 1.0,
            Scale::Log10 => 1.0 / (v * std::f64::consts::LN_10),
        };
        (1.0 / (q * (1.0 - q)) / span * dt_dv).ln()
    }

    /// θ → its scale coordinate t (log10 θ on a log scale): the flow's space when θ is
    /// z-scored directly instead of passed through the logit.
    pub fn to_t(&self, v: f64) -> f64 {
        self.t(v)
    }

    /// t → θ, clamped into the box.
    pub fn from_t(&self, t: f64) -> f64 {
        space::value(self.scale, t).clamp(self.low, self.high)
    }

    /// Whether scale coordinate t lies inside the box.
    pub fn t_inside(&self, t: f64) -> bool {
        t >= self.t(self.low) && t <= self.t(self.high)
    }

    /// log |dt/dθ| at θ.
    pub fn t_log_jacobian(&self, v: f64) -> f64 {
        match self.scale {
            Scale::Linear => 0.0,
            Scale::Log10 => -(v * std::f64::consts::LN_10).ln(),
        }
    }

    /// Whether `v` is finite and inside the box.
    pub fn contains(&self, v: f64) -> bool {
        v.is_finite() && v >= self.low && v <= self.high
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bijection_round_trips_stays_inside_and_has_the_right_jacobian() {
        let ps = [
            Param { name: "a".into(), unit: "Pa".into(), scale: Scale::Log10, low: 5e3, high: 1e7 },
            Param { name: "b".into(), unit: "".into(), scale: Scale::Linear, low: -3.0, high: 3.0 },
        ];
        for p in &ps {
            for q in [0.001, 0.3, 0.5, 0.97] {
                let v = if p.scale == Scale::Log10 {
                    10f64.powf(p.low.log10() + q * (p.high.log10() - p.low.log10()))
                } else {
                    p.low + q * (p.high - p.low)
                };
                assert!((p.from_u(p.to_u(v)) - v).abs() < 1e-9 * v.abs().max(1.0));
                let h = 1e-6 * v.abs().max(1.0);
                let fd = ((p.to_u(v + h) - p.to_u(v - h)) / (2.0 * h)).abs().ln();
                assert!((fd - p.log_jacobian(v)).abs() < 1e-5, "{} at {v}: {fd} vs {}", p.name, p.log_jacobian(v));
            }
            for u in [-50.0, 50.0, f64::MAX.ln()] {
                assert!(p.contains(p.from_u(u)));
            }
        }
    }
}
