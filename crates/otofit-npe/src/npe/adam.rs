//! Adam on the host over the flow's weights as [`Weights`] holds them, computed as burn's
//! `AdamConfig` computes it with per-tensor norm clipping and L2 weight decay. A training
//! keeps its weights and moments off burn for a whole epoch: burn's step, a dozen tensor
//! ops per parameter tensor, was the largest serial part of a batch once the gradients ran
//! on many cores (docs/results/scaling.md). Tensors are stepped on the thread pool, each by
//! one thread, so the bits do not depend on the threads.

use crate::flow::gradient::{Gradient, Weights};
use rayon::prelude::*;

const BETA_1: f32 = 0.9;
const BETA_2: f32 = 0.999;

/// What a checkpoint's optimizer state starts with.
const MAGIC: &[u8; 8] = b"OTADAM01";

/// Adam's settings and moments.
#[derive(Clone, Debug, PartialEq)]
pub struct Adam {
    eps: f32,
    /// Each tensor's gradient scaled down to this norm when above it.
    clip: Option<f32>,
    /// L2 penalty added to the gradient.
    decay: Option<f32>,
    /// Steps taken.
    time: i32,
    /// First and second moments per tensor (empty before the first step).
    m: Vec<Vec<f32>>,
    v: Vec<Vec<f32>>,
}

/// Optimizer state that does not fit the flow it is read for.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("optimizer state: {0}")]
pub struct AdamStateError(&'static str);

impl Adam {
    /// Adam with ε `eps`, clipping each tensor's gradient to norm `clip` and adding
    /// `decay` × the weights to it, where given.
    pub fn new(eps: f32, clip: Option<f32>, decay: Option<f32>) -> Adam {
        Adam { eps, clip, decay, time: 0, m: vec![], v: vec![] }
    }

    /// One step of rate `lr` along `grad` (the weights' order).
    pub fn step(&mut self, lr: f64, weights: &mut Weights, grad: Gradient) {
        let values = weights.values_mut();
        if self.m.is_empty() {
            self.m = values.iter().map(|v| vec![0.0; v.len()]).collect();
            self.v = self.m.clone();
        }
        self.time += 1;
        let bc2 = (1.0 - BETA_2.powi(self.time)).sqrt();
        let factor = bc2 / (1.0 - BETA_1.powi(self.time));
        let (eps, lr) = (self.eps * bc2, lr as f32);
        let (clip, decay) = (self.clip, self.decay);
        values.par_iter_mut().zip(grad.0).zip(self.m.par_iter_mut().zip(self.v.par_iter_mut())).for_each(
            |((w, mut g), (m, v))| {
                if let Some(max) = clip {
                    let norm = g.iter().map(|g| g * g).sum::<f32>().sqrt();
                    let c = (max / (norm + f32::MIN_POSITIVE)).min(1.0);
                    g.iter_mut().for_each(|g| *g *= c);
                }
                if let Some(p) = decay {
                    g.iter_mut().zip(w.iter()).for_each(|(g, w)| *g += p * w);
                }
                for (((w, g), m), v) in w.iter_mut().zip(&g).zip(m.iter_mut()).zip(v.iter_mut()) {
                    *m = BETA_1 * *m + (1.0 - BETA_1) * g;
                    *v = BETA_2 * *v + (1.0 - BETA_2) * g * g;
                    *w -= lr * (*m * factor / (v.sqrt() + eps));
                }
            },
        );
        weights.refresh();
    }

    /// The steps taken and the moments, for a checkpoint (the settings come from the
    /// training's own).
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = MAGIC.to_vec();
        out.extend(self.time.to_le_bytes());
        out.extend((self.m.len() as u64).to_le_bytes());
        for (m, v) in self.m.iter().zip(&self.v) {
            out.extend((m.len() as u64).to_le_bytes());
            for x in m.iter().chain(v) {
                out.extend(x.to_le_bytes());
            }
        }
        out
    }

    /// These settings with the state of [`Adam::to_bytes`], checked against the tensors of
    /// `weights`.
    pub fn with_state(self, bytes: &[u8], weights: &Weights) -> Result<Adam, AdamStateError> {
        let mut rest = bytes.strip_prefix(MAGIC).ok_or(AdamStateError("not otofit's Adam state"))?;
        let mut take = |n: usize| -> Result<&[u8], AdamStateError> {
            let (head, tail) = rest.split_at_checked(n).ok_or(AdamStateError("cut short"))?;
            rest = tail;
            Ok(head)
        };
        let time = i32::from_le_bytes(take(4)?.try_into().expect("4 bytes"));
        let count = u64::from_le_bytes(take(8)?.try_into().expect("8 bytes")) as usize;
        let sizes: Vec<usize> = weights.sizes().collect();
        if time < 0 || (count != sizes.len() && !(count == 0 && time == 0)) {
            return Err(AdamStateError("another flow's tensors"));
        }
        let (mut m, mut v) = (vec![], vec![]);
        for &size in sizes.iter().take(count) {
            let len = u64::from_le_bytes(take(8)?.try_into().expect("8 bytes")) as usize;
            if len != size {
                return Err(AdamStateError("another flow's tensors"));
            }
            let floats = |b: &[u8]| -> Vec<f32> {
                b.chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes"))).collect()
            };
            m.push(floats(take(4 * len)?));
            v.push(floats(take(4 * len)?));
        }
        if !rest.is_empty() {
            return Err(AdamStateError("trailing bytes"));
        }
        Ok(Adam { time, m, v, ..self })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::flow::{Flow, FlowConfig};
    use burn::grad_clipping::GradientClippingConfig;
    use burn::optim::decay::WeightDecayConfig;
    use burn::optim::{AdamConfig, GradientsParams};
    use burn::prelude::*;

    /// Six steps of this Adam take a flow's weights where burn's Adam takes them, given the
    /// same gradients, with and without clipping and weight decay (the clip bites: the
    /// gradients are scaled up 50×); its state survives a round trip through bytes, and
    /// another flow's state is refused.
    #[test]
    fn host_adam_steps_as_burns_adam() {
        let cfg = FlowConfig { blocks: 1, lu: true, ..FlowConfig::new(3, 4, true) };
        for (clip, decay) in [(None, None), (Some(1.0f32), Some(1e-2f32))] {
            let dev = Device::flex().autodiff();
            let mut flow = Flow::seeded(&cfg, &dev, Some(4));
            let mut host = Weights::of(&flow, &cfg);
            let mut burn_adam = AdamConfig::new()
                .with_epsilon(1e-8)
                .with_grad_clipping(clip.map(GradientClippingConfig::Norm))
                .with_weight_decay(decay.map(WeightDecayConfig::new))
                .init();
            let mut adam = Adam::new(1e-8, clip, decay);
            let n = 30;
            for step in 0..6 {
                let v: Vec<f32> = (0..n * 3).map(|i| (((i + step) * 7919 % 97) as f32 / 97.0 - 0.5) * 4.0).collect();
                let x: Vec<f32> = (0..n * 4).map(|i| (((i + step) * 104_729 % 89) as f32 / 89.0 - 0.5) * 2.0).collect();
                let (_, g) = crate::flow::gradient::loss_and_gradient(&host, &v, &x, n);
                let g = Gradient(g.0.into_iter().map(|t| t.into_iter().map(|e| 50.0 * e).collect()).collect());
                let grads: GradientsParams = g.clone().into_params(&host, &Device::flex());
                flow = burn_adam.step(1e-3, flow, grads);
                adam.step(1e-3, &mut host, g);
                let reference = Weights::of(&flow, &cfg);
                for (t, (a, b)) in host.values_mut().iter().zip(reference.values()).enumerate() {
                    let scale = b.iter().fold(1e-3f32, |m, v| m.max(v.abs()));
                    for (e, (a, b)) in a.iter().zip(b).enumerate() {
                        assert!((a - b).abs() <= 2e-5 * scale, "step {step}, tensor {t}, element {e}: {a} vs {b}");
                    }
                }
            }
            let back = Adam::new(1e-8, clip, decay).with_state(&adam.to_bytes(), &host).unwrap();
            assert_eq!(back, adam);
            let other =
                Weights::of(&Flow::seeded(&FlowConfig::new(2, 4, true), &dev, Some(1)), &FlowConfig::new(2, 4, true));
            assert!(Adam::new(1e-8, clip, decay).with_state(&adam.to_bytes(), &other).is_err());
            let cut = adam.to_bytes();
            assert!(Adam::new(1e-8, clip, decay).with_state(&cut[..cut.len() - 1], &host).is_err());
        }
    }
}
