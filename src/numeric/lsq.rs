//! Small least squares: a straight line, and Levenberg–Marquardt over a fixed number of parameters.

use nalgebra::{Const, DimMin, SMatrix, SVector};

/// Minimises Σ (y − f(x, p))² over `samples` (x, y) by Levenberg–Marquardt from `p0`; `model(x, p)`
/// gives f and its gradient in p. The damping starts at 1e-3 of the diagonal, falls threefold after
/// a step that lowers the cost and rises fourfold after one that does not; it stops after 100
/// steps, when a step lowers the cost by less than 1e-12 of it, when the damped system is
/// singular, or when the damping passes 1e6.
pub fn levenberg_marquardt<const N: usize>(
    p0: SVector<f64, N>,
    samples: &[(f64, f64)],
    model: impl Fn(f64, &SVector<f64, N>) -> (f64, SVector<f64, N>),
) -> SVector<f64, N>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    let sse = |p: &SVector<f64, N>| -> f64 { samples.iter().map(|&(x, y)| (y - model(x, p).0).powi(2)).sum() };
    let mut p = p0;
    let (mut cost, mut lambda) = (sse(&p), 1e-3);
    for _ in 0..100 {
        let (mut jtj, mut jtr) = (SMatrix::<f64, N, N>::zeros(), SVector::<f64, N>::zeros());
        for &(x, y) in samples {
            let (value, row) = model(x, &p);
            jtj += row * row.transpose();
            jtr += row * (y - value);
        }
        let damped = jtj + SMatrix::<f64, N, N>::from_diagonal(&jtj.diagonal()) * lambda;
        let Some(step) = damped.lu().solve(&jtr) else { break };
        let trial = p + step;
        let trial_cost = sse(&trial);
        if trial_cost < cost {
            let converged = cost - trial_cost <= 1e-12 * cost.max(1e-30);
            (p, cost, lambda) = (trial, trial_cost, (lambda / 3.0).max(1e-9));
            if converged {
                break;
            }
        } else {
            lambda *= 4.0;
            if lambda > 1e6 {
                break;
            }
        }
    }
    p
}

/// Least-squares line through (x_k, y_k): (intercept at x = 0, slope); slope 0 when the x do not
/// spread.
pub fn fit_line(x: &[f64], y: &[f64]) -> (f64, f64) {
    let n = x.len() as f64;
    let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
    let (mut sxx, mut sxy) = (0.0, 0.0);
    for (a, b) in x.iter().zip(y) {
        sxx += (a - mx) * (a - mx);
        sxy += (a - mx) * (b - my);
    }
    let slope = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    (my - slope * mx, slope)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector2;

    #[test]
    fn an_exponential_decay_is_fitted_from_a_distant_start() {
        // y = 2 e^{−0.7 x}, sampled without noise; the fit starts at (1, −0.1).
        let samples: Vec<(f64, f64)> = (0..30).map(|i| 0.2 * i as f64).map(|x| (x, 2.0 * (-0.7 * x).exp())).collect();
        let p = levenberg_marquardt(Vector2::new(1.0, -0.1), &samples, |x, p| {
            let e = (p[1] * x).exp();
            (p[0] * e, Vector2::new(e, p[0] * x * e))
        });
        assert!((p[0] - 2.0).abs() < 1e-9 && (p[1] + 0.7).abs() < 1e-9, "{p:?}");
    }
}
