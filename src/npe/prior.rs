//! The prior box and its bijection to the unbounded space the flow works in:
//! θ → t (scale) → u = logit((t − lo)/(hi − lo)). Samples mapped back land inside the
//! box by construction; densities carry the log-Jacobian.

use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Scale {
    Linear,
    Log10,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Param {
    pub name: String,
    #[serde(default)]
    pub unit: String,
    pub scale: Scale,
    pub low: f64,
    pub high: f64,
}

impl From<&crate::sim::params::ParamSpec> for Param {
    /// The simulator's parameter as a prior dimension (one definition for every caller).
    fn from(p: &crate::sim::params::ParamSpec) -> Param {
        let scale = match p.scale {
            crate::sim::params::Scale::Log10 => Scale::Log10,
            crate::sim::params::Scale::Linear => Scale::Linear,
        };
        Param { name: p.name.into(), unit: p.unit.into(), scale, low: p.low, high: p.high }
    }
}

impl Param {
    fn t(&self, v: f64) -> f64 {
        match self.scale {
            Scale::Linear => v,
            Scale::Log10 => v.log10(),
        }
    }

    pub fn validate(&self) -> Result<(), String> {
        let ok = self.low.is_finite() && self.high.is_finite() && self.low < self.high;
        if !ok || (self.scale == Scale::Log10 && self.low <= 0.0) {
            return Err(format!(
                "parameter '{}': bounds [{}, {}] are not a valid {:?} box",
                self.name, self.low, self.high, self.scale
            ));
        }
        Ok(())
    }

    /// Position of `v` in the box on the parameter's scale: 0 at `low`, 1 at `high`.
    pub fn position(&self, v: f64) -> f64 {
        (self.t(v) - self.t(self.low)) / (self.t(self.high) - self.t(self.low))
    }

    /// θ → u. Values on or outside the bounds are pulled in by 1e-6 of the box.
    pub fn to_u(&self, v: f64) -> f64 {
        let q = ((self.t(v) - self.t(self.low)) / (self.t(self.high) - self.t(self.low))).clamp(1e-6, 1.0 - 1e-6);
        (q / (1.0 - q)).ln()
    }

    pub fn from_u(&self, u: f64) -> f64 {
        let q = 1.0 / (1.0 + (-u).exp());
        let t = self.t(self.low) + q * (self.t(self.high) - self.t(self.low));
        let v = match self.scale {
            Scale::Linear => t,
            Scale::Log10 => 10f64.powf(t),
        };
        v.clamp(self.low, self.high)
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
        let v = match self.scale {
            Scale::Linear => t,
            Scale::Log10 => 10f64.powf(t),
        };
        v.clamp(self.low, self.high)
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
