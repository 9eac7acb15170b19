//! Named simulation presets. Optics are chosen so that depth from focus is physically sound: the
//! depth of field (blur circle ≤ 1 pixel) is a fraction of the thread height, and the frame step a
//! fraction of the depth of field. `ci*` presets are small enough for tests.

use super::appearance::Appearance;
use super::part::{MillSurface, PartModel, PolishedPatch};
use super::render::Sensor;
use super::{PoseJitter, SimSpec, ViewPlan};
use crate::bundle::PartManifest;
use crate::domain::optics::{Optics, Projection, ViewPose};
use crate::domain::thread::ConnectionTable;

pub struct PresetInfo {
    pub name: &'static str,
    pub description: &'static str,
}

pub const PRESETS: &[PresetInfo] = &[
    PresetInfo {
        name: "ci",
        description: "BC 4-1/2, 3 views over 13° near Lc, 18 frames of 384×160 RGB; a black crest within Lc across threads 6–7 (accept)",
    },
    PresetInfo {
        name: "ci-telecentric",
        description: "LC 5-1/2 through a 0.2× telecentric lens, 3 views of 320×160, 16-bit gray; full crests within Lc (accept)",
    },
    PresetInfo {
        name: "ci-reject",
        description: "LC 4-1/2 round thread, eccentric pipe, 3 views of 384×160 RGB over its low side: a black crest within Lc (reject)",
    },
    PresetInfo {
        name: "standard",
        description: "BC 4-1/2 pin end, whole circumference (45 views × 20 frames, 864×320 RGB), z 0–35 mm; black crests only beyond Lc (accept)",
    },
    PresetInfo {
        name: "bc-black-1",
        description: "standard optics; 0.1 mm eccentric thread: one black-crested thread within Lc (accept)",
    },
    PresetInfo {
        name: "bc-black-2",
        description: "standard optics; undersize pipe: two black-crested threads within Lc, each under 25% (accept)",
    },
    PresetInfo {
        name: "bc-black-3",
        description: "standard optics; undersize, eccentric pipe: three black-crested threads within Lc (reject)",
    },
    PresetInfo {
        name: "bc-arc-over-25",
        description: "standard optics; a thread black over more than 25% of the circumference within Lc (reject)",
    },
    PresetInfo {
        name: "lc-round-black",
        description: "LC 4-1/2 round thread, oval pipe: a small black arc within Lc (reject)",
    },
    PresetInfo {
        name: "bc-polished",
        description: "standard optics; a black crest within Lc polished to look machined (found only by its geometry)",
    },
    PresetInfo {
        name: "bc-polished-long",
        description: "standard optics; a black crest within Lc polished to look machined over more than a quarter of the turn (reject, found only by its geometry)",
    },
    PresetInfo {
        name: "bc-polished-end",
        description: "standard optics; black crests polished to look machined on threads 1–6, the first next to the end face (reject, found only by their geometry)",
    },
    PresetInfo {
        name: "lc-accept",
        description: "LC 4-1/2 round thread, nominal pipe: black crests only beyond Lc (accept)",
    },
    PresetInfo {
        name: "seed-table1",
        description: "the seed's Table 1: custom 1.000 ± 0.030 mm buttress-type form, ten threads 0.9825 … 0.4216 mm high toward the vanish end, 5 views over 40°",
    },
];

/// The standard camera: 50 mm f/1.4 focused at 220 mm (magnification 0.29), 12 µm pixels (a 6 µm
/// sensor binned 2×2): 41 µm per pixel on the part, depth of field ≈ 0.5 mm (a third of the buttress
/// thread height).
pub(crate) fn standard_optics() -> Optics {
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

fn nominal_mill(od_mm: f64) -> MillSurface {
    MillSurface {
        nominal_radius_mm: od_mm / 2.0,
        undersize_mm: 0.0,
        ovality_mm: 0.0,
        ovality_angle_deg: 0.0,
        eccentricity_mm: 0.0,
        eccentricity_angle_deg: 0.0,
    }
}

/// A table connection's part with its cone placed by the gauge plane (E7 at L7, E1 at L1).
fn connection_part(
    designation: &str,
    mill: impl FnOnce(&mut MillSurface),
    helix_z_h_mm: f64,
) -> (PartManifest, PartModel) {
    let table = ConnectionTable::api5b();
    let conn = table.get(designation).expect("preset designations are in the table");
    let form = conn.form().clone();
    let root_at_end =
        conn.gauge.pitch_diameter_mm / 2.0 - form.pitch_line_height_mm() - conn.gauge.z_mm * form.radius_slope();
    let mut mill_surface = nominal_mill(conn.pipe_od_mm);
    mill(&mut mill_surface);
    let part = PartModel {
        chamfer_radius_at_end_mm: root_at_end - 0.4,
        chamfer_angle_deg: 65.0,
        root_radius_at_end_mm: root_at_end,
        form,
        helix_z_h_mm,
        mill: mill_surface,
        polished: vec![],
        turned_blank_mm: vec![],
        pipe_od_mm: conn.pipe_od_mm,
        lc_mm: conn.lc_mm,
    };
    let manifest = PartManifest { serial: None, connection: Some(conn.designation.clone()), thread: None };
    (manifest, part)
}

/// A mill surface `undersize_mm` under nominal radius (negative: oversize) whose centre is
/// `eccentricity_mm` off the thread axis; the mill surface is lowest, and crests go black first, at
/// `low_side_deg`.
fn eccentric(undersize_mm: f64, eccentricity_mm: f64, low_side_deg: f64) -> impl FnOnce(&mut MillSurface) {
    move |m| {
        m.undersize_mm = undersize_mm;
        m.eccentricity_mm = eccentricity_mm;
        m.eccentricity_angle_deg = low_side_deg + 180.0;
    }
}

pub(crate) struct Layout {
    pub width: u32,
    pub height: u32,
    pub first_angle_deg: f64,
    pub angle_step_deg: f64,
    pub angles: usize,
    pub axials_mm: Vec<f64>,
    pub frame_step_mm: f64,
}

/// Views and frame offsets: each view's lens radius puts the middle of its expected depth range in
/// focus at offset 0; the offsets cover the deepest root to the highest crest in any view, plus the
/// encoder error and a margin of one depth of field.
pub(crate) fn plan(
    part: &PartModel,
    optics: &Optics,
    layout: &Layout,
    jitter: &PoseJitter,
) -> (Vec<ViewPlan>, Vec<f64>) {
    let pixel = optics.object_pixel_mm(optics.focus_distance_mm);
    let half_axial = layout.width as f64 * pixel / 2.0;
    let half_arc = layout.height as f64 * pixel / 2.0;
    let margin = optics.depth_of_field_mm(1.0) + jitter.lens_radius_mm;
    let (mut lo, mut hi) = (f64::MAX, f64::MIN);
    let mut views = Vec::new();
    for (j, &axial) in layout.axials_mm.iter().enumerate() {
        let z_lo = (axial - half_axial).max(0.0);
        let z_hi = axial + half_axial;
        let r_lo = part.root_cone_radius(z_lo).min(part.chamfer_radius_at_end_mm.max(part.root_cone_radius(0.0) - 0.5));
        let r_hi = part.mill.max_radius().min(part.root_cone_radius(z_hi) + part.form.height_mm);
        let r_mid = 0.5 * (r_lo + r_hi);
        let sag = r_mid - (r_mid * r_mid - half_arc * half_arc).sqrt();
        // In focus at offset o when lens_radius + o − r = F, i.e. o = r − r_mid.
        lo = lo.min(r_lo - r_mid - sag - margin);
        hi = hi.max(r_hi - r_mid + margin);
        for i in 0..layout.angles {
            let angle = layout.first_angle_deg + i as f64 * layout.angle_step_deg;
            views.push(ViewPlan {
                id: format!("a{i:03}-z{j:02}"),
                pose: ViewPose { angle_deg: angle, axial_mm: axial, lens_radius_mm: optics.focus_distance_mm + r_mid },
            });
        }
    }
    let n = ((hi - lo) / layout.frame_step_mm).ceil() as usize + 1;
    let start = 0.5 * (lo + hi) - 0.5 * (n - 1) as f64 * layout.frame_step_mm;
    let offsets = (0..n).map(|k| round_um(start + k as f64 * layout.frame_step_mm)).collect();
    (views, offsets)
}

fn round_um(mm: f64) -> f64 {
    (mm * 1000.0).round() / 1000.0
}

const ENCODER_JITTER: PoseJitter = PoseJitter { angle_deg: 1.0, axial_mm: 0.3, lens_radius_mm: 0.05 };

fn spec(
    name: &str,
    part_manifest: PartManifest,
    part: PartModel,
    optics: Optics,
    layout: Layout,
    truth_z_end_mm: f64,
    sensor: Sensor,
) -> SimSpec {
    spec_with_jitter(name, part_manifest, part, optics, layout, truth_z_end_mm, sensor, ENCODER_JITTER)
}

#[allow(clippy::too_many_arguments)]
fn spec_with_jitter(
    name: &str,
    part_manifest: PartManifest,
    part: PartModel,
    optics: Optics,
    layout: Layout,
    truth_z_end_mm: f64,
    sensor: Sensor,
    jitter: PoseJitter,
) -> SimSpec {
    let (views, offsets_mm) = plan(&part, &optics, &layout, &jitter);
    let description = PRESETS.iter().find(|p| p.name == name).map(|p| p.description).unwrap_or_default();
    SimSpec {
        name: name.to_string(),
        description: description.to_string(),
        part_manifest,
        part,
        optics,
        width: layout.width,
        height: layout.height,
        views,
        offsets_mm,
        jitter,
        truth_z_end_mm,
        appearance: Appearance::default(),
        sensor,
        station: None,
        focus_drift_mm: 0.0,
    }
}

/// The whole circumference of the pin end from the chamfer to a little past Lc. Views 8° apart,
/// each 13 mm (13°) wide: neighbours overlap by 5 mm, still 3 mm when two encoders err by 1° apart.
fn ring_layout() -> Layout {
    Layout {
        width: 864,
        height: 320,
        first_angle_deg: 0.0,
        angle_step_deg: 8.0,
        angles: 45,
        axials_mm: vec![17.3],
        frame_step_mm: 0.25,
    }
}

pub fn preset(name: &str) -> Option<SimSpec> {
    let sensor = Sensor::default();
    Some(match name {
        "ci" => {
            let (pm, part) = connection_part("BC 4-1/2", eccentric(-0.259, 0.4, 5.0), 0.8);
            let layout = Layout {
                width: 384,
                height: 160,
                first_angle_deg: 0.0,
                angle_step_deg: 5.0,
                angles: 3,
                axials_mm: vec![26.0],
                frame_step_mm: 0.25,
            };
            spec(name, pm, part, standard_optics(), layout, 33.8, sensor)
        }
        "ci-reject" => {
            // lc-round-black's pipe, seen only over its low side, where the crests stay black.
            let (pm, part) = connection_part("LC 4-1/2", eccentric(0.109, 0.3, 200.0), 1.1);
            let layout = Layout {
                width: 384,
                height: 160,
                first_angle_deg: 195.0,
                angle_step_deg: 5.0,
                angles: 3,
                axials_mm: vec![42.0],
                frame_step_mm: 0.25,
            };
            spec(name, pm, part, standard_optics(), layout, 50.0, sensor)
        }
        "ci-telecentric" => {
            let (pm, part) = connection_part("LC 5-1/2", |_| {}, 2.0);
            // 0.2× telecentric at image-side f/1 (object-side NA 0.1): 29 µm per pixel, depth of
            // field 0.3 mm against the 1.81 mm thread. Its small views overlap by 1 mm, so this
            // fixture's encoders are taken to be finer (±0.2°, ±0.1 mm).
            let optics = Optics {
                projection: Projection::Telecentric,
                // A telecentric lens is described by its magnification (bundle.md).
                focal_length_mm: None,
                f_number: 1.0,
                focus_distance_mm: 110.0,
                pixel_pitch_um: 5.86,
                principal_point_px: None,
                magnification: Some(0.2),
            };
            let layout = Layout {
                width: 320,
                height: 160,
                first_angle_deg: 90.0,
                angle_step_deg: 3.0,
                angles: 3,
                axials_mm: vec![20.0],
                frame_step_mm: 0.15,
            };
            let jitter = PoseJitter { angle_deg: 0.2, axial_mm: 0.1, lens_radius_mm: 0.02 };
            let sensor = Sensor { bit_depth: 16, monochrome: true, ..sensor };
            spec_with_jitter(name, pm, part, optics, layout, 29.0, sensor, jitter)
        }
        "standard" => {
            let (pm, part) = connection_part(
                "BC 4-1/2",
                |m| {
                    m.ovality_mm = 0.2;
                    m.ovality_angle_deg = 30.0;
                },
                1.7,
            );
            spec(name, pm, part, standard_optics(), ring_layout(), 34.5, sensor)
        }
        "bc-black-1" => {
            let (pm, part) = connection_part("BC 4-1/2", eccentric(-0.028, 0.2, 265.0), 1.7);
            spec(name, pm, part, standard_optics(), ring_layout(), 34.5, sensor)
        }
        "bc-black-2" => {
            let (pm, part) = connection_part("BC 4-1/2", eccentric(-0.003, 0.3, 330.0), 1.7);
            spec(name, pm, part, standard_optics(), ring_layout(), 34.5, sensor)
        }
        "bc-black-3" => {
            let (pm, part) = connection_part("BC 4-1/2", eccentric(-0.247, 0.7, 330.0), 1.7);
            spec(name, pm, part, standard_optics(), ring_layout(), 34.5, sensor)
        }
        "bc-arc-over-25" => {
            let (pm, part) = connection_part("BC 4-1/2", eccentric(0.166, 0.1, 300.0), 1.7);
            spec(name, pm, part, standard_optics(), ring_layout(), 34.5, sensor)
        }
        "bc-polished" | "bc-polished-long" | "bc-polished-end" => {
            let mill = match name {
                // Deep enough that the crest is cut short by more than the height tolerance.
                "bc-polished" => eccentric(-0.15, 0.4, 265.0),
                // A pipe 0.5 mm off the thread axis: polished black crests on threads 3–6 whose
                // runs grow from 63° to 192° along the helix (the short preset's is 85°), all clear
                // of the chamfer band at the end face.
                "bc-polished-long" => eccentric(0.27, 0.5, 95.0),
                // A pipe 0.8 mm off the thread axis: polished black crests on threads 1–6, thread
                // 1's and the start of thread 2's within the chamfer zone (1.5 pitches of the end
                // face).
                _ => eccentric(0.27, 0.8, 95.0),
            };
            let (pm, mut part) = connection_part("BC 4-1/2", mill, 1.7);
            part.polished = vec![PolishedPatch { from_deg: 0.0, to_deg: 360.0, z_from_mm: 0.0, z_to_mm: 200.0 }];
            spec(name, pm, part, standard_optics(), ring_layout(), 34.5, sensor)
        }
        "lc-round-black" | "lc-accept" => {
            let black = name == "lc-round-black";
            let mill = if black { eccentric(0.109, 0.3, 200.0) } else { eccentric(0.0, 0.0, 0.0) };
            let (pm, part) = connection_part("LC 4-1/2", mill, 1.1);
            let layout = Layout { axials_mm: vec![25.0], width: 1280, ..ring_layout() };
            spec(name, pm, part, standard_optics(), layout, 50.0, sensor)
        }
        "seed-table1" => seed_table1(sensor),
        _ => return None,
    })
}

/// The seed's Table 1 crest heights (reconstruction = CMM within 0.3 µm), read from the vanish end:
/// thread 10 is the shallowest.
pub const SEED_TABLE1_HEIGHTS_MM: [f64; 10] =
    [0.9825, 0.9823, 0.9792, 0.9799, 0.9828, 0.9486, 0.8211, 0.6655, 0.5129, 0.4216];

/// The seed's premium example as a custom form (BGT2-like buttress, 1.000 ± 0.030 mm, Lc 35.8 mm)
/// whose crests are cut by a turned blank so that, at θ = 0.5°, threads 1…10 have exactly the
/// heights of the seed's Table 1.
fn seed_table1(sensor: Sensor) -> SimSpec {
    use crate::bundle::CustomThread;
    use crate::domain::thread::{Family, ThreadForm};
    let form = ThreadForm::api_buttress(5.08, 1.0, 0.03, 0.0625).expect("valid form");
    let od = 114.3;
    let helix_z_h_mm = 1.0;
    // Root cone: a full crest would reach the mill surface at z = 60 mm, past the ten threads.
    let root_at_end = od / 2.0 - form.height_mm - 60.0 * form.radius_slope();
    let mut part = PartModel {
        chamfer_radius_at_end_mm: root_at_end - 0.4,
        chamfer_angle_deg: 65.0,
        root_radius_at_end_mm: root_at_end,
        form: form.clone(),
        helix_z_h_mm,
        mill: nominal_mill(od),
        polished: vec![],
        turned_blank_mm: vec![],
        pipe_od_mm: od,
        lc_mm: 35.8,
    };
    part.turned_blank_mm = SEED_TABLE1_HEIGHTS_MM
        .iter()
        .enumerate()
        .map(|(i, h)| {
            let z = part.crest_z(i as u32 + 1, 0.5);
            [z, part.root_cone_radius(z) + h]
        })
        .collect();
    let manifest = PartManifest {
        serial: Some("SEED-TABLE1".into()),
        connection: Some("BGT2 4-1/2 (seed)".into()),
        thread: Some(CustomThread {
            family: Some(Family::Buttress),
            pitch_mm: Some(5.08),
            thread_height_mm: Some(1.0),
            height_tolerance_mm: Some(0.03),
            taper_on_diameter: Some(0.0625),
            pipe_od_mm: Some(od),
            lc_mm: Some(35.8),
            ..Default::default()
        }),
    };
    let layout = Layout { width: 1344, first_angle_deg: 0.0, angles: 5, axials_mm: vec![26.5], ..ring_layout() };
    spec("seed-table1", manifest, part, standard_optics(), layout, 52.0, sensor)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_listed_preset_builds_and_names_match() {
        for info in PRESETS {
            let spec = preset(info.name).unwrap_or_else(|| panic!("{}", info.name));
            assert_eq!(spec.name, info.name);
            assert!(spec.offsets_mm.len() >= 3);
            assert!(spec.offsets_mm.windows(2).all(|w| w[1] > w[0]));
        }
        assert!(preset("nope").is_none());
    }

    /// `simulate --list` prints these descriptions: the counts and frame sizes they state are the
    /// plan's (the standard preset once said 19 frames where its plan had 20).
    #[test]
    fn descriptions_state_the_planned_views_frames_and_size() {
        for info in PRESETS {
            let spec = preset(info.name).unwrap();
            let words: Vec<&str> = info.description.split_whitespace().collect();
            for pair in words.windows(2) {
                let Ok(n) = pair[0].parse::<usize>() else { continue };
                let unit = pair[1].trim_end_matches([',', ')', ';']);
                match unit {
                    "views" => assert_eq!(n, spec.views.len(), "{}: {}", info.name, info.description),
                    "frames" => assert_eq!(n, spec.offsets_mm.len(), "{}: {}", info.name, info.description),
                    _ => {}
                }
            }
            for word in &words {
                let word = word.trim_start_matches('(').trim_end_matches([',', ')', ';']);
                if let Some((w, h)) = word.split_once('×')
                    && let (Ok(w), Ok(h)) = (w.parse::<u32>(), h.parse::<u32>())
                {
                    assert_eq!((w, h), (spec.width, spec.height), "{}: {}", info.name, info.description);
                }
            }
        }
    }
}
