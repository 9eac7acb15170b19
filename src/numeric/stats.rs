//! Order statistics: the median and robust scales.

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
