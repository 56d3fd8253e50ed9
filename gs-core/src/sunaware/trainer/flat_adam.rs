//! Adam over one flat vector (a network's weights), the rule and constants of
//! [`crate::optim::Adam`].
//!
//! Invariant: a refused step (mismatched lengths, a non-finite or oversized gradient)
//! changes neither the weights nor the moments nor the step counter.

/// Adam over one flat vector (a network's weights), same rule and constants as [`crate::optim::Adam`].
#[derive(Clone, Debug, PartialEq)]
pub struct FlatAdam {
    pub m: Vec<f32>,
    pub v: Vec<f32>,
    pub step: u64,
}

impl FlatAdam {
    pub fn new(len: usize) -> Self {
        Self {
            m: vec![0.0; len],
            v: vec![0.0; len],
            step: 0,
        }
    }

    /// One Adam step of `params` with `grads` at learning rate `lr` (the step counter
    /// first incremented). `params`, `grads` and both moments must have the same length,
    /// else `OptimError::Shape`; a gradient [`crate::optim::is_usable_gradient`] refuses
    /// gives `OptimError::NonFiniteFlatGradient`; either way nothing changes.
    pub fn apply(
        &mut self,
        params: &mut [f32],
        grads: &[f32],
        lr: f32,
    ) -> Result<(), crate::optim::OptimError> {
        let moment_rows = self.m.len().min(self.v.len());
        if grads.len() != params.len()
            || self.m.len() != params.len()
            || self.v.len() != params.len()
        {
            return Err(crate::optim::OptimError::Shape {
                params_rows: params.len(),
                grads_rows: grads.len(),
                moment_rows,
            });
        }
        if let Some(index) = grads
            .iter()
            .position(|&g| !crate::optim::is_usable_gradient(g))
        {
            return Err(crate::optim::OptimError::NonFiniteFlatGradient { index });
        }
        let (b1, b2, eps) = (0.9f32, 0.999f32, crate::optim::ADAM_EPS);
        self.step += 1;
        let t = self.step as i32;
        let bias1 = 1.0 - (b1 as f64).powi(t);
        let bias2 = 1.0 - (b2 as f64).powi(t);
        let step_size = (lr as f64 / bias1) as f32;
        let inv_sqrt_bias2 = (1.0 / bias2.sqrt()) as f32;
        for i in 0..params.len() {
            self.m[i] = b1 * self.m[i] + (1.0 - b1) * grads[i];
            self.v[i] = b2 * self.v[i] + (1.0 - b2) * grads[i] * grads[i];
            let denom = self.v[i].sqrt() * inv_sqrt_bias2 + eps;
            params[i] -= step_size * self.m[i] / denom;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn network_adam_refuses_oversized_gradients_without_change() {
        let mut adam = FlatAdam::new(3);
        let mut params = vec![0.5f32; 3];
        for g in [1e21f32, f32::NAN] {
            let before = (params.clone(), adam.clone());
            let err = adam.apply(&mut params, &[0.0, g, 1.0], 1e-3);
            assert_eq!(
                err,
                Err(crate::optim::OptimError::NonFiniteFlatGradient { index: 1 })
            );
            assert_eq!((params.clone(), adam.clone()), before);
        }
        adam.apply(&mut params, &[0.0, 1e18, 1.0], 1e-3).unwrap();
        assert!(adam.v.iter().chain(&params).all(|v| v.is_finite()));
        assert_eq!(adam.step, 1);
    }
}
