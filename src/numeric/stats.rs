//! Order statistics (the median and robust scales) and Student's t.

/// The median (the upper one of an even count), reordering `values`; None when empty.
pub fn median(values: &mut [f64]) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    let mid = values.len() / 2;
    Some(*values.select_nth_unstable_by(mid, f64::total_cmp).1)
}

/// Robust scale of deviations from a centre (1.4826 × their median absolute value: σ for normal
/// noise, blind to a minority of outliers).
pub fn robust_scale(deviations: impl Iterator<Item = f64>) -> Option<f64> {
    let mut abs: Vec<f64> = deviations.map(f64::abs).collect();
    median(&mut abs).map(|m| 1.4826 * m)
}

/// Student's t at 97.5% for `dof` degrees of freedom (conservative between the tabulated ones).
pub fn student_t_975(dof: usize) -> f64 {
    const TABLE: [(usize, f64); 14] = [
        (1, 12.706),
        (2, 4.303),
        (3, 3.182),
        (4, 2.776),
        (5, 2.571),
        (6, 2.447),
        (7, 2.365),
        (8, 2.306),
        (9, 2.262),
        (10, 2.228),
        (12, 2.179),
        (15, 2.131),
        (20, 2.086),
        (30, 2.042),
    ];
    if dof > 30 {
        return 1.96;
    }
    TABLE.iter().rev().find(|(d, _)| *d <= dof).map_or(12.706, |(_, t)| *t)
}

/// Student's t with `dof` degrees of freedom at the tail probability the standard normal has at
/// `z` (so `student_t_like_normal(3.0, 9)` is the t of a 99.73% two-sided bound from 10 samples).
/// The Cornish–Fisher expansion in 1/ν to the fourth order (Abramowitz & Stegun 26.7.5): within
/// 0.1% from 9 degrees of freedom for |z| ≤ 3.1, which is all a control chart asks; written here
/// rather than taking a statistics crate for one quantile.
pub fn student_t_like_normal(z: f64, dof: usize) -> f64 {
    let v = dof.max(1) as f64;
    let (z2, z3) = (z * z, z * z * z);
    let (z5, z7, z9) = (z3 * z2, z3 * z2 * z2, z3 * z3 * z3);
    z + (z3 + z) / (4.0 * v)
        + (5.0 * z5 + 16.0 * z3 + 3.0 * z) / (96.0 * v * v)
        + (3.0 * z7 + 19.0 * z5 + 17.0 * z3 - 15.0 * z) / (384.0 * v.powi(3))
        + (79.0 * z9 + 776.0 * z7 + 1482.0 * z5 - 1920.0 * z3 - 945.0 * z) / (92160.0 * v.powi(4))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn t_quantiles_match_the_tables() {
        // (z of the normal at p, dof, t at p from the tables)
        for (z, dof, t) in [
            (1.959964, 10, 2.2281),
            (2.575829, 20, 2.8453),
            (3.090232, 9, 4.2968),
            (3.090232, 30, 3.3852),
            (1.959964, 9, 2.2622),
        ] {
            let got = student_t_like_normal(z, dof);
            assert!((got - t).abs() / t < 1e-3, "t({z}, {dof}) = {got}, tables {t}");
        }
        assert!((student_t_like_normal(3.0, 100_000) - 3.0).abs() < 1e-3);
    }
}
