//! The simulated pin end: a mill surface (undersize, ovality, eccentricity) into which a tapered
//! helical thread is cut, with the end chamfer; the surface radius is the least of the three, so a
//! crest that would rise above the mill surface keeps it (a black crest), and past the vanish point
//! the unthreaded body remains.

use crate::domain::arcs::arc_length_mm;
use crate::domain::rules::{CrestBin, RuleInput, ThreadObservation};
use crate::domain::thread::{ProfileKernel, ThreadForm};
use serde::{Deserialize, Serialize};
use std::f64::consts::{PI, TAU};

/// The pipe's original outside surface.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MillSurface {
    pub nominal_radius_mm: f64,
    /// Radius below nominal (a pipe under its OD).
    pub undersize_mm: f64,
    /// Largest minus smallest diameter.
    pub ovality_mm: f64,
    pub ovality_angle_deg: f64,
    /// Offset of the mill surface's centre from the thread axis (a thread cut off centre).
    pub eccentricity_mm: f64,
    pub eccentricity_angle_deg: f64,
}

impl MillSurface {
    pub fn radius_at(&self, theta_rad: f64) -> f64 {
        let (sin, cos) = theta_rad.sin_cos();
        MillKernel::new(self).radius(cos, sin)
    }

    pub fn max_radius(&self) -> f64 {
        self.nominal_radius_mm - self.undersize_mm + self.ovality_mm / 4.0 + self.eccentricity_mm
    }
}

/// A patch of mill surface polished to look machined: only geometry gives it away.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PolishedPatch {
    pub from_deg: f64,
    pub to_deg: f64,
    pub z_from_mm: f64,
    pub z_to_mm: f64,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Material {
    /// Cut by the chaser (thread flanks, roots, full crests) or the chamfer tool.
    Machined,
    /// Original mill surface with its scale.
    MillScale,
    /// Original mill surface polished to look machined.
    Polished,
    /// The pipe's end face (z = 0).
    EndFace,
}

impl Material {
    pub fn is_original_surface(self) -> bool {
        matches!(self, Material::MillScale | Material::Polished)
    }
}

/// The mill surface with its angles resolved, evaluated from the direction (cos θ, sin θ).
#[derive(Clone, Copy, Debug)]
struct MillKernel {
    base: f64,
    quarter_ovality: f64,
    ovality_cos2: f64,
    ovality_sin2: f64,
    eccentricity: f64,
    ecc_cos: f64,
    ecc_sin: f64,
}

impl MillKernel {
    fn new(m: &MillSurface) -> Self {
        let (ovality_sin2, ovality_cos2) = (2.0 * m.ovality_angle_deg.to_radians()).sin_cos();
        let (ecc_sin, ecc_cos) = m.eccentricity_angle_deg.to_radians().sin_cos();
        Self {
            base: m.nominal_radius_mm - m.undersize_mm,
            quarter_ovality: m.ovality_mm / 4.0,
            ovality_cos2,
            ovality_sin2,
            eccentricity: m.eccentricity_mm,
            ecc_cos,
            ecc_sin,
        }
    }

    /// Distance from the thread axis to the mill surface in direction θ: an oval of diameters
    /// differing by the ovality, whose centre is `eccentricity` off the axis.
    #[inline]
    fn radius(&self, cos: f64, sin: f64) -> f64 {
        let (cos2, sin2) = (cos * cos - sin * sin, 2.0 * sin * cos);
        let base = self.base + self.quarter_ovality * (cos2 * self.ovality_cos2 + sin2 * self.ovality_sin2);
        let along = cos * self.ecc_cos + sin * self.ecc_sin; // cos(θ − φ)
        let across = sin * self.ecc_cos - cos * self.ecc_sin; // sin(θ − φ)
        let e = self.eccentricity;
        e * along + (base * base - e * e * across * across).sqrt()
    }
}

/// A [`PartModel`] ready for evaluating many points (the ray tracer's inner loop).
#[derive(Clone, Copy, Debug)]
pub struct SurfaceKernel<'a> {
    part: &'a PartModel,
    profile: ProfileKernel,
    mill: MillKernel,
    radius_slope: f64,
    chamfer_slope: f64,
    pitch_per_rad: f64,
}

impl SurfaceKernel<'_> {
    /// Surface radius and material at z ≥ 0 in direction θ, given also as (cos θ, sin θ).
    #[inline]
    pub fn surface(&self, z_mm: f64, theta_rad: f64, cos: f64, sin: f64) -> (f64, Material) {
        let part = self.part;
        let offset = z_mm - part.helix_z_h_mm - self.pitch_per_rad * theta_rad;
        let form = part.root_radius_at_end_mm + z_mm * self.radius_slope + self.profile.height_at(offset);
        let mill = self.mill.radius(cos, sin);
        let chamfer = part.chamfer_radius_at_end_mm + z_mm * self.chamfer_slope;
        let form = form.min(part.turned_blank_radius(z_mm));
        if mill < form && mill < chamfer {
            (mill, if part.is_polished(z_mm, theta_rad) { Material::Polished } else { Material::MillScale })
        } else {
            (form.min(chamfer), Material::Machined)
        }
    }

    /// Surface radius and material under the pipe-frame point (x, y, z), and the point's radius.
    #[inline]
    pub fn surface_under(&self, x: f64, y: f64, z_mm: f64) -> (f64, Material, f64) {
        let r = (x * x + y * y).sqrt();
        let (radius, material) = self.surface(z_mm, y.atan2(x), x / r, y / r);
        (radius, material, r)
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PartModel {
    pub form: ThreadForm,
    /// z of thread 1's crest centre line at θ = 0, in [0, pitch).
    pub helix_z_h_mm: f64,
    /// Root-cone radius at the end face.
    pub root_radius_at_end_mm: f64,
    pub mill: MillSurface,
    /// Chamfer cone: its radius at z = 0 and its angle from the pipe axis.
    pub chamfer_radius_at_end_mm: f64,
    pub chamfer_angle_deg: f64,
    pub polished: Vec<PolishedPatch>,
    /// A machined (turned) outside surface cut before threading, as (z, radius) knots joined
    /// linearly and held constant beyond the ends; empty for none. Crests above it are cut flat.
    #[serde(default)]
    pub turned_blank_mm: Vec<[f64; 2]>,
    pub pipe_od_mm: f64,
    pub lc_mm: f64,
}

impl PartModel {
    /// Radius of the turned blank at z (∞ where there is none).
    pub fn turned_blank_radius(&self, z_mm: f64) -> f64 {
        let knots = &self.turned_blank_mm;
        match knots.len() {
            0 => f64::INFINITY,
            1 => knots[0][1],
            _ => {
                let k = knots.partition_point(|p| p[0] < z_mm).clamp(1, knots.len() - 1);
                let ([z0, r0], [z1, r1]) = (knots[k - 1], knots[k]);
                let t = ((z_mm - z0) / (z1 - z0)).clamp(0.0, 1.0);
                r0 + (r1 - r0) * t
            }
        }
    }

    pub fn root_cone_radius(&self, z_mm: f64) -> f64 {
        self.root_radius_at_end_mm + z_mm * self.form.radius_slope()
    }

    /// Axial offset of z from the crest centre line at angle θ (any value; the form wraps it).
    fn helix_offset(&self, z_mm: f64, theta_rad: f64) -> f64 {
        z_mm - self.helix_z_h_mm - self.form.pitch_mm * theta_rad / TAU
    }

    fn chamfer_radius(&self, z_mm: f64) -> f64 {
        self.chamfer_radius_at_end_mm + z_mm * self.chamfer_angle_deg.to_radians().tan()
    }

    pub fn kernel(&self) -> SurfaceKernel<'_> {
        SurfaceKernel {
            part: self,
            profile: self.form.kernel(),
            mill: MillKernel::new(&self.mill),
            radius_slope: self.form.radius_slope(),
            chamfer_slope: self.chamfer_angle_deg.to_radians().tan(),
            pitch_per_rad: self.form.pitch_mm / TAU,
        }
    }

    /// Surface radius and material at (z ≥ 0, θ).
    pub fn surface(&self, z_mm: f64, theta_rad: f64) -> (f64, Material) {
        let (sin, cos) = theta_rad.sin_cos();
        self.kernel().surface(z_mm, theta_rad, cos, sin)
    }

    pub fn radius(&self, z_mm: f64, theta_rad: f64) -> f64 {
        self.surface(z_mm, theta_rad).0
    }

    fn is_polished(&self, z_mm: f64, theta_rad: f64) -> bool {
        let deg = theta_rad.to_degrees().rem_euclid(360.0);
        self.polished
            .iter()
            .any(|p| (p.z_from_mm..=p.z_to_mm).contains(&z_mm) && (p.from_deg..=p.to_deg).contains(&deg))
    }

    /// Bound on |∂r/∂z| of the surface.
    pub fn max_axial_slope(&self) -> f64 {
        self.form.max_slope().max(self.chamfer_angle_deg.to_radians().tan()) + self.form.radius_slope()
    }

    /// Bound on |∂r/∂θ| (per radian): the helix moves the profile pitch/2π per radian.
    pub fn max_angular_slope(&self) -> f64 {
        self.form.max_slope() * self.form.pitch_mm / TAU + self.mill.ovality_mm + self.mill.eccentricity_mm
    }

    pub fn circumference_mm(&self) -> f64 {
        PI * self.pipe_od_mm
    }

    /// Thread i's crest centre z at θ (degrees, 0..360), per the bundle contract.
    pub fn crest_z(&self, index: u32, theta_deg: f64) -> f64 {
        self.helix_z_h_mm + self.form.pitch_mm * ((index - 1) as f64 + theta_deg / 360.0)
    }

    /// Height of thread i at θ per the contract: crest radius minus the root radius interpolated
    /// linearly between the two adjacent roots at the crest's z. Roots beyond the end face are taken
    /// on the root cone. Also says whether the crest point is the mill surface and whether the end
    /// chamfer cut it.
    pub fn crest_at(&self, index: u32, theta_deg: f64) -> CrestTruth {
        let theta = theta_deg.to_radians();
        let z = self.crest_z(index, theta_deg);
        let (crest_r, material) = self.surface(z, theta);
        let (before, after) = self.form.root_centres_mm();
        let root_r = |dz: f64| {
            let zr = z + dz;
            if zr < 0.0 { self.root_cone_radius(zr) } else { self.radius(zr, theta) }
        };
        let (rb, ra) = (root_r(before), root_r(after));
        let root = rb + (ra - rb) * (0.0 - before) / (after - before);
        let cut = (self.root_cone_radius(z) + self.form.height_at(self.helix_offset(z, theta)))
            .min(self.turned_blank_radius(z));
        let chamfered = material == Material::Machined && self.chamfer_radius(z) < cut;
        CrestTruth { z_mm: z, height_mm: crest_r - root, material, chamfered }
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CrestTruth {
    pub z_mm: f64,
    pub height_mm: f64,
    pub material: Material,
    pub chamfered: bool,
}

/// One thread's truth, in the contract's shape.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ThreadTruth {
    pub index: u32,
    pub height_mm: HeightBins,
    pub black_crest_arcs_deg: Vec<[f64; 2]>,
    pub black_crest_length_mm: f64,
}

/// Heights at 1° bins centred on 0.5°, 1.5°, …; null where the bin lies outside the inspected length.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HeightBins {
    pub angles_deg: Vec<f64>,
    pub values: Vec<Option<f64>>,
}

pub fn bin_centres_deg() -> Vec<f64> {
    (0..360).map(|k| k as f64 + 0.5).collect()
}

/// Angular step for tracing black-crest arcs.
const ARC_STEP_DEG: f64 = 0.01;

impl PartModel {
    /// Truth for threads whose crest line starts at or before `z_end_mm`; bins beyond it are null.
    pub fn thread_truth(&self, z_end_mm: f64) -> (Vec<ThreadTruth>, RuleInput) {
        let mut threads = Vec::new();
        let mut observations = Vec::new();
        let circ = self.circumference_mm();
        let mut index = 1;
        while self.crest_z(index, 0.0) <= z_end_mm {
            let mut values = Vec::with_capacity(360);
            let mut bins = Vec::with_capacity(360);
            for (k, centre) in bin_centres_deg().into_iter().enumerate() {
                let crest = self.crest_at(index, centre);
                let inside = crest.z_mm <= z_end_mm;
                values.push(inside.then_some(crest.height_mm));
                bins.push(CrestBin {
                    angle_deg: k as f64,
                    width_deg: 1.0,
                    z_mm: crest.z_mm,
                    height_mm: inside.then_some(crest.height_mm),
                    chamfer: crest.chamfered,
                    // Every black crest point is already in the traced arcs.
                    on_mill_surface: false,
                    mill_arc_deg: None,
                    // Truth sees every crest.
                    seen: true,
                });
            }
            let arcs = self.black_arcs(index);
            let length = arc_length_mm(&arcs, circ);
            threads.push(ThreadTruth {
                index,
                height_mm: HeightBins { angles_deg: bin_centres_deg(), values },
                black_crest_arcs_deg: arcs.clone(),
                black_crest_length_mm: length,
            });
            observations.push(ThreadObservation { index, black_crest_arcs_deg: arcs, bins });
            index += 1;
        }
        let input = RuleInput {
            family: self.form.family,
            lc_mm: self.lc_mm,
            circumference_mm: circ,
            nominal_height_mm: self.form.height_mm,
            height_tolerance_mm: self.form.height_tolerance_mm,
            threads: observations,
        };
        (threads, input)
    }

    /// Arcs of thread i whose crest point is the original surface and lies within Lc.
    pub fn black_arcs(&self, index: u32) -> Vec<[f64; 2]> {
        let steps = (360.0 / ARC_STEP_DEG).round() as usize;
        let mut arcs: Vec<[f64; 2]> = Vec::new();
        let mut open: Option<f64> = None;
        for s in 0..steps {
            let (a0, a1) = (s as f64 * ARC_STEP_DEG, (s + 1) as f64 * ARC_STEP_DEG);
            let mid = 0.5 * (a0 + a1);
            let crest = self.crest_at(index, mid);
            let black = crest.material.is_original_surface() && crest.z_mm <= self.lc_mm;
            match (black, open) {
                (true, None) => open = Some(a0),
                (false, Some(start)) => {
                    arcs.push([start, a0]);
                    open = None;
                }
                _ => {}
            }
        }
        if let Some(start) = open {
            arcs.push([start, 360.0]);
        }
        arcs
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    pub(crate) fn buttress_part() -> PartModel {
        let form = ThreadForm::api_buttress(5.08, 1.5748, 0.0508, 0.0625).unwrap();
        PartModel {
            root_radius_at_end_mm: 57.15 - 1.5748 - 36.0 * form.radius_slope(),
            form,
            helix_z_h_mm: 0.3,
            mill: MillSurface {
                nominal_radius_mm: 57.15,
                undersize_mm: 0.0,
                ovality_mm: 0.0,
                ovality_angle_deg: 0.0,
                eccentricity_mm: 0.0,
                eccentricity_angle_deg: 0.0,
            },
            chamfer_radius_at_end_mm: 57.15 - 1.5748 - 36.0 / 32.0 - 0.4,
            chamfer_angle_deg: 65.0,
            polished: vec![],
            turned_blank_mm: vec![],
            pipe_od_mm: 114.3,
            lc_mm: 31.84,
        }
    }

    #[test]
    fn full_threads_have_nominal_height_within_a_micrometre() {
        let part = buttress_part();
        let (threads, _) = part.thread_truth(30.0);
        let mut checked = 0;
        for t in &threads {
            for (k, v) in t.height_mm.values.iter().enumerate() {
                let crest = part.crest_at(t.index, t.height_mm.angles_deg[k]);
                if let Some(h) = v
                    && crest.material == Material::Machined
                    && !crest.chamfered
                    && crest.z_mm > 3.0
                {
                    assert!((h - 1.5748).abs() < 1e-3, "thread {} bin {k}: {h}", t.index);
                    checked += 1;
                }
            }
        }
        assert!(checked > 360 * 4, "{checked}");
    }

    #[test]
    fn crests_above_the_mill_surface_are_black_and_lower() {
        let part = buttress_part();
        // Crest meets the mill at z = 36: thread whose crest crosses 36 mm is partly black.
        let (threads, _) = part.thread_truth(45.0);
        let t7 = threads.iter().find(|t| t.index == 7).unwrap(); // z from 31.78 to 36.86
        assert!(t7.black_crest_arcs_deg.is_empty(), "beyond Lc 31.84 only");
        let mut part2 = part.clone();
        part2.mill.undersize_mm = 0.2; // black from z = 36 − 6.4 = 29.6
        let arcs = part2.black_arcs(6); // z 26.7 .. 31.78
        assert_eq!(arcs.len(), 1);
        let z_start = 36.0 - 0.2 * 32.0;
        let expected_start = (z_start - part2.crest_z(6, 0.0)) / 5.08 * 360.0;
        assert!((arcs[0][0] - expected_start).abs() < 0.05, "{arcs:?} vs {expected_start}");
        assert_eq!(arcs[0][1], 360.0);
        let crest = part2.crest_at(6, 359.0);
        assert_eq!(crest.material, Material::MillScale);
        assert!(crest.height_mm < 1.5748);
    }

    #[test]
    fn chamfer_truncates_the_first_thread_and_is_machined() {
        let part = buttress_part();
        let crest = part.crest_at(1, 0.5);
        assert!(crest.chamfered);
        assert_eq!(crest.material, Material::Machined);
        assert!(crest.height_mm < 1.0, "{}", crest.height_mm);
    }
}
