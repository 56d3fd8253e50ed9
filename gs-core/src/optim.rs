//! Adam with per-group learning rates and the 3DGS exponential schedule.
//!
//! The first and second moments are [`ParamSet`]s with the same widths and rows as the
//! parameters, so densification edits them with the same row operations and they stay
//! in step (new rows start at zero moments, pruned rows take theirs with them).
//!
//! Invariants:
//! - one global step counter for the bias correction, as torch's Adam keeps per tensor
//!   (3DGS grows tensors in place and keeps the count);
//! - a step with any unusable gradient (non-finite, or larger in magnitude than
//!   [`MAX_GRADIENT_MAGNITUDE`], whose square would overflow the second moment to +inf) is
//!   refused as a whole (nothing is changed), so NaN/Inf never reach the parameters or the
//!   moments, and every state Adam holds can be checkpointed and read back;
//! - quaternions are NOT renormalised here: the rasterizer normalises them.

use crate::model::{Param, ParamSet};

/// Adam's epsilon in 3DGS (much smaller than torch's default 1e-8).
pub const ADAM_EPS: f32 = 1e-15;

/// Largest gradient magnitude a step accepts: its square (1e36) and every second moment
/// built from such squares stay below `f32::MAX` (3.4e38); sqrt(f32::MAX) ~ 1.8e19 would not.
pub const MAX_GRADIENT_MAGNITUDE: f32 = 1e18;

/// Whether Adam may apply `g`: finite and at most [`MAX_GRADIENT_MAGNITUDE`] in magnitude.
pub fn is_usable_gradient(g: f32) -> bool {
    g.abs() <= MAX_GRADIENT_MAGNITUDE
}

/// Error from an optimiser step.
#[derive(Debug, Clone, PartialEq)]
pub enum OptimError {
    /// Parameters, gradients and moments do not have the same widths and rows.
    Shape {
        params_rows: usize,
        grads_rows: usize,
        moment_rows: usize,
    },
    /// A gradient was NaN, infinite or above [`MAX_GRADIENT_MAGNITUDE`]; the step was not
    /// applied.
    NonFiniteGradient { param: Param, index: usize },
    /// The same for a flat vector (a network's weights).
    NonFiniteFlatGradient { index: usize },
}

impl std::fmt::Display for OptimError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            OptimError::Shape {
                params_rows,
                grads_rows,
                moment_rows,
            } => write!(
                f,
                "shape mismatch: {params_rows} parameter rows, {grads_rows} gradient rows, \
                 {moment_rows} moment rows (or different group widths)"
            ),
            OptimError::NonFiniteGradient { param, index } => write!(
                f,
                "non-finite or oversized gradient in group {} at index {index}; step not \
                 applied",
                param.name()
            ),
            OptimError::NonFiniteFlatGradient { index } => write!(
                f,
                "non-finite or oversized network gradient at index {index}; step not applied"
            ),
        }
    }
}

impl std::error::Error for OptimError {}

/// Learning rate per parameter group, indexed by [`Param::index`].
pub type GroupRates = [f32; Param::COUNT];

/// Adam state: moments beside the parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct Adam {
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
    /// First moment, same shape as the parameters.
    pub m: ParamSet,
    /// Second moment, same shape as the parameters.
    pub v: ParamSet,
    /// Steps taken so far.
    pub step: u64,
}

impl Adam {
    /// Zero moments shaped like `params`; betas 0.9 / 0.999 and eps 1e-15 as in 3DGS.
    pub fn new(params: &ParamSet) -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.999,
            eps: ADAM_EPS,
            m: params.zeros_like(),
            v: params.zeros_like(),
            step: 0,
        }
    }

    /// Index of the first gradient a step would refuse (non-finite or oversized), if any.
    pub fn first_unusable_gradient(grads: &ParamSet) -> Option<(Param, usize)> {
        Param::ALL.iter().find_map(|&p| {
            grads
                .get(p)
                .iter()
                .position(|&g| !is_usable_gradient(g))
                .map(|i| (p, i))
        })
    }

    /// Index of the first NaN or infinite value (of a model's parameters), if any. Large
    /// finite parameters are the model's business; only gradients are bounded.
    pub fn first_non_finite(values: &ParamSet) -> Option<(Param, usize)> {
        Param::ALL.iter().find_map(|&p| {
            values
                .get(p)
                .iter()
                .position(|v| !v.is_finite())
                .map(|i| (p, i))
        })
    }

    /// One Adam step: `params -= lr * m_hat / (sqrt(v_hat) + eps)` per group. A group with
    /// learning rate 0 is left untouched (moments included), like a frozen torch group.
    pub fn step(
        &mut self,
        params: &mut ParamSet,
        grads: &ParamSet,
        rates: &GroupRates,
    ) -> Result<(), OptimError> {
        let same = |a: &ParamSet, b: &ParamSet| a.dims() == b.dims() && a.len() == b.len();
        if !same(params, grads) || !same(params, &self.m) || !same(params, &self.v) {
            return Err(OptimError::Shape {
                params_rows: params.len(),
                grads_rows: grads.len(),
                moment_rows: self.m.len(),
            });
        }
        if let Some((param, index)) = Self::first_unusable_gradient(grads) {
            return Err(OptimError::NonFiniteGradient { param, index });
        }
        self.step += 1;
        let t = self.step as i32;
        let bias1 = 1.0 - (self.beta1 as f64).powi(t);
        let bias2 = 1.0 - (self.beta2 as f64).powi(t);
        let (b1, b2, eps) = (self.beta1, self.beta2, self.eps);
        for p in Param::ALL {
            let lr = rates[p.index()];
            if lr == 0.0 || params.dim(p) == 0 {
                continue;
            }
            // torch's formulation: step = lr / bias1, denom = sqrt(v) / sqrt(bias2) + eps.
            let step_size = (lr as f64 / bias1) as f32;
            let inv_sqrt_bias2 = (1.0 / bias2.sqrt()) as f32;
            let g = grads.get(p);
            let m = self.m.get_mut(p);
            let v = self.v.get_mut(p);
            let x = params.get_mut(p);
            for i in 0..x.len() {
                m[i] = b1 * m[i] + (1.0 - b1) * g[i];
                v[i] = b2 * v[i] + (1.0 - b2) * g[i] * g[i];
                let denom = v[i].sqrt() * inv_sqrt_bias2 + eps;
                x[i] -= step_size * m[i] / denom;
            }
        }
        Ok(())
    }

    /// Zeroes both moments of one group (3DGS does this for opacity after a reset).
    pub fn reset_group(&mut self, p: Param) {
        self.m.get_mut(p).fill(0.0);
        self.v.get_mut(p).fill(0.0);
    }
}

/// The 3DGS `get_expon_lr_func`: log-linear from `lr_init` to `lr_final` over `max_steps`,
/// optionally scaled by a delay ramp `delay_mult + (1 - delay_mult) sin(pi/2 t/delay)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExponentialSchedule {
    pub lr_init: f32,
    pub lr_final: f32,
    pub delay_steps: u64,
    pub delay_mult: f32,
    pub max_steps: u64,
}

impl ExponentialSchedule {
    /// The 3DGS position schedule: 1.6e-4 -> 1.6e-6 times the scene extent.
    pub fn position(scene_extent: f32, max_steps: u64) -> Self {
        Self {
            lr_init: 1.6e-4 * scene_extent,
            lr_final: 1.6e-6 * scene_extent,
            delay_steps: 0,
            delay_mult: 0.01,
            max_steps,
        }
    }

    /// Learning rate at `step` (0-based); 0 when either end is not positive (a frozen
    /// group; 3DGS returns 0 when both are).
    pub fn at(&self, step: u64) -> f32 {
        if self.lr_init <= 0.0 || self.lr_final <= 0.0 {
            return 0.0;
        }
        let delay = if self.delay_steps > 0 {
            let r = (step as f64 / self.delay_steps as f64).clamp(0.0, 1.0);
            self.delay_mult as f64
                + (1.0 - self.delay_mult as f64) * (0.5 * std::f64::consts::PI * r).sin()
        } else {
            1.0
        };
        let t = if self.max_steps == 0 {
            1.0
        } else {
            (step as f64 / self.max_steps as f64).clamp(0.0, 1.0)
        };
        let log_lerp =
            ((self.lr_init as f64).ln() * (1.0 - t) + (self.lr_final as f64).ln() * t).exp();
        (delay * log_lerp) as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{GaussianModel, ModelLayout};

    fn model(n: usize) -> ParamSet {
        let mut m = GaussianModel::new(ModelLayout::sh(1)).unwrap();
        m.params.push_zeros(n);
        m.params
    }

    /// Reference Adam written out in f64 for one scalar, torch's update rule.
    #[test]
    fn step_matches_reference_adam() {
        let mut params = model(2);
        for (i, v) in params.get_mut(Param::Mean).iter_mut().enumerate() {
            *v = i as f32 * 0.1;
        }
        let mut adam = Adam::new(&params);
        adam.eps = 1e-8;
        let mut rates = [0.0f32; Param::COUNT];
        rates[Param::Mean.index()] = 0.01;
        let (mut x, mut m, mut v) = (0.3f64, 0.0f64, 0.0f64);
        for t in 1..=5 {
            let g = 0.5 * x - 0.2 * t as f64;
            let mut grads = params.zeros_like();
            grads.get_mut(Param::Mean)[3] = g as f32;
            adam.step(&mut params, &grads, &rates).unwrap();
            m = 0.9 * m + 0.1 * g;
            v = 0.999 * v + 0.001 * g * g;
            let mhat = m / (1.0 - 0.9f64.powi(t));
            let vhat = v / (1.0 - 0.999f64.powi(t));
            x -= 0.01 * mhat / (vhat.sqrt() + 1e-8);
            assert!((params.get(Param::Mean)[3] as f64 - x).abs() < 1e-6);
        }
        // Zero gradient and zero moments: no motion; zero-rate groups untouched.
        assert_eq!(params.get(Param::Mean)[0], 0.0);
        assert!(params.get(Param::ShDc).iter().all(|&v| v == 0.0));
        assert_eq!(adam.step, 5);
    }

    /// With a constant gradient the first Adam step moves each value by exactly lr
    /// (sign of the gradient), whatever the gradient's magnitude.
    #[test]
    fn first_step_moves_by_the_group_rate() {
        let mut params = model(3);
        let mut adam = Adam::new(&params);
        let mut grads = params.zeros_like();
        grads
            .get_mut(Param::OpacityLogit)
            .copy_from_slice(&[1e-6, -3.0, 250.0]);
        grads.get_mut(Param::LogScale)[4] = 2.0;
        let mut rates = [0.0f32; Param::COUNT];
        rates[Param::OpacityLogit.index()] = 0.025;
        rates[Param::LogScale.index()] = 5e-3;
        adam.step(&mut params, &grads, &rates).unwrap();
        let o = params.get(Param::OpacityLogit);
        assert!((o[0] + 0.025).abs() < 1e-6);
        assert!((o[1] - 0.025).abs() < 1e-6);
        assert!((o[2] + 0.025).abs() < 1e-6);
        assert!((params.get(Param::LogScale)[4] + 5e-3).abs() < 1e-7);
    }

    #[test]
    fn non_finite_or_misshapen_gradients_are_refused_without_change() {
        let mut params = model(2);
        let mut adam = Adam::new(&params);
        let mut grads = params.zeros_like();
        grads.get_mut(Param::ShDc)[0] = 1.0;
        grads.get_mut(Param::Rotation)[5] = f32::NAN;
        let before = (params.clone(), adam.clone());
        let err = adam.step(&mut params, &grads, &[1.0; Param::COUNT]);
        assert_eq!(
            err,
            Err(OptimError::NonFiniteGradient {
                param: Param::Rotation,
                index: 5
            })
        );
        assert_eq!((params.clone(), adam.clone()), before);
        let short = model(1).zeros_like();
        assert!(matches!(
            adam.step(&mut params, &short, &[1.0; Param::COUNT]),
            Err(OptimError::Shape { .. })
        ));
    }

    /// A finite gradient whose square overflows f32 used to make the second moment +inf
    /// (then every later step divides by inf and the moment cannot be checkpointed).
    #[test]
    fn oversized_gradients_are_refused_and_moments_stay_finite() {
        let mut params = model(1);
        let mut adam = Adam::new(&params);
        let rates = [1e-3; Param::COUNT];
        for g in [2e19f32, 1e21, -f32::MAX] {
            let mut grads = params.zeros_like();
            grads.get_mut(Param::Mean)[1] = g;
            let before = (params.clone(), adam.clone());
            assert_eq!(
                adam.step(&mut params, &grads, &rates),
                Err(OptimError::NonFiniteGradient {
                    param: Param::Mean,
                    index: 1
                }),
                "gradient {g}"
            );
            assert_eq!((params.clone(), adam.clone()), before, "gradient {g}");
        }
        // The largest accepted gradient, applied many times, keeps everything finite.
        let mut grads = params.zeros_like();
        grads.get_mut(Param::Mean)[1] = -MAX_GRADIENT_MAGNITUDE;
        for _ in 0..10_000 {
            adam.step(&mut params, &grads, &rates).unwrap();
        }
        assert!(Param::ALL
            .iter()
            .all(|&p| adam.v.get(p).iter().all(|v| v.is_finite())));
        assert!(Param::ALL
            .iter()
            .all(|&p| params.get(p).iter().all(|v| v.is_finite())));
        assert!(!is_usable_gradient(f32::NAN) && !is_usable_gradient(f32::INFINITY));
    }

    #[test]
    fn position_schedule_is_log_linear() {
        let s = ExponentialSchedule::position(2.0, 30_000);
        assert!((s.at(0) - 3.2e-4).abs() < 1e-10);
        assert!((s.at(30_000) - 3.2e-6).abs() < 1e-12);
        assert!((s.at(60_000) - 3.2e-6).abs() < 1e-12);
        // Halfway is the geometric mean.
        assert!((s.at(15_000) - 3.2e-5).abs() < 1e-10);
        let delayed = ExponentialSchedule {
            delay_steps: 100,
            ..s
        };
        assert!((delayed.at(0) - 0.01 * 3.2e-4).abs() < 1e-10);
        assert!((delayed.at(100) - s.at(100)).abs() < 1e-12);
    }
}
