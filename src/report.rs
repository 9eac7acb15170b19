//! The inspection report: the truth file's fields with the same names and meanings
//! (../shared/spec/bundle.md, "Result shape"), plus measures, timings and diagnostics.

use crate::profile::Helix;
use crate::register::Registration;
use crate::rules::{Assessment, Verdict};
use crate::thread::Family;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HeightSeries {
    pub angles_deg: Vec<f64>,
    /// null where the views did not cover the bin.
    pub values: Vec<Option<f64>>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ThreadReport {
    pub index: u32,
    pub height_mm: HeightSeries,
    pub black_crest_arcs_deg: Vec<[f64; 2]>,
    pub black_crest_length_mm: f64,
    // Extras.
    pub crest_z_mm: [f64; 2],
    pub min_height_mm: Option<f64>,
    pub mean_height_mm: Option<f64>,
    pub max_height_mm: Option<f64>,
    pub bins_measured: usize,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StageTiming {
    pub stage: String,
    pub seconds: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Report {
    pub connection: Option<String>,
    pub family: Family,
    pub pipe_od_mm: f64,
    pub lc_mm: f64,
    pub circumference_mm: f64,
    pub pitch_mm: f64,
    pub nominal_height_mm: f64,
    pub threads: Vec<ThreadReport>,
    pub verdict: Verdict,
    pub reasons: Vec<String>,
    // Extras.
    pub serial: Option<String>,
    pub height_tolerance_mm: f64,
    pub assessment: Assessment,
    pub helix: Helix,
    pub registration: Registration,
    /// The end face's silhouette, when the views showed it: the ring's axial offset it found and
    /// took out of every pose (registration cannot observe it).
    #[serde(default)]
    pub end_face: Option<crate::endface::EndFace>,
    pub depth_coverage: f64,
    pub map_coverage: f64,
    pub machined_crest_gray: f32,
    /// The machined crest cone the geometric black-crest test measured crests against.
    pub crest_cone: Option<crate::crest::CrestCone>,
    pub timings: Vec<StageTiming>,
    /// Peak resident memory of the process (Linux VmHWM), when known.
    pub peak_memory_mb: Option<f64>,
}

impl Report {
    /// A short human summary: verdict, the reasons, thread height statistics.
    pub fn summary(&self) -> String {
        let heights: Vec<f64> =
            self.threads.iter().flat_map(|t| t.height_mm.values.iter().flatten().copied()).collect();
        let full: Vec<f64> = heights
            .iter()
            .copied()
            .filter(|h| (h - self.nominal_height_mm).abs() <= self.height_tolerance_mm)
            .collect();
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
        let mut out = format!(
            "{} {}: {}\n",
            self.serial.as_deref().unwrap_or("(no serial)"),
            self.connection.as_deref().unwrap_or("custom thread"),
            self.verdict.as_str().to_uppercase()
        );
        for r in &self.reasons {
            out.push_str(&format!("  {r}\n"));
        }
        out.push_str(&format!(
            "  {} threads, {} height bins; full crests {:.4} mm mean (nominal {:.4} ± {:.4}); helix z_h {:.3} mm\n",
            self.threads.len(),
            heights.len(),
            mean(&full),
            self.nominal_height_mm,
            self.height_tolerance_mm,
            self.helix.z_h_mm
        ));
        match &self.end_face {
            Some(end) => out.push_str(&format!(
                "  z from the end face: the ring's axial offset {:+.1} µm taken out ({} views, scatter {:.1} µm)\n",
                1e3 * end.z_offset_mm,
                end.views,
                end.scatter_um
            )),
            None => out.push_str("  z from the encoders (no end face in view)\n"),
        }
        // The mesh and the profile run at the same time: together they take the longer of the two.
        let seconds_of = |stage: &str| self.timings.iter().find(|t| t.stage == stage).map(|t| t.seconds);
        let overlap = match (seconds_of("mesh"), seconds_of("profile")) {
            (Some(mesh), Some(profile)) => mesh.min(profile),
            _ => 0.0,
        };
        let total: f64 = self.timings.iter().map(|t| t.seconds).sum::<f64>() - overlap;
        let stages: Vec<String> = self
            .timings
            .iter()
            .map(|t| match t.stage.as_str() {
                "profile" if overlap > 0.0 => format!("beside it profile {:.2}", t.seconds),
                _ => format!("{} {:.2}", t.stage, t.seconds),
            })
            .collect();
        out.push_str(&format!(
            "  {:.2} s ({}){}",
            total,
            stages.join(", "),
            self.peak_memory_mb.map(|m| format!("; peak memory {m:.0} MB")).unwrap_or_default()
        ));
        out
    }
}

/// Peak resident set size of this process in MB (Linux), read from /proc/self/status.
pub fn peak_memory_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}
