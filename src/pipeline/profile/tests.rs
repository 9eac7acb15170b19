use super::*;

use crate::pipeline::profile::heights::{
    Section, WindowMiss, fit_at_centre, fit_curvature, fit_line_checked, nominal_curvatures,
};
use crate::pipeline::profile::helix::{form_fundamental, fundamental_beside_a_line};
use crate::pipeline::surface::GridSpec;

/// A synthetic fused map of an ideal buttress thread.
fn ideal_map(z_h: f64, noise: f64) -> (UnrolledMap, ThreadForm) {
    ideal_map_of(ThreadForm::api_buttress(5.08, 1.5748, 0.0508, 0.0625).unwrap(), z_h, noise)
}

/// A synthetic fused map of an ideal thread of `form`, with uniform noise of ± `noise` mm.
fn ideal_map_of(form: ThreadForm, z_h: f64, noise: f64) -> (UnrolledMap, ThreadForm) {
    let pitch = form.pitch_mm;
    let grid = GridSpec { z0_mm: 0.0, dz_mm: 0.04, nz: 800, ntheta: 1440 };
    let mut radius = Vec::with_capacity(grid.nz * grid.ntheta);
    let mut seed = 12345u64;
    for iz in 0..grid.nz {
        for it in 0..grid.ntheta {
            let (z, theta) = (grid.z_at(iz), grid.theta_deg_at(it));
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let jitter = ((seed >> 33) as f64 / (1u64 << 31) as f64 - 0.5) * 2.0 * noise;
            let r = 55.0 + z * form.radius_slope() + form.height_at(z - z_h - pitch * theta / 360.0) + jitter;
            radius.push(r as f32);
        }
    }
    let cells = radius.len();
    (UnrolledMap { grid, radius_mm: radius, weight: vec![1.0; cells], rgb: vec![[0.6; 3]; cells] }, form)
}

/// Threads vanishing towards the far end (their roots rising, as on the seed's Table 1 part)
/// pull the whole-length phase of an asymmetric form; read over the full threads alone (and
/// with the taper line fitted beside the harmonics), the phase is the crests' again.
#[test]
fn the_helix_phase_is_read_over_the_full_threads() {
    let z_h = 1.234;
    let (mut map, form) = ideal_map(z_h, 0.0);
    let g = map.grid.clone();
    // From z = 26 mm the roots rise 0.25 mm per mm above the root cone.
    for iz in 0..g.nz {
        let floor_mm = 55.0 + g.z_at(iz) * form.radius_slope() + 0.25 * (g.z_at(iz) - 26.0).max(0.0);
        for it in 0..g.ntheta {
            let i = map.index(iz, it);
            map.radius_mm[i] = map.radius_mm[i].max(floor_mm as f32);
        }
    }
    let first = estimate_helix(&map, &form).unwrap();
    let threads = measure_threads(&map, &form, &first, &ProfileOptions::default());
    let refined = refine_helix(&map, &form, &first, &threads);
    assert!(refined.z_h_mm != first.z_h_mm, "two full threads were found, so the phase was read again");
    let after_um = 1e3 * (refined.z_h_mm - z_h).abs();
    assert!(after_um < 1.0, "full threads {after_um} µm");
    // The survey of every sixth bin (what the pipeline hands refine_helix) finds the same full
    // threads, so the same helix, bit for bit.
    let surveyed = survey_threads(&map, &form, &first, &ProfileOptions::default());
    assert!(surveyed.iter().all(|t| t.bins.len() == 60 && t.bins[1].angle_deg == 6.5), "every sixth bin");
    assert_eq!(refine_helix(&map, &form, &first, &surveyed), refined);
}

/// Over a few pitches of an asymmetric (buttress) form on a taper, a line removed first takes
/// part of the thread with it and shifts the fundamental's phase; fitted beside the harmonics
/// it does not.
#[test]
fn the_fundamental_is_fitted_beside_the_taper_line() {
    let form = ThreadForm::api_buttress(5.08, 1.5748, 0.0508, 0.0625).unwrap();
    let p = form.pitch_mm;
    let phase_form = form_fundamental(&form).arg();
    let z_crest = 1.1;
    let samples: Vec<(f64, f64)> = (0..381)
        .map(|k| 0.04 * k as f64 + z_crest - 0.5 * p)
        .map(|z| (z, 55.0 + form.radius_slope() * z + form.height_at(z - z_crest)))
        .collect();
    let crest_from = |c: Complex<f64>| (phase_form - c.arg()) * p / TAU;
    let joint = crest_from(fundamental_beside_a_line(samples.iter().copied(), p).unwrap());
    let (z, r): (Vec<f64>, Vec<f64>) = samples.iter().copied().unzip();
    let (a, b) = fit_line(&z, &r);
    let line_first =
        crest_from(z.iter().zip(&r).map(|(&z, &r)| Complex::from_polar(r - a - b * z, -TAU * z / p)).sum());
    let wrap = |x: f64| 1e3 * ((x - z_crest + 0.5 * p).rem_euclid(p) - 0.5 * p).abs();
    assert!(
        wrap(joint) < 0.2 && wrap(line_first) > 1.0,
        "joint {} µm, line first {} µm",
        wrap(joint),
        wrap(line_first)
    );
}

#[test]
fn helix_and_heights_of_an_ideal_thread() {
    let (map, form) = ideal_map(1.234, 0.0);
    let helix = estimate_helix(&map, &form).unwrap();
    assert!((helix.z_h_mm - 1.234).abs() < 0.01, "{}", helix.z_h_mm);
    assert!((helix.taper_on_diameter - 0.0625).abs() < 0.005, "{}", helix.taper_on_diameter);
    let threads = measure_threads(&map, &form, &helix, &ProfileOptions::default());
    let mut checked = 0;
    for t in &threads {
        for b in &t.bins {
            if let Some(h) = b.height_mm {
                assert!((h - 1.5748).abs() < 0.002, "thread {} at {}: {h}", t.index, b.angle_deg);
                checked += 1;
            }
        }
    }
    assert!(checked > 360 * 4, "{checked}");
}

#[test]
fn noise_averages_out() {
    let (map, form) = ideal_map(3.9, 0.06);
    let helix = estimate_helix(&map, &form).unwrap();
    assert!((helix.z_h_mm - 3.9).abs() < 0.02, "{}", helix.z_h_mm);
    let threads = measure_threads(&map, &form, &helix, &ProfileOptions::default());
    let heights: Vec<f64> = threads.iter().flat_map(|t| t.bins.iter().filter_map(|b| b.height_mm)).collect();
    let rms = (heights.iter().map(|h| (h - 1.5748).powi(2)).sum::<f64>() / heights.len() as f64).sqrt();
    assert!(rms < 0.01, "{rms}");
}

/// The map's first cell on the part holds the end face's edge, whose silhouette pulls the
/// fused radius off the surface: no root window reaches into it.
#[test]
fn the_end_face_cell_is_not_taken_for_a_root() {
    let form = ThreadForm::api_round(3.175, 1.810, 0.05, 0.0625, None).unwrap();
    let (mut map, form) = ideal_map_of(form, 1.1, 0.01);
    let helix = estimate_helix(&map, &form).unwrap();
    let options = ProfileOptions { height_window_half_bins: 0, ..Default::default() };
    let clean = measure_threads(&map, &form, &helix, &options);
    // The edge reads 12 µm low all round (within the noise's reach: no outlier to reject).
    let ntheta = map.grid.ntheta;
    map.radius_mm[..ntheta].iter_mut().for_each(|r| *r -= 0.012);
    let edged = measure_threads(&map, &form, &helix, &options);
    // Every height as before, but for the shared section's curvature, refitted over windows
    // that include the edge (−0.017 µm on every bin here), and the window fit's half of nearest
    // samples, which a change that small can swap a sample of (up to 0.12 µm on a bin here).
    // With the root windows allowed into the edge cell, thread 1's first bin reads +0.44 µm.
    let mut measured = 0;
    for (e, c) in edged[0].bins.iter().zip(&clean[0].bins) {
        assert_eq!(e.height_mm.is_some(), c.height_mm.is_some());
        if let (Some(edged_mm), Some(clean_mm)) = (e.height_mm, c.height_mm) {
            assert!((edged_mm - clean_mm).abs() < 2.5e-4, "{}° moved {} µm", e.angle_deg, (edged_mm - clean_mm) * 1e3);
            measured += 1;
        }
    }
    assert!(measured > 200, "{measured}");
}

/// A round thread's crest and root arcs: the shared curvature is measured from the map (here
/// the form's own, ∓1/2ρ) and the heights come out unbiased with less scatter than a free
/// curvature per bin would give.
#[test]
fn round_thread_heights_with_a_shared_section() {
    let form = ThreadForm::api_round(3.175, 1.810, 0.05, 0.0625, None).unwrap();
    let nominal = form.height_mm;
    let (crest_c, root_c) = nominal_curvatures(&form).unwrap();
    assert!(crest_c < 0.0 && root_c > 0.0, "{crest_c} {root_c}");
    let (map, form) = ideal_map_of(form, 2.2, 0.03);
    let helix = estimate_helix(&map, &form).unwrap();
    assert!((helix.z_h_mm - 2.2).abs() < 0.02, "{}", helix.z_h_mm);
    let threads = measure_threads(&map, &form, &helix, &ProfileOptions::default());
    let heights: Vec<f64> = threads.iter().flat_map(|t| t.bins.iter().filter_map(|b| b.height_mm)).collect();
    assert!(heights.len() > 360 * 5, "{}", heights.len());
    let mean = heights.iter().sum::<f64>() / heights.len() as f64;
    let rms = (heights.iter().map(|h| (h - nominal).powi(2)).sum::<f64>() / heights.len() as f64).sqrt();
    assert!((mean - nominal).abs() < 0.002, "bias {}", mean - nominal);
    assert!(rms < 0.006, "{rms}");
}

#[test]
fn fixed_section_fit_recovers_the_centre_of_an_arc() {
    let radius = 0.45;
    let section = Section::Parabola { c_per_mm: -0.5 / radius };
    // An arc seen from x = −0.25 … 0.25 mm, tilted by the taper.
    let pts: Vec<(f64, f64)> =
        (0..=50).map(|i| -0.25 + 0.01 * i as f64).map(|x| (x, 10.0 + 0.03 * x - x * x / (2.0 * radius))).collect();
    let centre = fit_at_centre(&pts, section, 0.25, 0.9).unwrap();
    assert!((centre - 10.0).abs() < 1e-9, "{centre}");
    let measured = fit_curvature(&pts).unwrap();
    assert!((measured + 0.5 / radius).abs() < 1e-6, "{measured}");
    // Samples on one side only: an extrapolation, refused.
    assert_eq!(fit_at_centre(&pts[30..], section, 0.25, 0.9), Err(WindowMiss::OneSided));
    // Nothing, or too little to fit, each named.
    assert_eq!(fit_at_centre(&[], section, 0.25, 0.9), Err(WindowMiss::Empty));
    assert_eq!(fit_at_centre(&pts[..5], section, 0.25, 0.9), Err(WindowMiss::TooFew));
}

/// A root window near a flank: two thirds of its samples on the root (with noise), a third that
/// took the crest's depth a thread height up, crowded at the window's end nearest the crest.
fn contaminated_root_window(contaminated_share: f64) -> Vec<(f64, f64)> {
    let (half, height, n) = (0.7, 1.5748, 150usize);
    let mut seed = 7u64;
    let mut noise = move || {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((seed >> 33) as f64 / (1u64 << 31) as f64 - 0.5) * 0.06
    };
    let bled = (contaminated_share * n as f64) as usize;
    (0..n)
        .map(|i| {
            if i < bled {
                // The crest's depth, at the window's last 40%.
                (half * (0.2 + 0.8 * i as f64 / bled as f64), 50.0 + height + noise())
            } else {
                (-half + 2.0 * half * (i - bled) as f64 / (n - bled) as f64, 50.0 + noise())
            }
        })
        .collect()
}

#[test]
fn a_window_fit_is_not_pulled_by_a_third_of_its_samples_from_the_other_surface() {
    for share in [0.0, 0.2, 0.35, 0.45] {
        let pts = contaminated_root_window(share);
        let level = fit_at_centre(&pts, Section::Flat, 0.7, 0.5 * 1.5748).unwrap();
        assert!((level - 50.0).abs() < 0.01, "{share}: {level}");
    }
    // The one-pass rejection this replaced: a least-squares line and 3 MAD about it keep the
    // crest's samples at 35% and land hundreds of µm off.
    let pts = contaminated_root_window(0.35);
    let (a, b) = fit_line(&pts.iter().map(|p| p.0).collect::<Vec<_>>(), &pts.iter().map(|p| p.1).collect::<Vec<_>>());
    let resid: Vec<f64> = pts.iter().map(|&(x, r)| (r - a - b * x).abs()).collect();
    let mad = median(&mut resid.clone()).unwrap();
    let kept: Vec<(f64, f64)> =
        pts.iter().zip(&resid).filter(|(_, e)| **e <= 3.0 * 1.4826 * mad).map(|(p, _)| *p).collect();
    let (a_old, _) = fit_line_checked(&kept).unwrap();
    assert!((a_old - 50.0).abs() > 0.1, "{a_old}");
}

#[test]
fn a_window_whose_own_surface_lies_to_one_side_gives_no_value() {
    // The crest's depth over the window's last 60% is the majority: what is left of the root
    // sits at one end, and its centre would be an extrapolation.
    let pts = contaminated_root_window(0.6);
    let level = fit_at_centre(&pts, Section::Flat, 0.7, 0.5 * 1.5748);
    assert!(level.is_err() || level.is_ok_and(|l| (l - 50.0 - 1.5748).abs() < 0.01), "{level:?}");
}

/// Every bin without a height says why, and the count by reason adds up to the unmeasured bins:
/// a hole in the fused surface over the crests is `crest_no_surface`, the end face's first row is
/// `root_off_part`.
#[test]
fn each_unmeasured_bin_is_counted_by_its_reason() {
    let (mut map, form) = ideal_map(1.234, 0.002);
    let helix = estimate_helix(&map, &form).unwrap();
    let g = map.grid.clone();
    // No surface over thread 3's crest between 90° and 120°.
    let crest_z = |theta: f64| helix.z_h_mm + helix.pitch_mm * (2.0 + theta / 360.0);
    for it in 0..g.ntheta {
        let theta = g.theta_deg_at(it);
        if !(90.0..120.0).contains(&theta) {
            continue;
        }
        for iz in 0..g.nz {
            if (g.z_at(iz) - crest_z(theta)).abs() < 0.9 {
                let i = map.index(iz, it);
                map.radius_mm[i] = f32::NAN;
            }
        }
    }
    let threads = measure_threads(&map, &form, &helix, &ProfileOptions::default());
    let third = &threads[2];
    let hole: Vec<_> = third.bins.iter().filter(|b| (90.0..120.0).contains(&b.angle_deg)).collect();
    assert_eq!(hole.len(), 30);
    assert!(hole.iter().all(|b| b.height_mm.is_none() && b.unmeasured == Some(Unmeasured::CrestNoSurface)));
    let counts = count_unmeasured(&third.bins);
    assert_eq!(counts, vec![UnmeasuredCount { reason: Unmeasured::CrestNoSurface, bins: 30 }]);
    // Every bin without a height has a reason, and none with one has.
    for t in &threads {
        for b in &t.bins {
            assert_eq!(b.height_mm.is_none(), b.unmeasured.is_some(), "thread {} at {}°", t.index, b.angle_deg);
        }
        let unmeasured = t.bins.iter().filter(|b| b.height_mm.is_none()).count();
        assert_eq!(count_unmeasured(&t.bins).iter().map(|c| c.bins).sum::<usize>(), unmeasured);
    }
    // The first thread's roots before the crest lie off the part at the end face.
    assert!(threads[0].bins.iter().any(|b| b.unmeasured == Some(Unmeasured::RootOffPart)));
}

/// `auto` follows the shipped model's measured effect: at the standard station's pixels a
/// buttress part stays classical (the model is known to add error there); at coarse pixels it is
/// corrected; `on` always runs and `off` never.
#[test]
fn auto_corrects_where_the_models_card_says_it_helps() {
    use crate::domain::thread::Family;
    let models = crate::learned::Models::new(None);
    let choose = |correction, family, pixel_mm| {
        let options = ProfileOptions { correction, ..Default::default() };
        choose_correction(&options, &models, family, pixel_mm).unwrap().map(|(c, _)| c)
    };
    let standard = choose(Correction::Auto, Family::Buttress, 0.041).expect("a choice under auto");
    assert!(!standard.run, "{}", standard.why);
    let effect = standard.effect.as_ref().expect("the shipped card measured buttress at fine pixels");
    assert!(!effect.helps() && standard.why.contains("not known to help"), "{}", standard.why);
    let coarse = choose(Correction::Auto, Family::Buttress, 0.12).unwrap();
    assert!(coarse.run && coarse.effect.as_ref().unwrap().helps(), "{}", coarse.why);
    assert!(coarse.error_per_change() > 0.0);
    assert!(choose(Correction::On, Family::Buttress, 0.041).unwrap().run);
    assert!(choose(Correction::Off, Family::Buttress, 0.12).is_none());
    // Beyond every measured range: auto leaves the heights classical and says why.
    let unmeasured = choose(Correction::Auto, Family::Round, 10.0).unwrap();
    assert!(!unmeasured.run && unmeasured.effect.is_none() && unmeasured.why.contains("measured nothing"));
    assert_eq!(unmeasured.error_per_change(), 1.0);
}

fn helix_read_at(readings: Vec<(u16, f64)>) -> Helix {
    Helix {
        z_h_mm: 0.01,
        pitch_mm: 5.08,
        taper_on_diameter: 0.0625,
        fit_rms_um: 100.0,
        bins_used: readings.len(),
        amplitude_ratio: Some(1.0),
        phase_readings: readings,
        local_offsets_mm: Vec::new(),
    }
}

fn buttress() -> ThreadForm {
    ThreadForm::api_buttress(5.08, 1.5748, 0.0508, 0.0625).unwrap()
}

/// Every sector of the circumference reading the same phase leaves nothing to doubt; views whose
/// crests sit off the helix by ±a move the windows by a, and z_h by their scatter; readings that
/// scatter over the pitch say nothing.
#[test]
fn the_phase_is_known_as_far_as_independent_sectors_agree() {
    let (form, p) = (buttress(), 5.08);
    // Readings wrap: p reads 0.01 mm before z_h = 0.01, not a pitch after it.
    let agreed = helix_read_at((0..360).map(|b| (b, if b % 2 == 0 { 0.02 } else { p })).collect());
    let u = agreed.phase_uncertainty(&form, 10.0);
    assert_eq!((u.sectors, u.unknown), (36, false));
    assert!(u.spread_mm > 0.0099 && u.spread_mm < 0.0101, "{u:?}");
    assert!(u.u_mm < 0.011, "{u:?}");
    // Twelve views 30° apart, alternately 0.1 mm before and after the helix.
    let a = 0.1;
    let staggered = helix_read_at((0..360).map(|b| (b, 0.01 + if (b / 30) % 2 == 0 { a } else { -a })).collect())
        .phase_uncertainty(&form, 30.0);
    assert_eq!((staggered.sectors, staggered.unknown), (12, false));
    assert!((staggered.spread_mm - a).abs() < 1e-9, "{staggered:?}");
    // z_h's own uncertainty: t(11)·a·√(12/11)/√12 / 2, conservatively with t(10) = 2.228.
    let z_h_u = 0.5 * 2.228 * a * (12.0f64 / 11.0).sqrt() / 12f64.sqrt();
    assert!((staggered.u_mm - a.hypot(z_h_u)).abs() < 1e-9, "{staggered:?}");
    assert_eq!(staggered.error, PhaseError::Normal { sigma_mm: staggered.u_mm });
    // Views scattered over the whole pitch: unknown, though many.
    let scattered = helix_read_at((0..360).map(|b| (b, 0.01 + p * ((b / 30) as f64 / 12.0))).collect())
        .phase_uncertainty(&form, 30.0);
    assert!(scattered.unknown, "{scattered:?}");
}

/// Two neighbouring bins of one view cannot show their view's error: the phase is bounded by the
/// helix's fit residual instead, the tighter the closer the form fits, and not at all where the
/// residual is as large as the form's difference from itself half a pitch away.
#[test]
fn one_views_phase_is_bounded_by_the_fit_residual() {
    let (form, p) = (buttress(), 5.08);
    let one_view = |fit_rms_um| Helix { fit_rms_um, ..helix_read_at(vec![(40, 0.01), (41, 0.01)]) };
    let half_width = |u: &PhaseUncertainty| match u.error {
        PhaseError::Uniform { half_width_mm } => half_width_mm,
        PhaseError::Normal { .. } => panic!("one sector read the phase: {u:?}"),
    };
    let tight = one_view(100.0).phase_uncertainty(&form, 18.0);
    let loose = one_view(600.0).phase_uncertainty(&form, 18.0);
    assert_eq!((tight.sectors, tight.unknown, loose.unknown), (1, false, false));
    assert!(0.0 < half_width(&tight) && half_width(&tight) < half_width(&loose), "{tight:?} {loose:?}");
    assert!((tight.u_mm - half_width(&tight) / 3f64.sqrt()).abs() < 1e-12);
    // A residual of the whole thread height: no shift accounts for it.
    let none = one_view(1575.0).phase_uncertainty(&form, 18.0);
    assert!(none.unknown && half_width(&none) == p / 2.0, "{none:?}");
    assert_eq!(helix_read_at(vec![]).phase_uncertainty(&form, 18.0).sectors, 0);
}

/// On a flat crest and root the windows can move by the flats' spare width and read the same
/// height; on a round thread's arcs (circles of radius ρ, fitted as parabolas over windows of half
/// width w) a shift δ lowers the crest's fit by about δ²·(1/2ρ + w²/4ρ³) and raises the roots' alike,
/// so over δ ~ N(0, u²) the RMS change is √3·κ·u² with κ the sum of the two; a phase unknown
/// within the pitch puts windows on flanks and roots, and costs most of a height.
#[test]
fn a_windows_phase_error_costs_what_the_form_says() {
    let buttress = buttress();
    let ProfileShape::Trapezoid { load_flank_deg, stab_flank_deg, crest_width_mm } = buttress.profile else {
        unreachable!()
    };
    let root_mm = buttress.pitch_mm
        - crest_width_mm
        - buttress.height_mm * (load_flank_deg.to_radians().tan() + stab_flank_deg.to_radians().tan());
    // Windows are 60% of a flat: 20% of it spare either side, and δ reaches 4σ.
    let spare_mm = 0.2 * crest_width_mm.min(root_mm);
    let normal = |sigma_mm| PhaseError::Normal { sigma_mm };
    assert!(phase_height_rms_mm(&buttress, normal(0.9 * spare_mm / 4.0)) < 1e-9);
    assert!(phase_height_rms_mm(&buttress, PhaseError::Uniform { half_width_mm: 0.9 * spare_mm }) < 1e-9);
    assert!(phase_height_rms_mm(&buttress, normal(2.0 * spare_mm)) > 1e-3);
    let whole_pitch = PhaseError::Uniform { half_width_mm: buttress.pitch_mm / 2.0 };
    assert!(phase_height_rms_mm(&buttress, whole_pitch) > 0.5 * buttress.height_mm);
    let round = ThreadForm::api_round(3.175, 1.80975, 0.0508, 0.0625, Some(0.4318)).unwrap();
    let (rho_crest, rho_root) = round.arc_radii_mm().unwrap();
    let (w_crest, w_root) = round.window_half_widths_mm();
    let kappa_of = |rho: f64, w: f64| 0.5 / rho + w * w / (4.0 * rho.powi(3));
    let kappa = kappa_of(rho_crest, w_crest) + kappa_of(rho_root, w_root);
    let u = 0.005;
    let expected = 3f64.sqrt() * kappa * u * u;
    let got = phase_height_rms_mm(&round, normal(u));
    // The circle's next term (x⁶, about 3% at these windows) is left out of κ.
    assert!((got - expected).abs() < 0.05 * expected, "{got} against {expected}");
}

/// A quarter of the ring seen by a view placed 0.2 mm off along z shows its crests there; on a
/// round thread, windows left at the one helix sit off those crests and read the heights low
/// (the arcs fall away with the square of the offset), while windows placed by the bins' own
/// phase readings read them as elsewhere.
#[test]
fn windows_follow_the_crests_of_a_view_placed_off_along_z() {
    let form = ThreadForm::api_round(3.175, 1.80975, 0.0508, 0.0625, Some(0.4318)).unwrap();
    let (z_h, shift_mm) = (0.7, 0.2);
    let (mut map, form) = ideal_map_of(form, z_h, 0.0);
    let g = map.grid.clone();
    for iz in 0..g.nz {
        for it in 0..g.ntheta {
            let (z, theta) = (g.z_at(iz), g.theta_deg_at(it));
            if (90.0..180.0).contains(&theta) {
                let i = map.index(iz, it);
                let r =
                    55.0 + z * form.radius_slope() + form.height_at(z - shift_mm - z_h - form.pitch_mm * theta / 360.0);
                map.radius_mm[i] = r as f32;
            }
        }
    }
    let options = ProfileOptions::default();
    let first = estimate_helix(&map, &form).unwrap();
    let helix = refine_helix(&map, &form, &first, &survey_threads(&map, &form, &first, &options));
    // Worst error over the shifted quarter, away from its edges, on the full threads.
    let worst_um = |h: &Helix| {
        let threads = measure_threads(&map, &form, h, &options);
        threads[2..6]
            .iter()
            .flat_map(|t| t.bins[100..170].iter().filter_map(|b| b.height_mm))
            .map(|v| 1e3 * (v - form.height_mm).abs())
            .fold(0.0, f64::max)
    };
    let global = worst_um(&helix);
    let local = worst_um(&helix.clone().with_local_phase(5));
    assert!(global > 20.0, "windows at the one helix: {global} µm");
    assert!(local < 0.2 * global, "windows at the local phase: {local} µm against {global}");
    assert!((helix.clone().with_local_phase(5).local_offset_mm(135) - 0.75 * shift_mm).abs() < 0.02);
}
