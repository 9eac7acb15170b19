//! JSON with its numbers rounded to their resolution: `0.01016`, not `0.010159999999999999`.
//!
//! A number's unit is read from the nearest enclosing key that names one (`height_mm.values[3]` is
//! in mm), and each unit has a resolution well below what the instrument resolves: 0.1 µm for
//! lengths in mm, 0.01 µm in µm, 0.0001° for angles, 1 ms for times; numbers without a unit
//! (shares, grey levels, ratios) keep 6 significant digits. Integers are left as they are.

use serde::Serialize;
use serde_json::Value;

/// Decimal places kept for a unit suffix; None: no unit, significant digits apply.
fn decimals_for(key: &str) -> Option<i32> {
    const UNITS: [(&str, i32); 8] =
        [("_mm", 4), ("_um", 2), ("_deg", 4), ("seconds", 3), ("_s", 3), ("_ms", 1), ("_mb", 1), ("_percent", 2)];
    UNITS.iter().find(|(suffix, _)| key.ends_with(suffix)).map(|&(_, d)| d)
}

const SIGNIFICANT_DIGITS: i32 = 6;

/// `x` to `decimals` places (negative: to tens, hundreds, …). Dividing an integral double by a
/// power of ten gives the double nearest the decimal, which prints as that decimal.
fn round_to(x: f64, decimals: i32) -> f64 {
    if decimals >= 0 {
        let scale = 10f64.powi(decimals);
        let scaled = (x * scale).round();
        if scaled.abs() >= 2f64.powi(53) { x } else { scaled / scale }
    } else {
        let scale = 10f64.powi(-decimals);
        (x / scale).round() * scale
    }
}

fn round_number(x: f64, unit_decimals: Option<i32>) -> f64 {
    if !x.is_finite() || x == 0.0 {
        return x;
    }
    let decimals = unit_decimals.unwrap_or_else(|| SIGNIFICANT_DIGITS - 1 - x.abs().log10().floor() as i32);
    // A value that rounds to zero is 0, not -0.
    round_to(x, decimals) + 0.0
}

/// Rounds every non-integral number of `value` in place (see the module's note).
pub fn round_numbers(value: &mut Value) {
    walk(value, None);
}

fn walk(value: &mut Value, unit: Option<i32>) {
    match value {
        Value::Number(n) if n.is_f64() => {
            let x = n.as_f64().expect("an f64 number");
            if let Some(rounded) = serde_json::Number::from_f64(round_number(x, unit)) {
                *n = rounded;
            }
        }
        Value::Array(items) => items.iter_mut().for_each(|v| walk(v, unit)),
        Value::Object(map) => {
            for (key, v) in map.iter_mut() {
                walk(v, decimals_for(key).or(unit));
            }
        }
        _ => {}
    }
}

/// `value` as JSON, numbers rounded to their resolution.
pub fn to_vec<T: Serialize>(value: &T) -> serde_json::Result<Vec<u8>> {
    let mut v = serde_json::to_value(value)?;
    round_numbers(&mut v);
    serde_json::to_vec(&v)
}

/// `value` as indented JSON, numbers rounded to their resolution.
pub fn to_vec_pretty<T: Serialize>(value: &T) -> serde_json::Result<Vec<u8>> {
    let mut v = serde_json::to_value(value)?;
    round_numbers(&mut v);
    serde_json::to_vec_pretty(&v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn numbers_are_rounded_to_the_resolution_of_their_unit() {
        let mut v = json!({
            "height_mm": {"values": [0.010159999999999999, null, 1.57480000000001], "angles_deg": [0.5, 359.49999999999]},
            "scatter_um": 3.14159265,
            "timings": [{"stage": "depth", "seconds": 0.12345678}],
            "depth_coverage": 0.876543219,
            "map_coverage": 123456.789,
            "views": 45,
            "tiny": 1.23456789e-9,
        });
        round_numbers(&mut v);
        assert_eq!(
            v.to_string(),
            r#"{"depth_coverage":0.876543,"height_mm":{"angles_deg":[0.5,359.5],"values":[0.0102,null,1.5748]},"map_coverage":123457.0,"scatter_um":3.14,"timings":[{"seconds":0.123,"stage":"depth"}],"tiny":1.23457e-9,"views":45}"#
        );
    }

    #[test]
    fn rounding_keeps_what_the_unit_resolves_and_prints_short() {
        for (x, decimals, printed) in [(0.010159999999999999, 5, "0.01016"), (1234.5, -2, "1200.0")] {
            assert_eq!(serde_json::to_string(&round_to(x, decimals)).unwrap(), printed, "{x}");
        }
        assert_eq!(serde_json::to_string(&round_number(-0.00004, Some(4))).unwrap(), "0.0");
        // Every 4-decimal value prints as at most 4 decimals.
        for k in -20_000..20_000 {
            let x = k as f64 / 10_000.0 + 1e-12;
            let s = serde_json::to_string(&round_to(x, 4)).unwrap();
            let decimals = s.split('.').nth(1).map_or(0, str::len);
            assert!(decimals <= 4, "{x} printed {s}");
        }
    }
}
