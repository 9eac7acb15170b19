//! The camera model of bundle v1: a thin lens (or telecentric lens) looking radially at the pipe,
//! moved along its optical axis through the focal stack with a fixed sensor distance.

use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Projection {
    Perspective,
    Telecentric,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Optics {
    /// `perspective` (thin lens) or `telecentric` (then `magnification` is required and `f_number`
    /// is the image-side working f-number).
    pub projection: Projection,
    /// Required for a perspective (thin-lens) projection; a telecentric one is described by its
    /// magnification, and may leave it out or null.
    #[serde(default)]
    pub focal_length_mm: Option<f64>,
    pub f_number: f64,
    /// The object distance in focus at frame offset 0, mm.
    pub focus_distance_mm: f64,
    /// The sensor's pixel pitch, µm.
    pub pixel_pitch_um: f64,
    /// `[cx, cy]`, pixels; null: the image centre.
    #[serde(default)]
    pub principal_point_px: Option<[f64; 2]>,
    #[serde(default)]
    pub magnification: Option<f64>,
}

/// A camera ray in the camera frame at offset 0: `origin + t · direction`, with direction.z = 1, so
/// `t` is the depth along the optical axis from that frame's lens centre.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub origin: Point3<f64>,
    pub direction: Vector3<f64>,
}

impl Ray {
    pub fn at(&self, depth_mm: f64) -> Point3<f64> {
        self.origin + self.direction * depth_mm
    }
}

/// The smallest f-number a manifest may declare (see [`Optics::validate`]).
pub const MIN_F_NUMBER: f64 = 0.1;

impl Optics {
    /// Checks every field; the error names the field relative to `optics`.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        // Each value finite, positive, and within bounds far outside any camera (so that a typo or
        // 1e308 is named here rather than overflowing a stage). f/0.5 is a lens in air's limit, but
        // the simulator's random stations reach f/0.28 for a shallow depth of field at coarse
        // pixels (16 of the 82 station-suite stations), and their figures stay comparable only if
        // they are read: the bound is f/0.1.
        let finite_positive = |name: &'static str, v: f64| {
            let max = match name {
                "f_number" => 256.0,
                "focal_length_mm" => 10_000.0,
                "focus_distance_mm" => 100_000.0,
                "pixel_pitch_um" => 1_000.0,
                _ => 10_000.0,
            };
            let min = if name == "f_number" { MIN_F_NUMBER } else { 0.0 };
            if !(v.is_finite() && v > 0.0) {
                Err((name, format!("must be a finite number > 0, got {v}")))
            } else if v < min || v > max {
                Err((name, format!("{v} is outside [{min}, {max}]")))
            } else {
                Ok(())
            }
        };
        match (self.projection, self.focal_length_mm) {
            (Projection::Perspective, None) => {
                return Err(("focal_length_mm", "is required for a perspective projection".into()));
            }
            (_, Some(f)) => finite_positive("focal_length_mm", f)?,
            _ => {}
        }
        finite_positive("f_number", self.f_number)?;
        finite_positive("focus_distance_mm", self.focus_distance_mm)?;
        finite_positive("pixel_pitch_um", self.pixel_pitch_um)?;
        if let (Projection::Perspective, Some(f)) = (self.projection, self.focal_length_mm)
            && self.focus_distance_mm <= f
        {
            return Err((
                "focus_distance_mm",
                format!(
                    "{} mm must exceed focal_length_mm {f} mm: a thin lens cannot focus closer than its focal length",
                    self.focus_distance_mm
                ),
            ));
        }
        if let Some([cx, cy]) = self.principal_point_px
            && !(cx.is_finite() && cy.is_finite() && cx.abs() <= 1e6 && cy.abs() <= 1e6)
        {
            return Err(("principal_point_px", format!("must be finite and within ±1e6 px, got [{cx}, {cy}]")));
        }
        match (self.projection, self.magnification) {
            (Projection::Telecentric, None) => {
                return Err(("magnification", "is required for a telecentric projection".into()));
            }
            (_, Some(m)) => finite_positive("magnification", m)?,
            _ => {}
        }
        Ok(())
    }

    pub fn pixel_pitch_mm(&self) -> f64 {
        self.pixel_pitch_um * 1e-3
    }

    /// The thin lens's focal length. Only the perspective projection's formulas use it, and
    /// [`Optics::validate`] (which every bundle passes) requires it there.
    fn thin_lens_focal_length_mm(&self) -> f64 {
        self.focal_length_mm.expect("validated: a perspective projection has a focal length")
    }

    /// Lens-to-sensor distance dᵢ = f·F / (F − f), fixed for the whole stack (perspective).
    pub fn sensor_distance_mm(&self) -> f64 {
        let (f, big_f) = (self.thin_lens_focal_length_mm(), self.focus_distance_mm);
        f * big_f / (big_f - f)
    }

    /// Magnification at the focus distance (perspective) or the lens's (telecentric).
    pub fn magnification_at_focus(&self) -> f64 {
        match self.projection {
            Projection::Perspective => self.sensor_distance_mm() / self.focus_distance_mm,
            Projection::Telecentric => self.magnification.unwrap_or(1.0),
        }
    }

    /// Object-space size of one pixel at `depth_mm` from the lens.
    pub fn object_pixel_mm(&self, depth_mm: f64) -> f64 {
        match self.projection {
            Projection::Perspective => self.pixel_pitch_mm() * depth_mm / self.sensor_distance_mm(),
            Projection::Telecentric => self.pixel_pitch_mm() / self.magnification_at_focus(),
        }
    }

    pub fn principal_point(&self, width: u32, height: u32) -> [f64; 2] {
        self.principal_point_px.unwrap_or([width as f64 / 2.0, height as f64 / 2.0])
    }

    /// The ray of pixel (u, v) (centre at u + 0.5, v + 0.5) for the frame at `offset_mm`, in the camera
    /// frame of offset 0. The frame's lens centre sits `offset_mm` behind that of offset 0.
    pub fn pixel_ray(&self, u: f64, v: f64, principal: [f64; 2], offset_mm: f64) -> Ray {
        let p = self.pixel_pitch_mm();
        let (sx, sy) = ((u + 0.5 - principal[0]) * p, (v + 0.5 - principal[1]) * p);
        match self.projection {
            Projection::Perspective => {
                let di = self.sensor_distance_mm();
                Ray { origin: Point3::new(0.0, 0.0, -offset_mm), direction: Vector3::new(sx / di, sy / di, 1.0) }
            }
            Projection::Telecentric => {
                let m = self.magnification_at_focus();
                Ray { origin: Point3::new(sx / m, sy / m, -offset_mm), direction: Vector3::new(0.0, 0.0, 1.0) }
            }
        }
    }

    /// Blur-circle diameter on the sensor, in pixels, of a point at `depth_mm` from the lens.
    pub fn coc_px(&self, depth_mm: f64) -> f64 {
        let (big_f, n) = (self.focus_distance_mm, self.f_number);
        let coc_mm = match self.projection {
            Projection::Perspective => {
                let f = self.thin_lens_focal_length_mm();
                (depth_mm - big_f).abs() / depth_mm * f * f / (n * (big_f - f))
            }
            Projection::Telecentric => {
                let m = self.magnification_at_focus();
                m * m * (depth_mm - big_f).abs() / n
            }
        };
        coc_mm / self.pixel_pitch_mm()
    }

    /// Depth of field: the depth range over which the blur circle stays within `max_coc_px` pixels.
    pub fn depth_of_field_mm(&self, max_coc_px: f64) -> f64 {
        // Solve coc_px(d) = max_coc_px on both sides of F by bisection (monotone on each side).
        let big_f = self.focus_distance_mm;
        let solve = |sign: f64| {
            let (mut lo, mut hi) = (0.0, big_f * 0.5);
            for _ in 0..200 {
                let mid = 0.5 * (lo + hi);
                if self.coc_px(big_f + sign * mid) < max_coc_px { lo = mid } else { hi = mid }
            }
            lo
        };
        solve(-1.0) + solve(1.0)
    }
}

/// A view's pose as the fixture's encoders give it (bundle v1 `pose`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ViewPose {
    /// θ of the view's radial optical axis, degrees (approximate: registration refines it).
    pub angle_deg: f64,
    /// Where the optical axis meets the pipe axis, mm from the end face toward the body.
    pub axial_mm: f64,
    /// The lens centre's radius at frame offset 0, mm.
    pub lens_radius_mm: f64,
}

impl ViewPose {
    /// Camera (offset 0) → pipe frame. Camera x = +z of the pipe, y = +θ direction, z = toward the axis.
    pub fn camera_to_pipe(&self) -> Isometry3<f64> {
        let (s, c) = self.angle_deg.to_radians().sin_cos();
        let axes = Matrix3::from_columns(&[Vector3::z(), Vector3::new(-s, c, 0.0), Vector3::new(-c, -s, 0.0)]);
        let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(axes));
        let translation = Translation3::new(self.lens_radius_mm * c, self.lens_radius_mm * s, self.axial_mm);
        Isometry3::from_parts(translation, rotation)
    }
}

/// The standard preset's camera for unit tests below the simulator, which they may not import: a
/// 50 mm f/1.4 lens focused at 220 mm on 12 µm pixels (`sim::presets` defines the preset itself).
#[cfg(test)]
impl Optics {
    pub(crate) fn standard_camera() -> Self {
        Optics {
            projection: Projection::Perspective,
            focal_length_mm: Some(50.0),
            f_number: 1.4,
            focus_distance_mm: 220.0,
            pixel_pitch_um: 12.0,
            principal_point_px: None,
            magnification: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_f_number_bound_takes_the_simulators_stations_and_refuses_typos() {
        let at = |f_number: f64| Optics { f_number, ..Optics::standard_camera() }.validate();
        assert!(at(0.28).is_ok(), "the random stations' fastest lens");
        assert!(at(1.4).is_ok());
        assert_eq!(at(0.05).unwrap_err().0, "f_number");
        assert_eq!(at(300.0).unwrap_err().0, "f_number");
    }

    fn spec_example() -> Optics {
        Optics {
            projection: Projection::Perspective,
            focal_length_mm: Some(50.0),
            f_number: 2.8,
            focus_distance_mm: 120.0,
            pixel_pitch_um: 3.45,
            principal_point_px: None,
            magnification: None,
        }
    }

    #[test]
    fn coc_follows_the_contract_formula() {
        let o = spec_example();
        assert_eq!(o.coc_px(120.0), 0.0);
        let expected_mm = 1.0 / 121.0 * 2500.0 / (2.8 * 70.0);
        assert!((o.coc_px(121.0) - expected_mm / 0.00345).abs() < 1e-9);
        assert!((o.sensor_distance_mm() - 6000.0 / 70.0).abs() < 1e-12);
    }

    #[test]
    fn pose_axes_match_the_contract() {
        let pose = ViewPose { angle_deg: 90.0, axial_mm: 12.0, lens_radius_mm: 177.2 };
        let iso = pose.camera_to_pipe();
        let centre = iso * Point3::origin();
        assert!((centre - Point3::new(0.0, 177.2, 12.0)).norm() < 1e-9);
        // Optical axis points at the pipe axis; image x is +z; image y is +θ (here −x of the pipe).
        assert!((iso * Vector3::z() - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-12);
        assert!((iso * Vector3::x() - Vector3::z()).norm() < 1e-12);
        assert!((iso * Vector3::y() - Vector3::new(-1.0, 0.0, 0.0)).norm() < 1e-12);
        // A point on the axis at depth lens_radius.
        let on_axis = iso * Point3::new(0.0, 0.0, 177.2);
        assert!((on_axis - Point3::new(0.0, 0.0, 12.0)).norm() < 1e-9);
    }

    #[test]
    fn invalid_optics_name_the_field() {
        let mut o = spec_example();
        o.focus_distance_mm = 40.0;
        assert_eq!(o.validate().unwrap_err().0, "focus_distance_mm");
        let mut o = spec_example();
        o.f_number = f64::NAN;
        assert_eq!(o.validate().unwrap_err().0, "f_number");
        let mut o = spec_example();
        o.projection = Projection::Telecentric;
        assert_eq!(o.validate().unwrap_err().0, "magnification");
    }
}
