//! Thread profile: the helix (phase z_h, pitch, taper) by Fourier analysis along the generatrix,
//! then every thread's height per 1° bin measured on the fused map per the bundle contract.
//!
//! Along one generatrix the surface is r(z) = taper line + the thread form shifted to the crest
//! positions. Removing the line leaves the thread spectrum: its fundamental at 1/pitch carries the
//! crest position in its phase (offset by the form's own fundamental phase, known analytically for
//! asymmetric forms such as buttress). Combining bins gives z_h, the crest of thread 1 at θ = 0.
//! Heights are then measured directly on the data, at the contract's points: the crest on its
//! centre line and the two adjacent roots at their centres, each by a local least-squares fit over
//! the flat (or arc) around that point, so that noise averages out and edges are avoided.

mod heights;
mod helix;
pub mod pitch;

pub use heights::{crest_window_half_mm, measure_threads, phase_height_rms_mm, smooth_along_helix, survey_threads};
pub use helix::{PhaseError, PhaseUncertainty, estimate_helix, refine_helix};

#[cfg(test)]
use crate::domain::thread::ProfileShape;
use crate::domain::thread::ThreadForm;
use crate::numeric::lsq::fit_line;
use crate::numeric::sequence::trimmed_mean_counted;
use crate::numeric::stats::median;
use crate::pipeline::surface::UnrolledMap;
use rayon::prelude::*;
use rustfft::FftPlanner;
use rustfft::num_complex::Complex;
use serde::{Deserialize, Serialize};
use std::f64::consts::TAU;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Helix {
    /// z of thread 1's crest centre line at θ = 0, in [0, pitch).
    pub z_h_mm: f64,
    /// The pitch the helix was fitted with, mm.
    pub pitch_mm: f64,
    /// Measured taper on diameter (from the detrended generatrix slope).
    pub taper_on_diameter: f64,
    /// RMS of the analytic profile (nominal form at the measured phase, taper line) against data.
    pub fit_rms_um: f64,
    /// The 1° bins (generatrices) the helix was fitted over.
    pub bins_used: usize,
    /// The measured profile's fundamental over the nominal form's (median over the bins used):
    /// under 1 where depth from focus flattens the profile. None in reports stored before it was.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub amplitude_ratio: Option<f64>,
    /// Each 1° bin's own reading of z_h (bin, mm), from the generatrices the phase was combined
    /// over: where they disagree, windows placed by the one helix sit off some crests
    /// ([`Helix::phase_uncertainty`]). Not reported.
    #[serde(skip)]
    pub phase_readings: Vec<(u16, f64)>,
    /// Per 1° bin, where the generatrices about it read the crests along z relative to z_h, mm
    /// ([`Helix::with_local_phase`]); empty: every bin at z_h. Not reported.
    #[serde(skip)]
    pub local_offsets_mm: Vec<f64>,
}

/// One thread at one 1° bin.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct BinMeasure {
    /// Bin centre.
    pub angle_deg: f64,
    pub crest_z_mm: f64,
    pub height_mm: Option<f64>,
    pub crest_radius_mm: Option<f64>,
    /// Mean brightness of the crest (all-in-focus), for the photometric black-crest test.
    pub crest_gray: Option<f32>,
    /// The bin's own fit, before the trimmed mean along the helix, and how many bins that mean
    /// kept (1: the bin's own).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub raw_height_mm: Option<f64>,
    #[serde(default)]
    pub kept_bins: usize,
    /// The expanded uncertainty (k = 2) of `height_mm`, set by the uncertainty stage.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub uncertainty_mm: Option<f64>,
}

/// How the profile stage reports heights.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ProfileOptions {
    /// Each 1° bin's reported height is the trimmed mean of the 2h + 1 bins centred on it along
    /// the helix (a quarter of them, rounded down, dropped at each end: the middle 7 of 11), h
    /// being this half width (fewer at the ends of a measured run). One bin's own fit scatters by
    /// several µm (its depth is noisy and the fit spans a few dozen samples); the thread's true
    /// height changes slowly along the helix (taper, run-out, the mill surface meeting the cone at
    /// a shallow angle), so averaging over a few degrees lowers the scatter, and the trimming
    /// keeps a spike out. The price is resolution: a dent of a degree or two is trimmed away and
    /// one of a few degrees flattened. 0 reports each bin's own fit.
    pub height_window_half_bins: usize,
    /// Correct each bin's pitch of profile with the seed's MLP before its height is taken
    /// ([`pitch::correct_heights`]; needs ONNX Runtime): `on`, `off`, or `auto`: where the
    /// station's object pixel exceeds `correction_min_pixel_mm`.
    pub correction: Correction,
    /// The object pixel, mm, above which `auto` corrects: the MLP helps where the classical fits
    /// are coarse and adds error where they are already close (measured: docs/models.md).
    pub correction_min_pixel_mm: f64,
    /// The correction model by name: a shipped one or one installed in the models folder
    /// (docs/models.md); none: the shipped model.
    pub correction_model: Option<String>,
    /// Place each bin's windows where the generatrices within half a view's spacing of it read the
    /// crests ([`Helix::with_local_phase`]), rather than at the one helix: a view placed off along
    /// z shows its crests off the helix.
    pub local_phase: bool,
}

/// Whether the profile-correction MLP runs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Correction {
    Off,
    On,
    #[default]
    Auto,
}

impl Correction {
    /// Whether the MLP is wanted at a station of this object pixel.
    pub fn wanted(self, object_pixel_mm: f64, min_pixel_mm: f64) -> bool {
        match self {
            Correction::Off => false,
            Correction::On => true,
            Correction::Auto => object_pixel_mm > min_pixel_mm,
        }
    }
}

impl Default for ProfileOptions {
    fn default() -> Self {
        Self {
            height_window_half_bins: 5,
            correction: Correction::default(),
            correction_min_pixel_mm: 0.06,
            correction_model: None,
            local_phase: true,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ThreadMeasure {
    pub index: u32,
    pub bins: Vec<BinMeasure>,
}

#[cfg(test)]
mod tests;
