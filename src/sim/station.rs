//! Stations: the camera, lens, fixture and sensor a bundle is recorded with, apart from the part.
//!
//! The presets share one station design (41 µm object pixels, 45 views 8° apart, 20 frames every
//! half depth of field, one texture model). A plant's differs, so a defect preset can be rendered
//! at another station: a named one, or one drawn at random by seed from the ranges a real station
//! spans (docs/simulator.md, "Stations"). Every draw is physically consistent: the object pixel
//! and the depth of field follow from a real lens (focal length, f-number, focus distance) and
//! sensor, and the frame step from the depth of field.

use super::appearance::Appearance;
use super::presets::{Layout, plan};
use super::render::Sensor;
use super::{PoseJitter, SimSpec};
use crate::domain::optics::{Optics, Projection};
use crate::domain::station::IN_FOCUS_BLUR_PX;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// The ranges a random station is drawn from.
pub mod ranges {
    pub const OBJECT_PIXEL_MM: (f64, f64) = (0.03, 0.15);
    pub const DEPTH_OF_FIELD_MM: (f64, f64) = (0.05, 0.6);
    /// Frame step in depths of field.
    pub const FRAME_STEP_DOF: (f64, f64) = (0.3, 1.5);
    pub const VIEWS_AROUND: (usize, usize) = (12, 64);
    pub const AXIAL_ROWS: (usize, usize) = (1, 3);
    pub const OVERLAP_DEG: (f64, f64) = (2.0, 15.0);
    /// Encoder error bounds: up to these (each drawn from a tenth of it to all of it).
    pub const ENCODER_ANGLE_DEG: f64 = 1.0;
    pub const ENCODER_AXIAL_MM: f64 = 0.3;
    pub const ENCODER_LENS_RADIUS_MM: f64 = 0.3;
    /// Noise relative to the standard sensor's.
    pub const NOISE_FACTOR: (f64, f64) = (1.0, 8.0);
    /// Pixel-frames rendered per case at most (views × frames × pixels): a fine station around
    /// the whole ring would take hours to render on two cores, so beyond this its views cover a
    /// sector of the ring (said in the station's description and seen in the report's coverage).
    pub const MAX_PIXEL_FRAMES: f64 = 40e6;
    /// Frames per stack at most: a very shallow depth of field is stepped no finer than the stack
    /// span over this many frames (the step may then exceed the drawn fraction of the depth of
    /// field, up to the range's top).
    pub const MAX_FRAMES: usize = 48;
}

/// A station: everything of a simulated bundle but the part.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StationSpec {
    pub name: String,
    pub optics: Optics,
    /// Frame size: width along the pipe's axis, height along the arc.
    pub width: u32,
    pub height: u32,
    /// Views per axial row around the ring, their spacing, the first one's angle and how many are
    /// rendered (all of them, or a sector when the ring would cost too much).
    pub views_around: usize,
    pub first_angle_deg: f64,
    pub views_rendered: usize,
    /// Axial rows: the z of each row's view centres is the preset's span split evenly.
    pub axial_rows: usize,
    /// Frame step, mm.
    pub frame_step_mm: f64,
    pub jitter: PoseJitter,
    pub sensor: Sensor,
    pub appearance: Appearance,
    /// Overlap between neighbouring views along the arc, degrees, as planned.
    pub overlap_deg: f64,
}

/// Named stations (`crestscan simulate --station NAME`).
pub const NAMED: &[(&str, &str)] = &[
    (
        "coarse-survey",
        "0.12 mm object pixels, depth of field 0.48 mm (±0.24 mm), frames every 0.30 mm, 16 views overlapping \
         by 3.5°, encoders ±0.9° and ±0.27 mm: the independent renderer's station",
    ),
    ("fine-ring", "0.05 mm object pixels, depth of field 0.24 mm, frames every 0.12 mm, 16 views overlapping by 3°"),
    (
        "telecentric-coarse",
        "a 0.1× telecentric lens on 10 µm pixels (0.1 mm), depth of field 0.5 mm, 20 views overlapping by 4°, 16-bit gray",
    ),
];

/// A named station, or `random` drawn by `seed`; None for an unknown name.
pub fn station(name: &str, seed: u64, pipe_radius_mm: f64, z_span_mm: f64) -> Option<StationSpec> {
    let mut s = match name {
        "random" => return Some(random(seed, pipe_radius_mm, z_span_mm)),
        "coarse-survey" => {
            let optics = lens_for(Projection::Perspective, 0.12, 0.48, pitch_for(0.12, 0.48, 1.0), 100.0);
            sized(name, optics, 16, 3.5, 1, 0.30, pipe_radius_mm, z_span_mm)
        }
        "fine-ring" => {
            let optics = lens_for(Projection::Perspective, 0.05, 0.24, pitch_for(0.05, 0.24, 2.0), 75.0);
            sized(name, optics, 16, 3.0, 1, 0.12, pipe_radius_mm, z_span_mm)
        }
        "telecentric-coarse" => {
            let optics = lens_for(Projection::Telecentric, 0.10, 0.5, 10.0, 0.0);
            let mut s = sized(name, optics, 20, 4.0, 1, 0.25, pipe_radius_mm, z_span_mm);
            s.sensor.bit_depth = 16;
            s.sensor.monochrome = true;
            s
        }
        _ => return None,
    };
    if name == "coarse-survey" {
        s.jitter = PoseJitter { angle_deg: 0.9, axial_mm: 0.27, lens_radius_mm: 0.1 };
    }
    Some(s)
}

/// A lens on sensor pixels of `pitch_um` whose object pixel is `pixel_mm` (a perspective lens of
/// focal length `f_mm` focused where its magnification gives that pixel, or a telecentric lens of
/// that magnification), its f-number set so that the depth of field (blur ≤ 1 pixel) is `dof_mm`.
fn lens_for(projection: Projection, pixel_mm: f64, dof_mm: f64, pitch_um: f64, f_mm: f64) -> Optics {
    let m = pitch_um * 1e-3 / pixel_mm;
    let mut optics = Optics {
        projection,
        focal_length_mm: (projection == Projection::Perspective).then_some(f_mm),
        f_number: 1.0,
        // Thin lens: in focus at F = f (1 + 1/m) in front of it.
        focus_distance_mm: match projection {
            Projection::Perspective => round_to(f_mm * (1.0 + 1.0 / m), 0.01),
            Projection::Telecentric => 110.0,
        },
        pixel_pitch_um: pitch_um,
        principal_point_px: None,
        magnification: (projection == Projection::Telecentric).then_some(round_to(m, 1e-5)),
    };
    // The depth of field grows in proportion to the f-number (to first order): a few steps of
    // that proportion land on the target.
    for _ in 0..4 {
        let dof = optics.depth_of_field_mm(IN_FOCUS_BLUR_PX);
        optics.f_number *= dof_mm / dof;
    }
    optics.f_number = round_to(optics.f_number, 1e-4);
    optics
}

/// The sensor pixel (µm, 2–48: binned as needed) at which a lens of f-number near `n` gives
/// `dof_mm` at `pixel_mm`: the depth of field is about 2·N·p²/c for object pixel p and sensor
/// pixel c, so coarse object pixels with a shallow depth of field need big sensor pixels.
fn pitch_for(pixel_mm: f64, dof_mm: f64, n: f64) -> f64 {
    round_to((1e3 * 2.0 * n * pixel_mm * pixel_mm / dof_mm).clamp(2.0, 48.0), 0.01)
}

fn round_to(v: f64, step: f64) -> f64 {
    (v / step).round() * step
}

/// A station with `views_around` views per row overlapping by `overlap_deg`, frames every
/// `frame_step_mm`, its frames sized to cover `z_span_mm` in `rows` rows (2 mm shared between
/// rows), with the standard sensor and texture.
#[allow(clippy::too_many_arguments)]
fn sized(
    name: &str,
    optics: Optics,
    views_around: usize,
    overlap_deg: f64,
    rows: usize,
    frame_step_mm: f64,
    pipe_radius_mm: f64,
    z_span_mm: f64,
) -> StationSpec {
    let pixel = optics.object_pixel_mm(optics.focus_distance_mm);
    let arc_deg = 360.0 / views_around as f64 + overlap_deg;
    let height = ((arc_deg.to_radians() * pipe_radius_mm / pixel).ceil() as u32).max(16);
    let row_mm = z_span_mm / rows as f64 + if rows > 1 { 2.0 } else { 0.0 };
    let width = ((row_mm / pixel).ceil() as u32).max(16);
    StationSpec {
        name: name.into(),
        optics,
        width,
        height,
        views_around,
        first_angle_deg: 0.0,
        views_rendered: views_around,
        axial_rows: rows,
        frame_step_mm,
        jitter: PoseJitter { angle_deg: 1.0, axial_mm: 0.3, lens_radius_mm: 0.05 },
        sensor: Sensor::default(),
        appearance: Appearance::default(),
        overlap_deg,
    }
}

/// A station drawn at random by `seed` from [`ranges`].
pub fn random(seed: u64, pipe_radius_mm: f64, z_span_mm: f64) -> StationSpec {
    use ranges::*;
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x57A7_1000_5EED_0001);
    let log_uniform = |rng: &mut ChaCha8Rng, (lo, hi): (f64, f64)| (rng.random_range(lo.ln()..=hi.ln())).exp();
    let pixel = log_uniform(&mut rng, OBJECT_PIXEL_MM);
    // The depth of field a lens gives at this pixel: from 2 to 12 object pixels (the standard
    // station's is 12), within the range.
    let dof_range = (DEPTH_OF_FIELD_MM.0.max(2.0 * pixel), DEPTH_OF_FIELD_MM.1.min(12.0 * pixel));
    let dof = log_uniform(&mut rng, dof_range);
    let projection = if rng.random_bool(0.25) { Projection::Telecentric } else { Projection::Perspective };
    let n = log_uniform(&mut rng, (1.0, 8.0));
    let f_mm = [25.0, 35.0, 50.0, 75.0, 100.0][rng.random_range(0..5)];
    let optics = lens_for(projection, pixel, dof, pitch_for(pixel, dof, n), f_mm);
    let dof = optics.depth_of_field_mm(IN_FOCUS_BLUR_PX);
    let views_around = rng.random_range(VIEWS_AROUND.0..=VIEWS_AROUND.1);
    let rows = rng.random_range(AXIAL_ROWS.0..=AXIAL_ROWS.1);
    let overlap_deg = rng.random_range(OVERLAP_DEG.0..=OVERLAP_DEG.1);
    let step_dof = rng.random_range(FRAME_STEP_DOF.0..=FRAME_STEP_DOF.1);
    let mut s = sized("random", optics, views_around, overlap_deg, rows, step_dof * dof, pipe_radius_mm, z_span_mm);
    s.first_angle_deg = rng.random_range(0.0..360.0 / views_around as f64);
    s.jitter = PoseJitter {
        angle_deg: ENCODER_ANGLE_DEG * rng.random_range(0.1..=1.0),
        axial_mm: ENCODER_AXIAL_MM * rng.random_range(0.1..=1.0),
        lens_radius_mm: ENCODER_LENS_RADIUS_MM * rng.random_range(0.1..=1.0),
    };
    let noise = rng.random_range(NOISE_FACTOR.0..=NOISE_FACTOR.1);
    s.sensor = Sensor {
        // Shot and read noise both `noise` times the standard sensor's, relative to full scale.
        full_well_e: 12_000.0 / (noise * noise),
        read_noise_e: 4.0 / noise,
        // Above about 0.85 the specular lobes of machined crests clip.
        white_level: rng.random_range(0.55..=1.1),
        lens_vignetting: rng.random_range(0.0..=0.4),
        bit_depth: if rng.random_bool(0.3) { 16 } else { 8 },
        monochrome: rng.random_bool(0.4),
    };
    s.optics.principal_point_px = rng.random_bool(0.5).then(|| {
        let (w, h) = (s.width as f64, s.height as f64);
        [
            round_to(w / 2.0 + rng.random_range(-0.05..=0.05) * w, 0.01),
            round_to(h / 2.0 + rng.random_range(-0.05..=0.05) * h, 0.01),
        ]
    });
    // Texture from faint to strong: grain and chaser marks scaled together or apart, gloss.
    let mut a = Appearance::default();
    let grain = log_uniform(&mut rng, (0.2, 1.6));
    let marks = rng.random_range(0.0..=1.6);
    let gloss = rng.random_range(0.4..=1.6);
    a.machined.albedo_variation *= grain;
    a.polished.albedo_variation *= grain;
    a.mill_scale.albedo_variation = (a.mill_scale.albedo_variation * grain).min(0.9);
    a.machined.tool_mark_slope *= marks;
    a.polished.tool_mark_slope *= marks;
    a.machined.specular *= gloss;
    a.polished.specular *= gloss;
    a.machined.shininess *= rng.random_range(0.5..=2.0);
    s.appearance = a;
    s
}

impl StationSpec {
    pub fn object_pixel_mm(&self) -> f64 {
        self.optics.object_pixel_mm(self.optics.focus_distance_mm)
    }

    pub fn depth_of_field_mm(&self) -> f64 {
        self.optics.depth_of_field_mm(IN_FOCUS_BLUR_PX)
    }

    /// One line for a description: pixel, depth of field, frame step, views, rows, overlap.
    pub fn summary(&self) -> String {
        let sector = if self.views_rendered < self.views_around {
            format!(
                ", {} of the ring's {} views (a sector of {:.0}°)",
                self.views_rendered,
                self.views_around,
                self.views_rendered as f64 * 360.0 / self.views_around as f64
            )
        } else {
            String::new()
        };
        format!(
            "station {}: {:?} lens, object pixel {:.3} mm, depth of field {:.3} mm, frames every {:.3} mm \
             ({:.2} DOF), {} view(s) around × {} row(s) of {}×{}{}, overlap {:.1}°, encoders ±{:.2}° ±{:.2} mm",
            self.name,
            self.optics.projection,
            self.object_pixel_mm(),
            self.depth_of_field_mm(),
            self.frame_step_mm,
            self.frame_step_mm / self.depth_of_field_mm(),
            self.views_around,
            self.axial_rows,
            self.width,
            self.height,
            sector,
            self.overlap_deg,
            self.jitter.angle_deg,
            self.jitter.axial_mm,
        )
    }
}

/// `spec`'s part recorded at `station`: the views and frame offsets planned for it, the rows
/// spread over the axial span the preset's own views covered. The views rendered are limited to
/// a sector when the whole ring would cost more than [`ranges::MAX_PIXEL_FRAMES`].
pub fn at_station(spec: &SimSpec, station: &StationSpec) -> SimSpec {
    let (z_lo, z_hi) = axial_span(spec);
    let pixel = station.object_pixel_mm();
    let row_mm = station.width as f64 * pixel;
    let rows = station.axial_rows.max(1);
    let axials_mm: Vec<f64> = if rows == 1 {
        vec![0.5 * (z_lo + z_hi)]
    } else {
        // First and last rows flush with the span's ends.
        let (first, last) = (z_lo + row_mm / 2.0, z_hi - row_mm / 2.0);
        (0..rows).map(|j| first + (last - first) * j as f64 / (rows - 1) as f64).collect()
    };
    let step_deg = 360.0 / station.views_around as f64;
    let mut layout = Layout {
        width: station.width,
        height: station.height,
        first_angle_deg: station.first_angle_deg,
        angle_step_deg: step_deg,
        angles: station.views_around,
        axials_mm,
        frame_step_mm: station.frame_step_mm,
    };
    let (mut views, mut offsets) = plan(&spec.part, &station.optics, &layout, &station.jitter);
    // Too many frames for a shallow depth of field: a coarser step, never past the range's top.
    if offsets.len() > ranges::MAX_FRAMES {
        let span = offsets[offsets.len() - 1] - offsets[0];
        layout.frame_step_mm =
            (span / (ranges::MAX_FRAMES - 1) as f64).min(ranges::FRAME_STEP_DOF.1 * station.depth_of_field_mm());
        (views, offsets) = plan(&spec.part, &station.optics, &layout, &station.jitter);
    }
    let per_view = offsets.len() as f64 * station.width as f64 * station.height as f64;
    let mut station = station.clone();
    station.frame_step_mm = layout.frame_step_mm;
    let affordable = ((ranges::MAX_PIXEL_FRAMES / per_view).floor() as usize / rows).max(3);
    if affordable < station.views_around {
        station.views_rendered = affordable;
        // Keep each row's first `affordable` views: a contiguous sector.
        views.retain(|v| v.id[1..4].parse::<usize>().is_ok_and(|i| i < affordable));
    }
    let mut out = spec.clone();
    out.name = format!("{}@{}", spec.name, station.name);
    out.description = format!("{}; {}", spec.description, station.summary());
    out.optics = station.optics.clone();
    out.width = station.width;
    out.height = station.height;
    out.views = views;
    out.offsets_mm = offsets;
    out.jitter = station.jitter;
    out.sensor = station.sensor.clone();
    out.appearance = station.appearance.clone();
    out.station = Some(station);
    out
}

/// The axial span the preset's own views cover: each view's footprint along z.
fn axial_span(spec: &SimSpec) -> (f64, f64) {
    let half = spec.width as f64 * spec.optics.object_pixel_mm(spec.optics.focus_distance_mm) / 2.0;
    spec.views
        .iter()
        .fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(v.pose.axial_mm - half), hi.max(v.pose.axial_mm + half)))
}

/// The axial span of `spec`'s views, for sizing a station's frames before it is planned.
pub fn z_span_mm(spec: &SimSpec) -> f64 {
    let (lo, hi) = axial_span(spec);
    hi - lo
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::preset;

    #[test]
    fn random_stations_stay_within_their_ranges_and_repeat_by_seed() {
        let spec = preset("standard").unwrap();
        let r = spec.part.pipe_od_mm / 2.0;
        for seed in 0..200 {
            let s = random(seed, r, z_span_mm(&spec));
            assert_eq!(s, random(seed, r, z_span_mm(&spec)));
            let p = s.object_pixel_mm();
            assert!((0.0295..=0.1505).contains(&p), "seed {seed}: pixel {p}");
            let dof = s.depth_of_field_mm();
            assert!((0.045..=0.65).contains(&dof), "seed {seed}: dof {dof} ({:?})", s.optics);
            assert!((12..=64).contains(&s.views_around));
            assert!((1..=3).contains(&s.axial_rows));
            assert!((2.0..=15.0).contains(&s.overlap_deg));
            let at = at_station(&spec, &s);
            let step = at.offsets_mm[1] - at.offsets_mm[0];
            let step_dof = step / dof;
            assert!((0.29..=1.51).contains(&step_dof), "seed {seed}: step {step_dof} DOF");
            assert!(at.offsets_mm.len() <= ranges::MAX_FRAMES + 1);
            let pixel_frames = at.views.len() as f64 * at.offsets_mm.len() as f64 * (at.width * at.height) as f64;
            assert!(pixel_frames <= ranges::MAX_PIXEL_FRAMES * 1.01 || at.views.len() <= 3 * s.axial_rows);
            // The stack covers the thread: root to crest plus a depth of field either side.
            let span = at.offsets_mm[at.offsets_mm.len() - 1] - at.offsets_mm[0];
            assert!(span >= spec.part.form.height_mm, "seed {seed}: span {span}");
        }
    }

    /// The envelope's classes claim figures over the ranges the station benchmark draws from.
    #[test]
    fn the_benchmarked_envelope_is_the_random_stations_ranges() {
        let b = crate::domain::station::BENCHMARKED;
        assert_eq!(b.object_pixel_mm, ranges::OBJECT_PIXEL_MM);
        assert_eq!(b.depth_of_field_mm, ranges::DEPTH_OF_FIELD_MM);
        assert_eq!(b.frame_step_dof, ranges::FRAME_STEP_DOF);
        assert_eq!(b.overlap_deg, ranges::OVERLAP_DEG);
        // Noise up to 8× the standard sensor's 0.84%: 6.7%.
        assert!(b.frame_noise_percent.1 >= 0.84 * ranges::NOISE_FACTOR.1);
    }

    #[test]
    fn a_named_station_recorded_is_the_one_described() {
        let spec = preset("standard").unwrap();
        let s = station("coarse-survey", 0, spec.part.pipe_od_mm / 2.0, z_span_mm(&spec)).unwrap();
        assert!((s.object_pixel_mm() - 0.12).abs() < 0.002, "{}", s.object_pixel_mm());
        assert!((s.depth_of_field_mm() - 0.48).abs() < 0.05, "{}", s.depth_of_field_mm());
        let at = at_station(&spec, &s);
        assert_eq!(at.views.len(), 16);
        assert!(at.name == "standard@coarse-survey" && at.description.contains("object pixel 0.120 mm"));
        assert!(station("nope", 0, 57.0, 35.0).is_none());
    }
}
