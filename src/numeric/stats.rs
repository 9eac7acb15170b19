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
