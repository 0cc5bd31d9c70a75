//! First-order optimisers over parameter tensors kept outside the tape (define-by-run: build
//! a fresh tape each step, read the gradients, then step). State is kept per parameter
//! position, so pass the parameters in the same order every step.

use crate::error::{AutodiffError, Result};
use crate::tensor::Tensor;
use crate::Real;

/// Checks every `(parameter, gradient)` pair against each other and against the state kept
/// from earlier steps, before anything is updated: a failed step changes nothing.
fn check_all<T: Real>(
    name: &'static str,
    pairs: &[(&mut Tensor<T>, &Tensor<T>)],
    states: &[&Vec<Tensor<T>>],
) -> Result<()> {
    for (k, (p, g)) in pairs.iter().enumerate() {
        if p.shape() != g.shape() {
            return Err(AutodiffError::shape(
                name,
                &[p.shape(), g.shape()],
                format!("gradient {k} does not match its parameter"),
            ));
        }
        for state in states {
            if let Some(s) = state.get(k) {
                if s.shape() != p.shape() {
                    return Err(AutodiffError::shape(
                        name,
                        &[s.shape(), p.shape()],
                        format!("parameter {k} changed shape between steps"),
                    ));
                }
            }
        }
    }
    Ok(())
}

/// State of parameter `k`, created as zeros on its first step.
fn state_for<'a, T: Real>(
    state: &'a mut Vec<Tensor<T>>,
    k: usize,
    p: &Tensor<T>,
) -> &'a mut Tensor<T> {
    if state.len() == k {
        state.push(Tensor::zeros(p.raw_dim()));
    }
    &mut state[k]
}

/// Stochastic gradient descent with (heavy-ball) momentum: `v = mu v + g; p -= lr v`.
#[derive(Clone, Debug)]
pub struct Sgd<T: Real> {
    /// Learning rate.
    pub lr: T,
    /// Momentum coefficient (0 for plain SGD).
    pub momentum: T,
    velocity: Vec<Tensor<T>>,
}

impl<T: Real> Sgd<T> {
    /// SGD with the given learning rate and momentum.
    pub fn new(lr: T, momentum: T) -> Self {
        Sgd {
            lr,
            momentum,
            velocity: Vec::new(),
        }
    }
    /// One step over `(parameter, gradient)` pairs. On a shape error nothing is updated.
    pub fn step<'a>(
        &mut self,
        params: impl IntoIterator<Item = (&'a mut Tensor<T>, &'a Tensor<T>)>,
    ) -> Result<()> {
        let pairs: Vec<_> = params.into_iter().collect();
        check_all("sgd", &pairs, &[&self.velocity])?;
        for (k, (p, g)) in pairs.into_iter().enumerate() {
            let v = state_for(&mut self.velocity, k, p);
            let (mu, lr) = (self.momentum, self.lr);
            ndarray::Zip::from(&mut *p)
                .and(v)
                .and(g)
                .for_each(|p, v, &g| {
                    *v = mu * *v + g;
                    *p -= lr * *v;
                });
        }
        Ok(())
    }
}

/// Adam (Kingma and Ba 2015, Algorithm 1) with bias correction.
#[derive(Clone, Debug)]
pub struct Adam<T: Real> {
    /// Step size.
    pub lr: T,
    /// First-moment decay.
    pub beta1: T,
    /// Second-moment decay.
    pub beta2: T,
    /// Denominator floor.
    pub eps: T,
    t: i32,
    m: Vec<Tensor<T>>,
    v: Vec<Tensor<T>>,
}

impl<T: Real> Adam<T> {
    /// Adam with the usual defaults (0.9, 0.999, 1e-8).
    pub fn new(lr: T) -> Self {
        Adam {
            lr,
            beta1: T::from_f64c(0.9),
            beta2: T::from_f64c(0.999),
            eps: T::from_f64c(1e-8),
            t: 0,
            m: Vec::new(),
            v: Vec::new(),
        }
    }
    /// Steps taken.
    pub fn steps(&self) -> i32 {
        self.t
    }
    /// One step over `(parameter, gradient)` pairs. On a shape error nothing is updated (not
    /// even the step count).
    pub fn step<'a>(
        &mut self,
        params: impl IntoIterator<Item = (&'a mut Tensor<T>, &'a Tensor<T>)>,
    ) -> Result<()> {
        let pairs: Vec<_> = params.into_iter().collect();
        check_all("adam", &pairs, &[&self.m, &self.v])?;
        self.t += 1;
        let one = T::one();
        let bc1 = one - self.beta1.powi(self.t);
        let bc2 = one - self.beta2.powi(self.t);
        for (k, (p, g)) in pairs.into_iter().enumerate() {
            let (b1, b2, lr, eps) = (self.beta1, self.beta2, self.lr, self.eps);
            state_for(&mut self.m, k, p);
            state_for(&mut self.v, k, p);
            ndarray::Zip::from(&mut *p)
                .and(&mut self.m[k])
                .and(&mut self.v[k])
                .and(g)
                .for_each(|p, m, v, &g| {
                    *m = b1 * *m + (one - b1) * g;
                    *v = b2 * *v + (one - b2) * g * g;
                    *p -= lr * (*m / bc1) / ((*v / bc2).sqrt() + eps);
                });
        }
        Ok(())
    }
}
