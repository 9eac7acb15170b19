//! The station a bundle was recorded at, as the bundle's own optics and view layout give it: the
//! object-space pixel, the depth of field, the frame step, the views and how far neighbours
//! overlap. Reports carry it as their provenance, and the quality of a result compares it with
//! the envelope the accuracy figures were measured in.

use crate::domain::frame::View;
use crate::domain::optics::{Optics, Projection};
use crate::numeric::stats::median;
use serde::{Deserialize, Serialize};

/// The blur circle, in pixels, within which a point counts as in focus for the depth of field.
pub const IN_FOCUS_BLUR_PX: f64 = 1.0;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Station {
    /// The camera's projection: perspective or telecentric.
    pub projection: Projection,
    /// One pixel on the part at the focus distance, mm.
    pub object_pixel_mm: f64,
    /// The depth range over which the blur circle stays within one pixel, mm.
    pub depth_of_field_mm: f64,
    /// The median spacing of the frames' offsets, mm, and as a fraction of the depth of field.
    pub frame_step_mm: f64,
    /// That spacing as a fraction of the depth of field.
    pub frame_step_dof: f64,
    /// The fewest frames of any view.
    pub frames_per_view: usize,
    /// How many views the bundle has.
    pub views: usize,
    /// Distinct axial positions of the views.
    pub axial_rows: usize,
    /// The median angle between neighbouring views of a row, and how far their footprints
    /// overlap along the arc at the pipe's radius (negative: a gap), degrees. None for one view
    /// per row.
    pub view_spacing_deg: Option<f64>,
    /// How far neighbouring views' footprints overlap along the arc at the pipe's radius,
    /// degrees (negative: a gap); null for one view per row.
    pub overlap_deg: Option<f64>,
    /// The frames' pixel noise, in per cent of their brightness: measured on the frames by the depth
    /// stage (the median over the views' first frames), not declared by the manifest. None before
    /// it is read (and in reports stored before it was).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_noise_percent: Option<f64>,
    /// The envelope's class the station falls in ([`StationClass`]; `GET /v1/capabilities` gives
    /// each class's ranges); None outside every class, or in reports stored before classes were.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub class: Option<StationClass>,
    /// The study that qualified this station for this inspection (ISO 15530-3): its correction
    /// was applied and its uncertainty stands in for the method's. None at a station no
    /// qualification applied to.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub qualified_by: Option<String>,
}

/// The classes of the declared envelope. `standard` is where the accuracy targets were met (the
/// presets' station ±10%); `fine`, `medium` and `coarse` split the station benchmark's ranges
/// ([`BENCHMARKED`]) by object pixel (≤ 0.06 mm, ≤ 0.10 mm, above), each with the figures the
/// station benchmark measured there, far from the targets (docs/status.md, docs/benchmark.md): a result
/// there is inspected, degraded and flagged for review.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum StationClass {
    Standard,
    Fine,
    Medium,
    Coarse,
}

impl StationClass {
    pub const ALL: [StationClass; 4] = [Self::Standard, Self::Fine, Self::Medium, Self::Coarse];

    pub fn as_str(self) -> &'static str {
        match self {
            Self::Standard => "standard",
            Self::Fine => "fine",
            Self::Medium => "medium",
            Self::Coarse => "coarse",
        }
    }

    /// The class's ranges: the measured envelope for `standard`, else the benchmarked ranges
    /// with the class's share of the object pixel.
    pub fn envelope(self) -> Envelope {
        let (lo, hi) = BENCHMARKED.object_pixel_mm;
        let object_pixel_mm = match self {
            Self::Standard => return MEASURED,
            Self::Fine => (lo, FINE_MAX_PIXEL_MM),
            Self::Medium => (FINE_MAX_PIXEL_MM, MEDIUM_MAX_PIXEL_MM),
            Self::Coarse => (MEDIUM_MAX_PIXEL_MM, hi),
        };
        Envelope { object_pixel_mm, ..BENCHMARKED }
    }
}

/// The object pixel bounds of the fine and medium classes, mm (the issue's own split: fine
/// stations at most 0.06 mm).
pub const FINE_MAX_PIXEL_MM: f64 = 0.06;
pub const MEDIUM_MAX_PIXEL_MM: f64 = 0.10;

/// The surface the views cover, in object pixels: the circumference by the band along the axis
/// that the views' axial poses span, widened by the widest frame (image columns run along the
/// axis). Registration's and fusion's grids scale with it. Also returns the band, mm, and the views
/// at its two ends.
pub fn surface_pixels(optics: &Optics, views: &[View], circumference_mm: f64) -> SurfaceBand {
    let pixel_mm = optics.object_pixel_mm(optics.focus_distance_mm);
    let axial = |i: usize| views[i].pose.axial_mm;
    let lo = (0..views.len()).min_by(|&a, &b| axial(a).total_cmp(&axial(b))).unwrap_or(0);
    let hi = (0..views.len()).max_by(|&a, &b| axial(a).total_cmp(&axial(b))).unwrap_or(0);
    let frame_mm = views.iter().map(|v| v.format.width).max().unwrap_or(0) as f64 * pixel_mm;
    let (spread_mm, band_mm) =
        if views.is_empty() { (0.0, 0.0) } else { (axial(hi) - axial(lo), axial(hi) - axial(lo) + frame_mm) };
    SurfaceBand {
        pixels: (circumference_mm / pixel_mm) * (band_mm / pixel_mm),
        band_mm,
        spread_mm,
        frame_mm,
        lo,
        hi,
        pixel_mm,
    }
}

/// What [`surface_pixels`] found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceBand {
    pub pixels: f64,
    pub band_mm: f64,
    /// How far the views' axial poses spread, and a frame's width along the axis, mm.
    pub spread_mm: f64,
    pub frame_mm: f64,
    /// The views with the lowest and the highest axial pose.
    pub lo: usize,
    pub hi: usize,
    pub pixel_mm: f64,
}

impl Station {
    /// The station of a recording: its optics, its views and the pipe's radius.
    pub fn of(optics: &Optics, views: &[View], pipe_radius_mm: f64) -> Self {
        let object_pixel_mm = optics.object_pixel_mm(optics.focus_distance_mm);
        let depth_of_field_mm = optics.depth_of_field_mm(IN_FOCUS_BLUR_PX);
        let mut steps: Vec<f64> = views
            .iter()
            .flat_map(|v| {
                let mut offsets: Vec<f64> = v.frames.iter().map(|f| f.offset_mm).collect();
                offsets.sort_by(f64::total_cmp);
                offsets.windows(2).map(|w| w[1] - w[0]).collect::<Vec<_>>()
            })
            .collect();
        let frame_step_mm = median(&mut steps).unwrap_or(0.0);
        let mut rows: Vec<f64> = views.iter().map(|v| v.pose.axial_mm).collect();
        rows.sort_by(f64::total_cmp);
        // Views within a pixel of each other axially stand in one row.
        rows.dedup_by(|a, b| (*a - *b).abs() < object_pixel_mm);
        let mut spacings = Vec::new();
        for &row in &rows {
            let mut angles: Vec<f64> = views
                .iter()
                .filter(|v| (v.pose.axial_mm - row).abs() < object_pixel_mm)
                .map(|v| v.pose.angle_deg.rem_euclid(360.0))
                .collect();
            angles.sort_by(f64::total_cmp);
            spacings.extend(angles.windows(2).map(|w| w[1] - w[0]));
            // Around the turn only where the row closes on itself within a view's reach.
            if angles.len() > 2 {
                let wrap = angles[0] + 360.0 - angles[angles.len() - 1];
                if wrap < 2.0 * angles.windows(2).map(|w| w[1] - w[0]).fold(0.0, f64::max) {
                    spacings.push(wrap);
                }
            }
        }
        let view_spacing_deg = median(&mut spacings);
        // The footprint along the arc: the image's rows span the arc (docs/bundle.md, camera frame).
        let footprint_deg =
            views.first().map(|v| (v.format.height as f64 * object_pixel_mm / pipe_radius_mm).to_degrees());
        Self {
            projection: optics.projection,
            object_pixel_mm,
            depth_of_field_mm,
            frame_step_mm,
            frame_step_dof: frame_step_mm / depth_of_field_mm.max(f64::MIN_POSITIVE),
            frames_per_view: views.iter().map(|v| v.frames.len()).min().unwrap_or(0),
            views: views.len(),
            axial_rows: rows.len(),
            overlap_deg: view_spacing_deg.zip(footprint_deg).map(|(s, f)| f - s),
            view_spacing_deg,
            frame_noise_percent: None,
            class: None,
            qualified_by: None,
        }
        .with_frame_noise(None)
    }

    /// The station with the frames' noise as the depth stage read it, and its class then.
    pub fn with_frame_noise(self, frame_noise_percent: Option<f64>) -> Self {
        let station = Self { frame_noise_percent, ..self };
        Self { class: station.classify(), ..station }
    }

    /// The first class whose ranges hold every parameter the station has (the standard class
    /// first); None outside them all.
    fn classify(&self) -> Option<StationClass> {
        StationClass::ALL.into_iter().find(|c| self.outside(&c.envelope()).is_empty())
    }

    /// The parameters of this station outside `envelope`, each as (name, value, range) text.
    pub fn outside(&self, envelope: &Envelope) -> Vec<String> {
        self.parameters(envelope)
            .into_iter()
            .filter(|p| p.is_outside())
            .map(|p| {
                let (lo, hi) = p.range;
                format!("{} {:.3}{u} (measured: {lo}–{hi}{u})", p.name, p.value.unwrap_or(f64::NAN), u = p.unit)
            })
            .collect()
    }

    /// Whether the optics (object pixel, depth of field, frame step) lie outside `envelope`: where
    /// the depth from focus itself, not only registration, was never measured.
    pub fn optics_outside(&self, envelope: &Envelope) -> bool {
        self.parameters(envelope).iter().any(|p| p.optics && p.is_outside())
    }

    /// Each parameter the envelope bounds, with its value (None: the station has none) and range.
    fn parameters(&self, e: &Envelope) -> [Parameter; 5] {
        let p = |name, value, range, unit, optics| Parameter { name, value, range, unit, optics };
        [
            p("object pixel", Some(self.object_pixel_mm), e.object_pixel_mm, " mm", true),
            p("depth of field", Some(self.depth_of_field_mm), e.depth_of_field_mm, " mm", true),
            p("frame step", Some(self.frame_step_dof), e.frame_step_dof, " depths of field", true),
            p("overlap between neighbouring views", self.overlap_deg, e.overlap_deg, "°", false),
            // Noise decides what depth from focus can resolve, as the optics do.
            p("frame noise", self.frame_noise_percent, e.frame_noise_percent, "% of the brightness", true),
        ]
    }
}

struct Parameter {
    name: &'static str,
    value: Option<f64>,
    range: (f64, f64),
    unit: &'static str,
    /// A parameter of the optics (depth from focus) rather than of the view layout.
    optics: bool,
}

impl Parameter {
    fn is_outside(&self) -> bool {
        self.value.is_some_and(|v| !(self.range.0..=self.range.1).contains(&v))
    }
}

/// A range of stations, per parameter, inclusive.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Envelope {
    pub object_pixel_mm: (f64, f64),
    pub depth_of_field_mm: (f64, f64),
    pub frame_step_dof: (f64, f64),
    pub overlap_deg: (f64, f64),
    /// The frames' noise in per cent of their brightness ([`Station::frame_noise_percent`]).
    pub frame_noise_percent: (f64, f64),
}

/// Where the accuracy figures were measured: every case of the accuracy and held-out suites shares
/// one station design (object pixel 0.041 mm, depth of field 0.50 mm, frames every 0.50 depths of
/// field, neighbours overlapping by 5.1°), and this envelope is that station ±10% on each. Its
/// sensor's frames read 0.65–0.84% noise; the bound is where the depth stage's noise pre-filter
/// starts (`DepthOptions::prefilter_min_noise`), above which the suites never ran: a bundle with
/// the standard optics on a noisier sensor is outside. A bundle outside it is inspected, and its
/// result's quality says which parameter lies outside: nothing has measured how well crestscan
/// does there.
pub const MEASURED: Envelope = Envelope {
    object_pixel_mm: (0.037, 0.045),
    depth_of_field_mm: (0.45, 0.55),
    frame_step_dof: (0.45, 0.55),
    overlap_deg: (4.6, 5.6),
    frame_noise_percent: (0.0, 1.5),
};

/// The expanded uncertainty (k = 2) of a corrected height, µm, that a qualification study stated
/// at each station the qualification benchmark ran (docs/benchmark.md, "Station qualification";
/// a test keeps the two the same): what `station plan` can say of a planned station's U before
/// its own study. Within a class it spans two orders of magnitude, set by each station's
/// repeatability, which its optics' class does not decide.
pub const QUALIFIED_U_UM: [(StationClass, &str, f64); 6] = [
    (StationClass::Fine, "fine-ring", 4.0),
    (StationClass::Medium, "random:287", 108.4),
    (StationClass::Coarse, "coarse-survey", 19.6),
    (StationClass::Coarse, "random:245", 84.1),
    (StationClass::Coarse, "random:217", 190.4),
    (StationClass::Coarse, "random:241", 1520.5),
];

/// The ranges the station benchmark's random stations are drawn from (`sim::station::ranges`:
/// object pixel, depth of field, frame step, overlap; noise up to 8× the standard sensor's, which
/// reads 0.65–0.84%): the classes below the standard one have measured figures only within them.
/// Beyond the coarsest object pixel a bundle is refused (`station_out_of_range`); outside the other
/// ranges it is inspected as unclassified, degraded.
pub const BENCHMARKED: Envelope = Envelope {
    object_pixel_mm: (0.03, 0.15),
    depth_of_field_mm: (0.05, 0.6),
    frame_step_dof: (0.3, 1.5),
    overlap_deg: (2.0, 15.0),
    frame_noise_percent: (0.0, 7.0),
};

/// The coarsest object pixel inspected, mm: the coarse class's bound and a margin for lenses that
/// round onto it (the simulator's land within 0.1505 mm); between the two a station is inspected,
/// unclassified. Beyond it a bundle is refused (`station_out_of_range`).
pub const MAX_OBJECT_PIXEL_MM: f64 = BENCHMARKED.object_pixel_mm.1 + 0.01;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::frame::{FrameEntry, FrameFormat};
    use crate::domain::optics::ViewPose;

    fn ring(views: usize, height_px: u32, step_mm: f64) -> Vec<View> {
        (0..views)
            .map(|v| View {
                id: format!("v{v}"),
                pose: ViewPose { angle_deg: 360.0 * v as f64 / views as f64, axial_mm: 0.0, lens_radius_mm: 250.0 },
                frames: (0..20)
                    .map(|k| FrameEntry { file: format!("{k}.png"), offset_mm: step_mm * k as f64 })
                    .collect(),
                format: FrameFormat { width: 864, height: height_px, channels: 3, bit_depth: 8 },
            })
            .collect()
    }

    /// A telecentric lens of magnification 0.25 on 10 µm pixels: 40 µm on the part.
    fn telecentric() -> Optics {
        Optics {
            projection: Projection::Telecentric,
            focal_length_mm: None,
            f_number: 8.0,
            focus_distance_mm: 100.0,
            pixel_pitch_um: 10.0,
            principal_point_px: None,
            magnification: Some(0.25),
        }
    }

    #[test]
    fn a_ring_reads_as_its_pixel_spacing_and_overlap() {
        let optics = telecentric();
        // 40 µm pixels; 45 views 8° apart, 320 rows: 12.8 mm of arc at 57.15 mm is 12.83°.
        let s = Station::of(&optics, &ring(45, 320, 0.25), 57.15);
        assert!((s.object_pixel_mm - 0.04).abs() < 1e-12);
        assert_eq!((s.views, s.axial_rows, s.frames_per_view), (45, 1, 20));
        assert!((s.view_spacing_deg.unwrap() - 8.0).abs() < 1e-9);
        assert!((s.overlap_deg.unwrap() - 4.833).abs() < 1e-3, "{s:?}");
        assert!((s.frame_step_mm - 0.25).abs() < 1e-12);
        // The telecentric depth of field: blur m²·|Δ|/N within one 10 µm pixel on each side.
        assert!((s.depth_of_field_mm - 2.0 * 8.0 * 0.010 / 0.0625).abs() < 1e-6, "{}", s.depth_of_field_mm);
    }

    #[test]
    fn each_parameter_outside_the_envelope_is_named_with_its_range() {
        let envelope = Envelope {
            object_pixel_mm: (0.03, 0.05),
            depth_of_field_mm: (0.1, 3.0),
            frame_step_dof: (0.05, 1.0),
            overlap_deg: (3.0, 12.0),
            frame_noise_percent: (0.0, 1.5),
        };
        let optics = telecentric();
        assert!(Station::of(&optics, &ring(45, 320, 0.25), 57.15).outside(&envelope).is_empty());
        // 12 views 30° apart overlap by −17°.
        let sparse = Station::of(&optics, &ring(12, 320, 0.25), 57.15).outside(&envelope);
        assert_eq!(sparse.len(), 1);
        assert!(sparse[0].starts_with("overlap between neighbouring views -17."), "{sparse:?}");
        let coarse = Optics { magnification: Some(0.08), ..optics };
        let names: Vec<String> = Station::of(&coarse, &ring(45, 320, 0.25), 57.15).outside(&envelope);
        assert!(names.iter().any(|n| n.starts_with("object pixel 0.125 mm")), "{names:?}");
        // The frames' noise, once the depth stage has read it: a noisy sensor behind the same optics
        // is outside, as its optics would be; not yet read, nothing is said of it.
        let standard = Station::of(&optics, &ring(45, 320, 0.25), 57.15);
        assert!(!standard.optics_outside(&envelope));
        let quiet = Station { frame_noise_percent: Some(0.8), ..standard.clone() };
        assert!(quiet.outside(&envelope).is_empty());
        let noisy = Station { frame_noise_percent: Some(5.75), ..standard };
        assert_eq!(
            noisy.outside(&envelope),
            vec!["frame noise 5.750% of the brightness (measured: 0–1.5% of the brightness)"]
        );
        assert!(noisy.optics_outside(&envelope));
    }

    #[test]
    fn a_station_falls_in_the_class_whose_ranges_hold_all_its_parameters() {
        let at = |object_pixel_mm: f64, depth_of_field_mm: f64, overlap_deg: f64, noise: f64| {
            Station {
                projection: Projection::Perspective,
                object_pixel_mm,
                depth_of_field_mm,
                frame_step_mm: 0.5 * depth_of_field_mm,
                frame_step_dof: 0.5,
                frames_per_view: 20,
                views: 45,
                axial_rows: 1,
                view_spacing_deg: Some(8.0),
                overlap_deg: Some(overlap_deg),
                frame_noise_percent: None,
                class: None,
                qualified_by: None,
            }
            .with_frame_noise(Some(noise))
            .class
        };
        // The presets' station is standard; the same optics on a sensor three times as noisy is not,
        // but it lies in the benchmarked ranges: fine, by its pixel.
        assert_eq!(at(0.041, 0.5, 5.1, 0.8), Some(StationClass::Standard));
        assert_eq!(at(0.041, 0.5, 5.1, 2.5), Some(StationClass::Fine));
        // The other station: 0.12 mm pixels, ±0.24 mm in focus, overlaps of 3°.
        assert_eq!(at(0.12, 0.48, 3.0, 2.0), Some(StationClass::Coarse));
        assert_eq!(at(0.08, 0.3, 10.0, 1.0), Some(StationClass::Medium));
        // At a class boundary the finer class holds it.
        assert_eq!(at(FINE_MAX_PIXEL_MM, 0.3, 10.0, 1.0), Some(StationClass::Fine));
        // Outside the benchmarked ranges in any parameter: no class.
        assert_eq!(at(0.08, 2.5, 10.0, 1.0), None, "a telecentric depth of field of 2.5 mm");
        assert_eq!(at(0.08, 0.3, 1.0, 1.0), None, "overlaps of 1°");
        assert_eq!(at(0.02, 0.3, 5.0, 1.0), None, "pixels finer than any benchmarked");
        // The classes tile the benchmarked object pixels without a gap.
        let classes = [StationClass::Fine, StationClass::Medium, StationClass::Coarse].map(|c| c.envelope());
        assert_eq!(classes[0].object_pixel_mm.0, BENCHMARKED.object_pixel_mm.0);
        assert_eq!(classes[2].object_pixel_mm.1, BENCHMARKED.object_pixel_mm.1);
        assert!(classes.windows(2).all(|w| w[0].object_pixel_mm.1 == w[1].object_pixel_mm.0));
    }
}
