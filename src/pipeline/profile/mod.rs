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
    /// Why the bin has no height (None where it has one, and in reports stored before reasons
    /// were kept).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unmeasured: Option<Unmeasured>,
}

/// Why a bin has no height: the first of its windows (crest, then the roots) that gave no level,
/// and what that window lacked. The counts go into the report per thread, so that a low coverage
/// says whether the surface was missing (no view resolved it), too thinly sampled for the window
/// (fused cells coarse against a crest arc), or one-sided (a flank's pixels rejected, leaving the
/// centre to extrapolation).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Unmeasured {
    /// A root window reaches past the end face or into the map's first row on the part: there is
    /// no adjacent root to measure from.
    RootOffPart,
    /// The crest window holds no fused cell: no view resolved the surface there.
    CrestNoSurface,
    /// The crest window holds fewer than six cells.
    CrestTooFewSamples,
    /// The crest window's cells (all, or those its own surface kept) lie to one side of its
    /// centre: the level there would be an extrapolation.
    CrestOneSided,
    /// A root window holds no fused cell.
    RootNoSurface,
    /// A root window holds fewer than six cells.
    RootTooFewSamples,
    /// A root window's cells lie to one side of its centre.
    RootOneSided,
    /// The profile-correction model answered no finite height for the bin's pitch.
    ModelNotFinite,
}

impl Unmeasured {
    pub const ALL: [Unmeasured; 8] = [
        Self::RootOffPart,
        Self::CrestNoSurface,
        Self::CrestTooFewSamples,
        Self::CrestOneSided,
        Self::RootNoSurface,
        Self::RootTooFewSamples,
        Self::RootOneSided,
        Self::ModelNotFinite,
    ];

    /// The reason's name as the report's JSON spells it.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::RootOffPart => "root_off_part",
            Self::CrestNoSurface => "crest_no_surface",
            Self::CrestTooFewSamples => "crest_too_few_samples",
            Self::CrestOneSided => "crest_one_sided",
            Self::RootNoSurface => "root_no_surface",
            Self::RootTooFewSamples => "root_too_few_samples",
            Self::RootOneSided => "root_one_sided",
            Self::ModelNotFinite => "model_not_finite",
        }
    }

    fn of_window(miss: heights::WindowMiss, crest: bool) -> Self {
        use heights::WindowMiss::*;
        match (miss, crest) {
            (Empty, true) => Self::CrestNoSurface,
            (TooFew, true) => Self::CrestTooFewSamples,
            (OneSided, true) => Self::CrestOneSided,
            (Empty, false) => Self::RootNoSurface,
            (TooFew, false) => Self::RootTooFewSamples,
            (OneSided, false) => Self::RootOneSided,
        }
    }
}

/// How many bins had no height for one reason.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct UnmeasuredCount {
    /// Why.
    pub reason: Unmeasured,
    /// How many bins.
    pub bins: usize,
}

/// The unmeasured bins of `bins` counted by reason, in [`Unmeasured::ALL`]'s order, reasons
/// with none left out.
pub fn count_unmeasured<'a>(bins: impl IntoIterator<Item = &'a BinMeasure>) -> Vec<UnmeasuredCount> {
    let mut counts = [0usize; Unmeasured::ALL.len()];
    for b in bins {
        if b.height_mm.is_none()
            && let Some(reason) = b.unmeasured
        {
            counts[reason as usize] += 1;
        }
    }
    listed(counts)
}

/// Counts by reason summed over several lists, in the same form.
pub fn sum_unmeasured<'a>(lists: impl IntoIterator<Item = &'a [UnmeasuredCount]>) -> Vec<UnmeasuredCount> {
    let mut counts = [0usize; Unmeasured::ALL.len()];
    for c in lists.into_iter().flatten() {
        counts[c.reason as usize] += c.bins;
    }
    listed(counts)
}

fn listed(counts: [usize; Unmeasured::ALL.len()]) -> Vec<UnmeasuredCount> {
    Unmeasured::ALL
        .into_iter()
        .zip(counts)
        .filter(|(_, n)| *n > 0)
        .map(|(reason, bins)| UnmeasuredCount { reason, bins })
        .collect()
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
    /// ([`pitch::correct_heights`]; needs ONNX Runtime): `on`, `off`, or `auto`: where the model's
    /// card says it is known to help threads of this family at this object pixel
    /// ([`choose_correction`]; docs/models.md).
    pub correction: Correction,
    /// The correction model by name: a shipped one or one installed in the models folder
    /// (docs/models.md); none: the shipped model.
    pub correction_model: Option<String>,
    /// Place each bin's windows where the generatrices within half a view's spacing of it read the
    /// crests ([`Helix::with_local_phase`]), rather than at the one helix: a view placed off along
    /// z shows its crests off the helix.
    pub local_phase: bool,
}

/// Whether the profile-correction MLP runs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Correction {
    Off,
    On,
    #[default]
    Auto,
}

/// Whether the profile correction ran, and why: what its model is known to do here, and the
/// change it made per thread.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct CorrectionChoice {
    /// The option as given: `on` or `auto`.
    pub mode: Correction,
    /// The model's name.
    pub model: String,
    /// Whether it changed the heights.
    #[serde(rename = "ran")]
    pub run: bool,
    /// What the model's card measured for this family of threads at this object pixel (absent
    /// where it measured nothing there).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub effect: Option<crate::learned::effect::EffectEntry>,
    /// Why it ran or did not, in words.
    pub why: String,
    /// Per thread, the RMS change the model made to its heights (corrected − classical), µm.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub change_by_thread: Vec<ThreadChange>,
}

impl CorrectionChoice {
    /// The corrected heights' error per micrometre of change: the card's, or 1 where it measured
    /// nothing here (a correction no one checked is as uncertain as it is large).
    pub fn error_per_change(&self) -> f64 {
        self.effect.as_ref().map_or(1.0, |e| e.error_per_change)
    }
}

/// One thread's RMS change, µm.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ThreadChange {
    /// The thread's number.
    pub thread: u32,
    /// The RMS change of its heights, µm.
    pub rms_um: f64,
    /// The bins it is over (those with a height before and after).
    pub bins: usize,
}

/// Whether the profile correction runs for a part of `family` at a station of `object_pixel_mm`,
/// with the model: None where the option is `off`. Under `auto` it runs where the model's card
/// says it helps there ([`crate::learned::effect::EffectEntry::helps`]) and nowhere its card
/// measured nothing; under `on`, always. An unknown model name is an error under both.
pub fn choose_correction(
    options: &ProfileOptions,
    models: &crate::learned::Models,
    family: crate::domain::thread::Family,
    object_pixel_mm: f64,
) -> Result<Option<(CorrectionChoice, std::sync::Arc<crate::learned::Model>)>, crate::learned::LearnedError> {
    if options.correction == Correction::Off {
        return Ok(None);
    }
    let model = models.get(crate::learned::ModelRole::ProfileCorrection, options.correction_model.as_deref())?;
    let effect = model.effect.as_ref().and_then(|e| e.at(family, object_pixel_mm)).cloned();
    let family_name = match family {
        crate::domain::thread::Family::Round => "round",
        crate::domain::thread::Family::Buttress => "buttress",
    };
    let known = |e: &crate::learned::effect::EffectEntry| {
        format!(
            "on {} of {} measured {family_name} cases with object pixels {:.3}–{:.3} mm it brought the heights closer \
             to truth (median RMS {:.1} µm classical, {:.1} µm corrected)",
            e.better_cases, e.cases, e.object_pixel_mm[0], e.object_pixel_mm[1], e.classical_rms_um, e.corrected_rms_um
        )
    };
    let (run, why) = match (options.correction, &effect) {
        (Correction::On, Some(e)) => (true, format!("Asked for (on); {}.", known(e))),
        (Correction::On, None) => (
            true,
            format!(
                "Asked for (on); its card measured nothing for {family_name} threads at {object_pixel_mm:.3} mm \
                 pixels, so each height's U carries the whole change it made."
            ),
        ),
        (_, Some(e)) if e.helps() => (true, format!("Run by auto: {}.", known(e))),
        (_, Some(e)) => (false, format!("Not run by auto: {}, which is not known to help.", known(e))),
        (_, None) => (
            false,
            format!(
                "Not run by auto: its card measured nothing for {family_name} threads at {object_pixel_mm:.3} mm pixels."
            ),
        ),
    };
    let choice = CorrectionChoice {
        mode: options.correction,
        model: model.identity.name.clone(),
        run,
        effect,
        why,
        change_by_thread: Vec::new(),
    };
    Ok(Some((choice, model)))
}

/// Per thread of `corrected`, the RMS of its heights' change from `classical` over the bins both
/// have, µm; threads with no such bin left out.
pub fn change_by_thread(classical: &[ThreadMeasure], corrected: &[ThreadMeasure]) -> Vec<ThreadChange> {
    corrected
        .iter()
        .filter_map(|t| {
            let before = classical.iter().find(|c| c.index == t.index)?;
            let changes: Vec<f64> =
                before.bins.iter().zip(&t.bins).filter_map(|(b, a)| Some(a.height_mm? - b.height_mm?)).collect();
            (!changes.is_empty()).then(|| ThreadChange {
                thread: t.index,
                rms_um: 1e3 * (changes.iter().map(|c| c * c).sum::<f64>() / changes.len() as f64).sqrt(),
                bins: changes.len(),
            })
        })
        .collect()
}

impl Default for ProfileOptions {
    fn default() -> Self {
        Self {
            height_window_half_bins: 5,
            correction: Correction::default(),
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
