//! The ring's pose graph: every pair's measured shift, solved per axis for the views' corrections,
//! with a gauge per connected component and Huber reweighting of the pairs.

use crate::numeric::union_find::components;

/// Solves, per axis, min Σ w (c_b − c_a − m)² + Σ_C (Σ_{v ∈ C} c_v)², with Huber reweighting of
/// the pairs. Overlaps fix only differences: each connected component of the pair graph gets its
/// own gauge (its corrections sum to zero), so a view none of whose pairs was measured stays
/// where the encoder put it, and a ring split in two keeps both parts near their encoder poses
/// (one gauge for all would leave the system singular).
pub(super) fn solve_axis(n: usize, pairs: &[(usize, usize, f64)], huber: f64) -> Vec<f64> {
    let mut weights = vec![1.0; pairs.len()];
    let mut c = vec![0.0; n];
    let component = components(n, pairs.iter().map(|&(a, b, _)| (a, b)));
    for _ in 0..5 {
        // The gauge terms.
        let mut lhs =
            nalgebra::DMatrix::<f64>::from_fn(n, n, |i, j| if component[i] == component[j] { 1.0 } else { 0.0 });
        let mut rhs = nalgebra::DVector::<f64>::zeros(n);
        for (&(a, b, m), w) in pairs.iter().zip(&weights) {
            lhs[(a, a)] += w;
            lhs[(b, b)] += w;
            lhs[(a, b)] -= w;
            lhs[(b, a)] -= w;
            rhs[b] += w * m;
            rhs[a] -= w * m;
        }
        let Some(sol) = lhs.lu().solve(&rhs) else { break };
        c = sol.iter().copied().collect();
        for (&(a, b, m), w) in pairs.iter().zip(weights.iter_mut()) {
            *w = huber_weight(c[b] - c[a] - m, huber);
        }
    }
    c
}

/// The Huber kernel's weight for a residual: 1 within `k`, k/|r| beyond it (a pair that disagrees
/// with the rest pulls with a constant force rather than one that grows with its error).
fn huber_weight(residual: f64, k: f64) -> f64 {
    let r = residual.abs();
    if r <= k { 1.0 } else { k / r }
}
