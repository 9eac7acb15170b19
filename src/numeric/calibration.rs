//! Whether a share measured on correlated values (an uncertainty's coverage over a helix of bins)
//! says anything: how many independent values the correlated sequences hold, and the binomial
//! interval of a share measured on that many. Written out rather than taken from `statrs`: two
//! small functions for the benchmark do not warrant a statistics crate in the build.

/// The effective number of independent values in `sequences` (each a run of equally spaced
/// slots, None where nothing was measured): n / (1 + 2 Σ ρ_lag), where ρ_lag is the lag
/// autocorrelation pooled over the sequences (second moments about zero, so that a bias shared
/// along a sequence counts as correlation, not as a mean to remove), summed from lag 1 up to the
/// first lag where it falls to `cutoff` or below or fewer than 10 pairs are left. Values in
/// different sequences are taken as independent, which overstates the count where sequences share
/// an error. Between 1 and n; None without a value.
pub fn effective_count(sequences: &[Vec<Option<f64>>], cutoff: f64) -> Option<f64> {
    let values = || sequences.iter().flat_map(|s| s.iter().flatten());
    let n = values().count();
    if n == 0 {
        return None;
    }
    let second_moment = values().map(|v| v * v).sum::<f64>() / n as f64;
    if second_moment <= 0.0 {
        return Some(n as f64);
    }
    let longest = sequences.iter().map(Vec::len).max().unwrap_or(0);
    let mut rho_sum = 0.0;
    for lag in 1..longest {
        let (mut sum, mut pairs) = (0.0, 0usize);
        for s in sequences {
            for (a, b) in s.iter().zip(s.iter().skip(lag)) {
                if let (Some(a), Some(b)) = (a, b) {
                    sum += a * b;
                    pairs += 1;
                }
            }
        }
        if pairs < 10 {
            break;
        }
        let rho = sum / pairs as f64 / second_moment;
        if rho <= cutoff {
            break;
        }
        rho_sum += rho;
    }
    Some((n as f64 / (1.0 + 2.0 * rho_sum)).clamp(1.0, n as f64))
}

/// The two-sided Clopper–Pearson interval at `confidence` of a share measured as `successes` of
/// `trials`: the proportions at which seeing `successes` or more (for the lower bound), or that
/// many or fewer (for the upper), has probability (1 − confidence) / 2. (0, 1) without a trial.
pub fn share_interval(successes: usize, trials: usize, confidence: f64) -> (f64, f64) {
    if trials == 0 {
        return (0.0, 1.0);
    }
    let successes = successes.min(trials);
    let tail = 0.5 * (1.0 - confidence);
    let ln_fact: Vec<f64> = std::iter::once(0.0)
        .chain((1..=trials).scan(0.0, |acc, i| {
            *acc += (i as f64).ln();
            Some(*acc)
        }))
        .collect();
    // P(X <= k) for X ~ Binomial(trials, p), summed in log space (p^n underflows for long runs).
    let cdf = |k: usize, p: f64| -> f64 {
        let (ln_p, ln_q) = (p.ln(), (1.0 - p).ln());
        let terms: Vec<f64> = (0..=k)
            .map(|i| {
                let ln_c = ln_fact[trials] - ln_fact[i] - ln_fact[trials - i];
                let a = if i == 0 { 0.0 } else { i as f64 * ln_p };
                let b = if i == trials { 0.0 } else { (trials - i) as f64 * ln_q };
                ln_c + a + b
            })
            .collect();
        let top = terms.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        if top == f64::NEG_INFINITY {
            return 0.0;
        }
        (top.exp() * terms.iter().map(|t| (t - top).exp()).sum::<f64>()).min(1.0)
    };
    // Bisection on p for a tail that falls as p rises (`falling`) or rises.
    let solve = |tail_at: &dyn Fn(f64) -> f64| {
        let (mut lo, mut hi) = (0.0f64, 1.0f64);
        for _ in 0..60 {
            let mid = 0.5 * (lo + hi);
            if tail_at(mid) > tail {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        0.5 * (lo + hi)
    };
    let lower = if successes == 0 { 0.0 } else { solve(&|p| 1.0 - cdf(successes - 1, p)) };
    let upper = if successes == trials { 1.0 } else { 1.0 - solve(&|q| cdf(successes, 1.0 - q)) };
    (lower, upper)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn independent_values_count_whole_and_a_shared_bias_counts_as_a_few() {
        // Alternating signs: no positive correlation at lag 1, every value counts.
        let alternating: Vec<Option<f64>> = (0..200).map(|i| Some(if i % 2 == 0 { 1.0 } else { -1.0 })).collect();
        assert_eq!(effective_count(&[alternating], 0.05), Some(200.0));
        // A constant error along each of four sequences of 100: at most one draw each, whatever
        // their length (400 / (1 + 2 · 99) = 2.0 here).
        let biased: Vec<Vec<Option<f64>>> = (0..4).map(|_| vec![Some(0.3); 100]).collect();
        let n = effective_count(&biased, 0.05).unwrap();
        assert!((1.0..=4.0).contains(&n), "{n}");
        // Gaps neither pair up nor count.
        assert_eq!(effective_count(&[vec![None, None]], 0.05), None);
    }

    #[test]
    fn smooth_errors_count_as_fewer_values_than_bins() {
        // A slow wave along 360 bins (period 60): neighbours agree, a few dozen independent draws.
        let wave: Vec<Option<f64>> = (0..360).map(|i| Some((i as f64 * std::f64::consts::TAU / 60.0).sin())).collect();
        let n = effective_count(&[wave], 0.05).unwrap();
        assert!(n > 5.0 && n < 60.0, "{n}");
    }

    #[test]
    fn the_interval_matches_clopper_pearson_and_its_edges() {
        // 95 of 100: R's binom.test gives 0.8872 to 0.9836.
        let (lo, hi) = share_interval(95, 100, 0.95);
        assert!((lo - 0.8872).abs() < 5e-4 && (hi - 0.9836).abs() < 5e-4, "{lo} {hi}");
        // All of 20: the upper bound is 1 and the lower solves p^20 = 0.025.
        let (lo, hi) = share_interval(20, 20, 0.95);
        assert!((lo - 0.025f64.powf(1.0 / 20.0)).abs() < 1e-6 && hi == 1.0, "{lo} {hi}");
        // None of 10, and a long run that would underflow p^n.
        assert_eq!(share_interval(0, 10, 0.95).0, 0.0);
        let (lo, hi) = share_interval(2400, 2500, 0.95);
        assert!(lo > 0.95 && lo < 0.96 && hi > 0.96 && hi < 0.97, "{lo} {hi}");
        assert_eq!(share_interval(3, 0, 0.95), (0.0, 1.0));
    }
}
