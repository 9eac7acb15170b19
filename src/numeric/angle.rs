//! Angles: fast exact wraps and floors for per-point loops, angles from a reference direction.

use std::f64::consts::{PI, TAU};

/// Angles about the pipe axis measured from a reference angle, for the points of one view.
///
/// A view sees a few degrees either side of its own angle, so a point's direction turned by the
/// reference has a small slope t = v/u, and atan t = t − t³/3 + t⁵/5 − … gives the angle to
/// within an ulp in ten multiply-adds for |t| ≤ 1/8 (the first term left out is below 1e-17 rad);
/// `atan2` and the wrap into (−π, π] cost several times that, once per point of every view in
/// registration and fusion (5% of an inspection). Directions farther out take `atan2`.
#[derive(Clone, Copy, Debug)]
pub struct AngleFrom {
    cos: f64,
    sin: f64,
}

impl AngleFrom {
    pub fn new(reference_rad: f64) -> Self {
        let (sin, cos) = reference_rad.sin_cos();
        Self { cos, sin }
    }

    /// The angle of the direction (x, y) from the reference, in (−π, π].
    #[inline]
    pub fn of(&self, x: f64, y: f64) -> f64 {
        let (u, v) = (x * self.cos + y * self.sin, y * self.cos - x * self.sin);
        if u > 0.0 && v.abs() <= 0.125 * u {
            let t = v / u;
            let t2 = t * t;
            // (atan t − t) / −t³ = 1/3 − t²(1/5 − t²(1/7 − …)), by Horner from 1/19 inwards.
            const INVERSE_ODD: [f64; 9] = [
                1.0 / 19.0,
                1.0 / 17.0,
                1.0 / 15.0,
                1.0 / 13.0,
                1.0 / 11.0,
                1.0 / 9.0,
                1.0 / 7.0,
                1.0 / 5.0,
                1.0 / 3.0,
            ];
            let series = INVERSE_ODD.iter().fold(0.0, |acc, &c| c - t2 * acc);
            t - t * t2 * series
        } else {
            // atan2 gives −π for a direction straight back whose v is −0.
            let angle = v.atan2(u);
            if angle == -std::f64::consts::PI { std::f64::consts::PI } else { angle }
        }
    }
}

/// ⌊x⌋ as an integer, for |x| < 2⁶³. Without SSE4.1 (the baseline x86-64 target) `f64::floor`
/// is a call into libm, once or twice per point of every view in registration and fusion.
#[inline]
pub fn floor_i64(x: f64) -> i64 {
    let t = x as i64;
    t - ((t as f64) > x) as i64
}

/// `theta.rem_euclid(TAU)`, bit for bit, without its `fmod` call where theta is within a turn
/// of [0, 2π) (as a point's angle from its view's angle is): there the remainder is theta itself
/// or theta ∓ 2π, which floating point subtracts exactly (Sterbenz) or rounds the same way.
#[inline]
pub fn wrap_turn(theta: f64) -> f64 {
    use std::f64::consts::TAU;
    if (0.0..TAU).contains(&theta) {
        theta
    } else if theta > -TAU && theta < 0.0 {
        // (At −2π itself the library gives −0.)
        theta + TAU
    } else if (TAU..2.0 * TAU).contains(&theta) {
        theta - TAU
    } else {
        theta.rem_euclid(TAU)
    }
}

/// Wraps an angle difference to (−π, π].
pub fn wrap_pi(a: f64) -> f64 {
    let w = a.rem_euclid(TAU);
    if w > PI { w - TAU } else { w }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_fast_floor_and_turn_wrap_agree_with_the_library_bit_for_bit() {
        use std::f64::consts::TAU;
        let mut x = -3.0 * TAU;
        while x < 3.0 * TAU {
            for v in [x, -x, x.next_up(), x.next_down()] {
                assert_eq!(floor_i64(v), v.floor() as i64, "{v}");
                assert_eq!(wrap_turn(v).to_bits(), v.rem_euclid(TAU).to_bits(), "{v}");
            }
            x += 0.0137;
        }
        for v in [0.0, -0.0, TAU, -TAU, 2.0 * TAU, -1e-300, 1e-300, 12.5, -12.5, -0.5, 4e15 + 0.5] {
            assert_eq!(floor_i64(v), v.floor() as i64, "{v}");
            assert_eq!(wrap_turn(v).to_bits(), v.rem_euclid(TAU).to_bits(), "{v}");
        }
    }

    #[test]
    fn angles_from_a_reference_match_atan2_and_wrap_into_the_half_open_circle() {
        for reference_deg in [0.0, 8.0, 90.0, 179.0, 184.0, 352.0, -30.0] {
            let frame = AngleFrom::new(f64::to_radians(reference_deg));
            // Offsets across the series' range (±7.1°) and beyond it, all round the circle.
            for k in -1800..=1800 {
                let offset_deg = 0.1 * k as f64;
                let theta = f64::to_radians(reference_deg + offset_deg);
                let (x, y) = (57.2 * theta.cos(), 57.2 * theta.sin());
                let want = (y.atan2(x) - f64::to_radians(reference_deg)).rem_euclid(std::f64::consts::TAU);
                let want = if want > std::f64::consts::PI { want - std::f64::consts::TAU } else { want };
                let got = frame.of(x, y);
                assert!(got > -std::f64::consts::PI && got <= std::f64::consts::PI, "{got}");
                // Within a few ulps of the wrapped atan2 (away from ±π, where the wrap may flip).
                if offset_deg.abs() < 179.0 {
                    assert!((got - want).abs() < 4e-15, "{reference_deg}° + {offset_deg}°: {got} vs {want}");
                }
            }
        }
    }
}
