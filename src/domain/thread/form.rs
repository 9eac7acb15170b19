//! A thread form is the thread's axial profile over one pitch, measured radially from the root
//! cone: 0 at the root, `height_mm` at the crest. Forms are exact analytic curves, so the simulator's
//! truth and the pipeline's analytic profile use the same geometry.

use serde::{Deserialize, Serialize};

/// The share of a crest's or root's own section ([`ThreadForm::flat_half_widths_mm`]) the
/// profile's windows read about its centre: the rest keeps their samples off the flanks.
pub const READ_SHARE_OF_FLAT: f64 = 0.6;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Family {
    /// API 8-round and 10-round: 60° symmetric V with rounded crest and root.
    Round,
    /// API buttress and buttress-derived premium forms: flat crest and root, asymmetric flanks.
    Buttress,
}

impl Family {
    pub fn as_str(self) -> &'static str {
        match self {
            Family::Round => "round",
            Family::Buttress => "buttress",
        }
    }
}

/// The profile over one pitch. Flank angles are measured from the radial direction
/// (perpendicular to the pipe axis), as thread drawings give them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "shape", rename_all = "snake_case")]
pub enum ProfileShape {
    /// Symmetric V (half angle `flank_deg`) whose crest and root are circular arcs tangent to the
    /// flanks; the arcs truncate the sharp V by `crest_truncation_mm` and `root_truncation_mm`.
    Rounded { flank_deg: f64, crest_truncation_mm: f64, root_truncation_mm: f64 },
    /// Flat crest of width `crest_width_mm` centred on the crest line, the load flank on the +z side
    /// (toward the pipe body, the side that bears under tension), the stab flank on the −z side, and a
    /// flat root taking the rest of the pitch.
    Trapezoid { load_flank_deg: f64, stab_flank_deg: f64, crest_width_mm: f64 },
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ThreadForm {
    pub family: Family,
    pub pitch_mm: f64,
    pub height_mm: f64,
    pub height_tolerance_mm: f64,
    /// Taper on diameter (mm per mm); the radius grows by half of it per mm along +z.
    pub taper_on_diameter: f64,
    pub profile: ProfileShape,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FormError {
    #[error("{field} must be a finite number > 0 (got {value})")]
    NotPositive { field: &'static str, value: f64 },
    #[error("{field} must be a finite number ≥ 0 (got {value})")]
    Negative { field: &'static str, value: f64 },
    #[error("{field} = {value} is outside {min}..{max}")]
    OutOfRange { field: &'static str, value: f64, min: f64, max: f64 },
    #[error("the profile does not fit in one pitch: {0}")]
    DoesNotFit(String),
}

fn positive(field: &'static str, value: f64) -> Result<f64, FormError> {
    if value.is_finite() && value > 0.0 { Ok(value) } else { Err(FormError::NotPositive { field, value }) }
}

fn non_negative(field: &'static str, value: f64) -> Result<f64, FormError> {
    if value.is_finite() && value >= 0.0 { Ok(value) } else { Err(FormError::Negative { field, value }) }
}

fn in_range(field: &'static str, value: f64, min: f64, max: f64) -> Result<f64, FormError> {
    if value.is_finite() && value >= min && value <= max {
        Ok(value)
    } else {
        Err(FormError::OutOfRange { field, value, min, max })
    }
}

impl ThreadForm {
    /// API round thread (8-round or 10-round): 60° included angle, crest and root rounded.
    /// `root_truncation_mm` None splits the truncation of the sharp V equally.
    pub fn api_round(
        pitch_mm: f64,
        height_mm: f64,
        height_tolerance_mm: f64,
        taper_on_diameter: f64,
        root_truncation_mm: Option<f64>,
    ) -> Result<Self, FormError> {
        Self::round(pitch_mm, height_mm, height_tolerance_mm, taper_on_diameter, 30.0, root_truncation_mm)
    }

    /// Symmetric V of half angle `flank_deg` with arc crest and root (a custom round form).
    pub fn round(
        pitch_mm: f64,
        height_mm: f64,
        height_tolerance_mm: f64,
        taper_on_diameter: f64,
        flank_deg: f64,
        root_truncation_mm: Option<f64>,
    ) -> Result<Self, FormError> {
        positive("pitch_mm", pitch_mm)?;
        in_range("flank_deg", flank_deg, 1.0, 60.0)?;
        let sharp_v_mm = pitch_mm / (2.0 * flank_deg.to_radians().tan());
        let truncation = sharp_v_mm - height_mm;
        if truncation < 0.0 {
            return Err(FormError::DoesNotFit(format!(
                "height {height_mm} mm exceeds the sharp-V height {sharp_v_mm:.4} mm of pitch {pitch_mm} mm at {flank_deg}° flanks"
            )));
        }
        let root = root_truncation_mm.unwrap_or(truncation / 2.0);
        Self::new(
            Family::Round,
            pitch_mm,
            height_mm,
            height_tolerance_mm,
            taper_on_diameter,
            ProfileShape::Rounded { flank_deg, crest_truncation_mm: truncation - root, root_truncation_mm: root },
        )
    }

    /// Buttress-like form: load flank 3°, stab flank 10°, crest and root flats of equal width.
    pub fn api_buttress(
        pitch_mm: f64,
        height_mm: f64,
        height_tolerance_mm: f64,
        taper_on_diameter: f64,
    ) -> Result<Self, FormError> {
        positive("pitch_mm", pitch_mm)?;
        positive("thread_height_mm", height_mm)?;
        let (load, stab) = (3.0_f64, 10.0_f64);
        let flanks_mm = height_mm * (load.to_radians().tan() + stab.to_radians().tan());
        if flanks_mm >= pitch_mm {
            return Err(FormError::DoesNotFit(format!(
                "flanks of a {height_mm} mm high buttress thread need {flanks_mm:.4} mm, more than the pitch {pitch_mm} mm"
            )));
        }
        let crest_width_mm = (pitch_mm - flanks_mm) / 2.0;
        Self::new(
            Family::Buttress,
            pitch_mm,
            height_mm,
            height_tolerance_mm,
            taper_on_diameter,
            ProfileShape::Trapezoid { load_flank_deg: load, stab_flank_deg: stab, crest_width_mm },
        )
    }

    /// The seed family's default form for a family (round → 60° rounded, buttress → 3°/10°).
    pub fn for_family(
        family: Family,
        pitch_mm: f64,
        height_mm: f64,
        height_tolerance_mm: f64,
        taper_on_diameter: f64,
    ) -> Result<Self, FormError> {
        match family {
            Family::Round => Self::api_round(pitch_mm, height_mm, height_tolerance_mm, taper_on_diameter, None),
            Family::Buttress => Self::api_buttress(pitch_mm, height_mm, height_tolerance_mm, taper_on_diameter),
        }
    }

    /// Validates every dimension and that the profile fits in one pitch.
    pub fn new(
        family: Family,
        pitch_mm: f64,
        height_mm: f64,
        height_tolerance_mm: f64,
        taper_on_diameter: f64,
        profile: ProfileShape,
    ) -> Result<Self, FormError> {
        positive("pitch_mm", pitch_mm)?;
        positive("thread_height_mm", height_mm)?;
        non_negative("height_tolerance_mm", height_tolerance_mm)?;
        in_range("taper_on_diameter", taper_on_diameter, 0.0, 0.5)?;
        if height_tolerance_mm >= height_mm {
            return Err(FormError::DoesNotFit(format!(
                "height_tolerance_mm {height_tolerance_mm} is not smaller than thread_height_mm {height_mm}"
            )));
        }
        match &profile {
            ProfileShape::Rounded { flank_deg, crest_truncation_mm, root_truncation_mm } => {
                in_range("flank_deg", *flank_deg, 1.0, 60.0)?;
                non_negative("crest_truncation_mm", *crest_truncation_mm)?;
                non_negative("root_truncation_mm", *root_truncation_mm)?;
                let sharp_v = pitch_mm / (2.0 * flank_deg.to_radians().tan());
                let sum = height_mm + crest_truncation_mm + root_truncation_mm;
                if (sum - sharp_v).abs() > 1e-6 {
                    return Err(FormError::DoesNotFit(format!(
                        "height {height_mm} mm + truncations {crest_truncation_mm} + {root_truncation_mm} mm \
                         must equal the sharp-V height {sharp_v:.4} mm of pitch {pitch_mm} mm"
                    )));
                }
            }
            ProfileShape::Trapezoid { load_flank_deg, stab_flank_deg, crest_width_mm } => {
                in_range("load_flank_deg", *load_flank_deg, 0.5, 60.0)?;
                in_range("stab_flank_deg", *stab_flank_deg, 0.5, 60.0)?;
                non_negative("crest_width_mm", *crest_width_mm)?;
                let used = crest_width_mm
                    + height_mm * (load_flank_deg.to_radians().tan() + stab_flank_deg.to_radians().tan());
                if used > pitch_mm {
                    return Err(FormError::DoesNotFit(format!(
                        "crest {crest_width_mm} mm and flanks need {used:.4} mm, more than the pitch {pitch_mm} mm"
                    )));
                }
            }
        }
        Ok(Self { family, pitch_mm, height_mm, height_tolerance_mm, taper_on_diameter, profile })
    }

    /// Lowest height that still counts as a full crest.
    pub fn min_full_height_mm(&self) -> f64 {
        self.height_mm - self.height_tolerance_mm
    }

    /// Radial growth of the cone per mm along +z.
    pub fn radius_slope(&self) -> f64 {
        self.taper_on_diameter / 2.0
    }

    /// Height above the root cone at axial offset `x_mm` from the nearest crest centre
    /// (any real x; the profile repeats every pitch).
    pub fn height_at(&self, x_mm: f64) -> f64 {
        self.kernel().height_at(x_mm)
    }

    /// Radii of a rounded form's crest and root arcs (None for a flat-crested form): the arcs are
    /// tangent to the flanks, so a truncation t at flank half angle α gives ρ = t·sin α / (1 − sin α).
    pub fn arc_radii_mm(&self) -> Option<(f64, f64)> {
        match self.profile {
            ProfileShape::Rounded { flank_deg, crest_truncation_mm, root_truncation_mm } => {
                let sin = flank_deg.to_radians().sin();
                let radius = |t: f64| t * sin / (1.0 - sin);
                Some((radius(crest_truncation_mm), radius(root_truncation_mm)))
            }
            ProfileShape::Trapezoid { .. } => None,
        }
    }

    /// The profile with its trigonometry done once, for evaluating many points.
    pub fn kernel(&self) -> ProfileKernel {
        let shape = match self.profile {
            ProfileShape::Rounded { flank_deg, crest_truncation_mm, .. } => {
                let (sin, cos) = flank_deg.to_radians().sin_cos();
                let (rho_crest, rho_root) = self.arc_radii_mm().expect("a rounded form");
                KernelShape::Rounded { cos, cot: cos / sin, rho_crest, rho_root, crest_truncation_mm }
            }
            ProfileShape::Trapezoid { load_flank_deg, stab_flank_deg, crest_width_mm } => KernelShape::Trapezoid {
                half_crest: crest_width_mm / 2.0,
                cot_load: 1.0 / load_flank_deg.to_radians().tan(),
                cot_stab: 1.0 / stab_flank_deg.to_radians().tan(),
            },
        };
        ProfileKernel { pitch: self.pitch_mm, inv_pitch: 1.0 / self.pitch_mm, height: self.height_mm, shape }
    }

    /// Half widths along z of the crest's and the root's own section about their centres: the
    /// flats of a trapezoid, or where a round form's arcs meet their flanks (ρ·cos α either side).
    pub fn flat_half_widths_mm(&self) -> (f64, f64) {
        match self.profile {
            ProfileShape::Trapezoid { load_flank_deg, stab_flank_deg, crest_width_mm } => {
                let flanks = self.height_mm * (load_flank_deg.to_radians().tan() + stab_flank_deg.to_radians().tan());
                (crest_width_mm / 2.0, (self.pitch_mm - crest_width_mm - flanks) / 2.0)
            }
            ProfileShape::Rounded { flank_deg, .. } => {
                let cos = flank_deg.to_radians().cos();
                let (crest, root) = self.arc_radii_mm().expect("a rounded form");
                (crest * cos, root * cos)
            }
        }
    }

    /// Half widths along z of the windows the profile reads about the crest's and the root's
    /// centres: [`READ_SHARE_OF_FLAT`] of [`ThreadForm::flat_half_widths_mm`].
    pub fn window_half_widths_mm(&self) -> (f64, f64) {
        let (crest, root) = self.flat_half_widths_mm();
        (READ_SHARE_OF_FLAT * crest, READ_SHARE_OF_FLAT * root)
    }

    /// Axial offsets, from a crest centre, of the centres of the root before (−z) and after (+z) it.
    pub fn root_centres_mm(&self) -> (f64, f64) {
        let p = self.pitch_mm;
        match self.profile {
            ProfileShape::Rounded { .. } => (-p / 2.0, p / 2.0),
            ProfileShape::Trapezoid { load_flank_deg, stab_flank_deg, crest_width_mm } => {
                let load = self.height_mm * load_flank_deg.to_radians().tan();
                let stab = self.height_mm * stab_flank_deg.to_radians().tan();
                let after = (crest_width_mm / 2.0 + load + p - crest_width_mm / 2.0 - stab) / 2.0;
                (after - p, after)
            }
        }
    }

    /// Height of the pitch line above the root: the middle of the sharp V for round threads, the
    /// middle of the thread height for buttress (where API 5B's pitch diameters E1 and E7 sit).
    pub fn pitch_line_height_mm(&self) -> f64 {
        match self.profile {
            ProfileShape::Rounded { flank_deg, root_truncation_mm, .. } => {
                self.pitch_mm / (4.0 * flank_deg.to_radians().tan()) - root_truncation_mm
            }
            ProfileShape::Trapezoid { .. } => self.height_mm / 2.0,
        }
    }

    /// Largest |d height / d z| of the profile: a Lipschitz bound for ray marching.
    pub fn max_slope(&self) -> f64 {
        match self.profile {
            ProfileShape::Rounded { flank_deg, .. } => 1.0 / flank_deg.to_radians().tan(),
            ProfileShape::Trapezoid { load_flank_deg, stab_flank_deg, .. } => {
                1.0 / load_flank_deg.min(stab_flank_deg).to_radians().tan()
            }
        }
    }
}

/// A [`ThreadForm`]'s profile, ready for fast evaluation (see [`ThreadForm::kernel`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProfileKernel {
    pitch: f64,
    inv_pitch: f64,
    height: f64,
    shape: KernelShape,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum KernelShape {
    Rounded { cos: f64, cot: f64, rho_crest: f64, rho_root: f64, crest_truncation_mm: f64 },
    Trapezoid { half_crest: f64, cot_load: f64, cot_stab: f64 },
}

impl ProfileKernel {
    /// Height above the root cone at axial offset `x_mm` from the nearest crest centre.
    #[inline]
    pub fn height_at(&self, x_mm: f64) -> f64 {
        let (p, h) = (self.pitch, self.height);
        // Nearest multiple of the pitch without a libm call: truncation, corrected below zero.
        let n = x_mm * self.inv_pitch + 0.5;
        let mut k = n as i64 as f64;
        if k > n {
            k -= 1.0;
        }
        let x = x_mm - p * k; // in [−p/2, p/2)
        match self.shape {
            KernelShape::Rounded { cos, cot, rho_crest, rho_root, crest_truncation_mm } => {
                let ax = x.abs();
                if ax <= rho_crest * cos {
                    return h - rho_crest + (rho_crest * rho_crest - ax * ax).sqrt();
                }
                let to_root = p / 2.0 - ax;
                if to_root <= rho_root * cos {
                    return rho_root - (rho_root * rho_root - to_root * to_root).max(0.0).sqrt();
                }
                (h + crest_truncation_mm - ax * cot).clamp(0.0, h)
            }
            KernelShape::Trapezoid { half_crest, cot_load, cot_stab } => {
                if x.abs() <= half_crest {
                    return h;
                }
                let (beyond, cot) = if x > 0.0 { (x - half_crest, cot_load) } else { (-x - half_crest, cot_stab) };
                (h - beyond * cot).max(0.0)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn eight_round() -> ThreadForm {
        ThreadForm::api_round(3.175, 1.80975, 0.0508, 0.0625, Some(0.4318)).unwrap()
    }

    #[test]
    fn round_profile_is_continuous_and_spans_root_to_crest() {
        let form = eight_round();
        assert!((form.height_at(0.0) - form.height_mm).abs() < 1e-12);
        assert!(form.height_at(form.pitch_mm / 2.0).abs() < 1e-12);
        let mut prev = form.height_at(-form.pitch_mm / 2.0);
        for i in 1..=20_000 {
            let x = -form.pitch_mm / 2.0 + form.pitch_mm * i as f64 / 20_000.0;
            let y = form.height_at(x);
            assert!((y - prev).abs() < 1e-3, "jump at x={x}: {prev} → {y}");
            assert!((0.0..=form.height_mm + 1e-12).contains(&y));
            prev = y;
        }
    }

    #[test]
    fn round_flanks_have_the_60_degree_slope() {
        let form = eight_round();
        let (x0, x1) = (0.6, 0.7);
        let slope = (form.height_at(x0) - form.height_at(x1)) / (x1 - x0);
        assert!((slope - 30f64.to_radians().tan().recip()).abs() < 1e-9);
    }

    #[test]
    fn buttress_has_flat_crest_and_root_and_fits_the_pitch() {
        let form = ThreadForm::api_buttress(5.08, 1.575, 0.0508, 0.0625).unwrap();
        let ProfileShape::Trapezoid { crest_width_mm, .. } = form.profile else { panic!() };
        assert_eq!(form.height_at(crest_width_mm / 2.0 - 1e-9), 1.575);
        let (before, after) = form.root_centres_mm();
        assert!((after - before - 5.08).abs() < 1e-12);
        assert_eq!(form.height_at(after), 0.0);
        assert_eq!(form.height_at(before), 0.0);
        // Load flank (+z) is steeper than the stab flank (−z).
        let drop = 0.05;
        assert!(form.height_at(crest_width_mm / 2.0 + drop) < form.height_at(-crest_width_mm / 2.0 - drop));
    }

    #[test]
    fn forms_that_do_not_fit_are_refused_with_the_field() {
        let err = ThreadForm::api_buttress(0.3, 1.575, 0.05, 0.0625).unwrap_err();
        assert!(err.to_string().contains("pitch"), "{err}");
        let err = ThreadForm::api_buttress(-5.0, 1.575, 0.05, 0.0625).unwrap_err();
        assert!(err.to_string().contains("pitch_mm"), "{err}");
        let err = ThreadForm::api_buttress(5.08, f64::NAN, 0.05, 0.0625).unwrap_err();
        assert!(err.to_string().contains("thread_height_mm"), "{err}");
    }
}
