use super::*;
use crate::numeric::union_find::components;

#[test]
fn a_gaussian_peaks_centre_is_found_exactly_where_a_parabola_pulls_it_toward_the_cell() {
    for true_offset in [-0.4, -0.25, -0.1, 0.0, 0.1, 0.25, 0.4] {
        // A peak one cell wide (σ), sampled at the best cell and its two neighbours.
        let peak = |x: f64| 0.8 * (-(x - true_offset).powi(2) / 2.0).exp();
        let (left, centre, right) = (peak(-1.0), peak(0.0), peak(1.0));
        assert!((sub_cell_gaussian(left, centre, right) - true_offset).abs() < 1e-12, "{true_offset}");
        // The parabola's bias: 0.022, 0.045 and 0.038 cells at 0.1, 0.25 and 0.4.
        let parabola = sub_cell(left, centre, right);
        assert!(parabola.abs() <= true_offset.abs() - 0.02 || true_offset == 0.0, "{true_offset}: {parabola}");
    }
    // A neighbour that is not positive has no logarithm: the parabola's estimate.
    assert_eq!(sub_cell_gaussian(-0.1, 0.5, 0.3), sub_cell(-0.1, 0.5, 0.3));
    assert_eq!(sub_cell_gaussian(0.2, 0.5, 0.0), sub_cell(0.2, 0.5, 0.0));
}

#[test]
fn a_lens_radius_error_shifts_an_overlap_along_the_arc_as_the_geometry_does() {
    // A surface point midway between two views (their overlap's centre). A view whose lens is
    // δ farther out than its pose says places the point δ nearer the axis along its optical
    // axis; the content shift b → a is then the angle where a places it minus where b does.
    let lattice = Lattice::new(57.15, 0.041);
    let r = lattice.radius_ref_mm;
    for (angle_a, angle_b, delta_a, delta_b) in
        [(10.0, 17.8, 0.05, -0.03), (17.8, 10.0, 0.05, -0.03), (356.0, 3.8, -0.04, -0.05), (30.0, 30.0, 0.05, 0.05)]
    {
        let pose = |angle_deg: f64| ViewPose { angle_deg, axial_mm: 10.0, lens_radius_mm: 270.0 };
        let (pa, pb) = (pose(angle_a), pose(angle_b));
        let mid = pa.angle_deg.to_radians() + 0.5 * wrap_pi((pb.angle_deg - pa.angle_deg).to_radians());
        let placed = |view_deg: f64, delta: f64| {
            let axis = view_deg.to_radians();
            let (x, y) = (r * mid.cos() - delta * axis.cos(), r * mid.sin() - delta * axis.sin());
            y.atan2(x)
        };
        let exact = wrap_pi(placed(angle_a, delta_a) - placed(angle_b, delta_b)).to_degrees();
        let model = lens_radius_arc_shift_deg(&pa, &pb, delta_a, delta_b, &lattice);
        // First order in δ/r: within 1% (0.3% here, a few nanometres of arc).
        assert!((model - exact).abs() <= 1e-2 * exact.abs(), "{angle_a}→{angle_b}: {model} vs {exact}");
        if angle_a != angle_b {
            // 0.05 mm at 3.9° off centre: several µm of arc, more than a pair's other errors.
            assert!(exact.abs().to_radians() * r > 1e-3, "{exact}");
        }
    }
}

#[test]
fn views_cut_off_from_the_ring_stay_at_their_encoder_poses() {
    // Six views; pairs 2–3 and 3–4 failed (view 3 is alone) and 5–0 failed: components
    // {0, 1, 2} and {4, 5} each keep their measured differences about a zero mean.
    let truth = [0.3, -0.1, 0.2, 0.0, 0.25, -0.05];
    let pairs: Vec<(usize, usize, f64)> =
        [(0, 1), (1, 2), (4, 5)].iter().map(|&(a, b)| (a, b, truth[b] - truth[a])).collect();
    assert_eq!(components(6, pairs.iter().map(|&(a, b, _)| (a, b))), [0, 0, 0, 3, 4, 4]);
    let c = solve_axis(6, &pairs, 0.02);
    assert!(c.iter().all(|v| v.is_finite() && v.abs() < 1.0), "{c:?}");
    assert!(c[3].abs() < 1e-12, "{c:?}");
    for &(a, b, m) in &pairs {
        assert!((c[b] - c[a] - m).abs() < 1e-9, "{c:?}");
    }
    assert!((c[0] + c[1] + c[2]).abs() < 1e-9 && (c[4] + c[5]).abs() < 1e-9, "{c:?}");
}

#[test]
fn graph_solve_spreads_a_ring_consistently() {
    // Four views in a ring with true corrections (0.3, −0.1, 0.2, −0.4): measured differences
    // c_b − c_a, one of them corrupted; Huber weighting keeps the corrupt one from spreading.
    let truth = [0.3, -0.1, 0.2, -0.4];
    let mut pairs: Vec<(usize, usize, f64)> = (0..4).map(|a| (a, (a + 1) % 4, truth[(a + 1) % 4] - truth[a])).collect();
    pairs.push((0, 2, truth[2] - truth[0]));
    pairs.push((1, 3, truth[3] - truth[1]));
    pairs[1].2 += 0.5;
    let c = solve_axis(4, &pairs, 0.02);
    for v in 0..4 {
        assert!((c[v] - truth[v]).abs() < 0.02, "{c:?}");
    }
}

#[test]
fn a_pair_that_would_move_a_view_beyond_the_encoders_bound_is_left_out_and_named() {
    // A chain of five views with true corrections within ±0.4°, and a sixth reached by one pair
    // whose peak lies at a wrong alignment 2.4° away (its truth: 0.1°).
    let truth = [0.3, -0.1, 0.2, -0.4, 0.0, 0.1];
    let pair = |a: usize, b: usize, shift_angle_deg: f64| PairMeasure {
        a,
        b,
        shift_angle_deg,
        shift_axial_mm: 0.0,
        shift_radius_mm: 0.0,
        peak_ncc: 0.6,
        rival_ratio: 0.3,
        overlap_cells: 5000,
        residual_angle_deg: 0.0,
        residual_axial_um: 0.0,
        residual_radius_um: 0.0,
    };
    let mut pairs: Vec<PairMeasure> = (0..4).map(|a| pair(a, a + 1, truth[a + 1] - truth[a])).collect();
    pairs.push(pair(4, 5, 2.4));
    let mut candidates: Vec<PairCandidate> = pairs
        .iter()
        .map(|p| PairCandidate {
            a: p.a,
            b: p.b,
            status: PairStatus::Measured,
            peak_ncc: Some(0.6),
            rival_ratio: Some(0.3),
            overlap_cells: Some(5000),
            radius_shift_um: None,
        })
        .collect();
    let kernels = Kernels { radius_mm: 0.01, angle_deg: 0.02, axial_mm: 0.01 };
    // With it, the component's zero mean puts view 5 at +2.0° (beyond ±1.25°) and the others
    // 0.4° off theirs.
    let with_it = solve_axis(6, &pairs.iter().map(|p| (p.a, p.b, p.shift_angle_deg)).collect::<Vec<_>>(), 0.02);
    assert!(with_it[5] > 1.25, "{with_it:?}");
    let (_, angle, _) = solve_within_encoder_bounds(6, &mut pairs, &mut candidates, kernels, (1.25, 0.4));
    assert_eq!(candidates.iter().map(|c| c.status).filter(|s| *s == PairStatus::Implausible).count(), 1);
    assert_eq!(candidates[4].status, PairStatus::Implausible);
    assert_eq!(pairs.len(), 4, "the implausible pair leaves the solve");
    // View 5 keeps its encoder pose; the chain keeps its measured differences about its mean.
    assert_eq!(angle[5], 0.0);
    let mean = truth[..5].iter().sum::<f64>() / 5.0;
    for v in 0..5 {
        assert!((angle[v] - (truth[v] - mean)).abs() < 1e-6, "{angle:?}");
    }
    // A chain whose wrong pair is in its middle: the zero mean puts every view beyond the bound
    // (−1.5° and +1.5°), yet only the wrong pair goes.
    let truth = [0.0; 6];
    let mut middle: Vec<PairMeasure> = (0..5).map(|a| pair(a, a + 1, if a == 2 { 3.0 } else { truth[a] })).collect();
    let mut statuses: Vec<PairCandidate> = candidates.clone();
    statuses.iter_mut().for_each(|c| c.status = PairStatus::Measured);
    let (_, angle, _) = solve_within_encoder_bounds(6, &mut middle, &mut statuses, kernels, (1.25, 0.4));
    assert_eq!(middle.len(), 4);
    assert!(!middle.iter().any(|p| (p.a, p.b) == (2, 3)));
    assert_eq!(statuses.iter().filter(|c| c.status == PairStatus::Implausible).count(), 1);
    assert!(angle.iter().all(|a| a.abs() < 1e-9), "{angle:?}");
    let truth = [0.3, -0.1, 0.2, -0.4, 0.0, 0.1];
    // Pairs that keep every view within the bound are all kept.
    let mut fine: Vec<PairMeasure> = (0..5).map(|a| pair(a, a + 1, truth[a + 1] - truth[a])).collect();
    let mut all_measured = candidates.clone();
    all_measured.iter_mut().for_each(|c| c.status = PairStatus::Measured);
    solve_within_encoder_bounds(6, &mut fine, &mut all_measured, kernels, (1.25, 0.4));
    assert_eq!(fine.len(), 5);
    assert!(all_measured.iter().all(|c| c.status == PairStatus::Measured));
}

#[test]
fn a_band_of_stronger_contrast_is_levelled_and_the_pattern_kept() {
    // A checkerboard texture of ±1 whose contrast triples over columns 20–29 (a band tied to the
    // view), with a missing cell.
    let (ns, nz) = (50, 12);
    let mut texture: Vec<f32> = (0..ns * nz)
        .map(|i| {
            let (s, z) = (i % ns, i / ns);
            let sign = if (s + z) % 2 == 0 { 1.0 } else { -1.0 };
            sign * if (20..30).contains(&s) { 3.0 } else { 1.0 }
        })
        .collect();
    texture[5 * ns + 7] = f32::NAN;
    let out = lattice::normalise_contrast(&texture, ns, nz, 4, 2);
    assert!(out[5 * ns + 7].is_nan());
    for z in 0..nz {
        for s in 0..ns {
            let (t, o) = (texture[z * ns + s], out[z * ns + s]);
            if t.is_nan() {
                continue;
            }
            assert_eq!(t.signum(), o.signum(), "the pattern is kept at ({s}, {z})");
            // Away from the band's edges (±4 cells), every cell reads unit contrast.
            if !(16..34).contains(&s) || (24..26).contains(&s) {
                assert!((o.abs() - 1.0).abs() < 0.05, "({s}, {z}): {o}");
            }
        }
    }
    // The brute force: a cell's neighbourhood RMS, read directly.
    let (s, z) = (18, 6);
    let window: Vec<f32> = (z - 2..=z + 2)
        .flat_map(|zz| (s - 4..=s + 4).map(move |ss| (ss, zz)))
        .map(|(ss, zz)| texture[zz * ns + ss])
        .filter(|t| t.is_finite())
        .collect();
    let rms = (window.iter().map(|t| t * t).sum::<f32>() / window.len() as f32).sqrt();
    assert!((out[z * ns + s] - texture[z * ns + s] / rms).abs() < 1e-5);
}

/// Brute-force NCC of a's cells (s, z) on the `step` grid against b's (s + off_s, z + off_z),
/// both z-major with NaN for missing cells: what the masked grids must reproduce.
fn brute_ncc(
    a: &[f32],
    (ans, anz): (usize, usize),
    b: &[f32],
    (bns, bnz): (usize, usize),
    off: (i64, i64),
    step: usize,
) -> f64 {
    let (mut n, mut sa, mut sb, mut saa, mut sbb, mut sab) = (0f64, 0f64, 0f64, 0f64, 0f64, 0f64);
    for z in (0..anz).step_by(step) {
        for s in (0..ans).step_by(step) {
            let (bs, bz) = (s as i64 + off.0, z as i64 + off.1);
            if bs < 0 || bz < 0 || bs >= bns as i64 || bz >= bnz as i64 {
                continue;
            }
            let (x, y) = (a[z * ans + s], b[bz as usize * bns + bs as usize]);
            if x.is_nan() || y.is_nan() {
                continue;
            }
            let (x, y) = (x as f64, y as f64);
            (n, sa, sb, saa, sbb, sab) = (n + 1.0, sa + x, sb + y, saa + x * x, sbb + y * y, sab + x * y);
        }
    }
    (sab - sa * sb / n) / ((saa - sa * sa / n) * (sbb - sb * sb / n)).sqrt()
}

#[test]
fn masked_grids_match_a_brute_force_ncc_at_every_parity() {
    let mut state = 7u64;
    let mut next = || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((state >> 33) % 1000) as f32 / 1000.0 - 0.5
    };
    let (ans, anz, bns, bnz) = (23, 57, 29, 61);
    let a: Vec<f32> = (0..ans * anz).map(|i| if i % 17 == 3 { f32::NAN } else { next() }).collect();
    // b holds a's texture moved by (3, −2) cells, noise elsewhere, and holes of its own.
    let b: Vec<f32> = (0..bns * bnz)
        .map(|i| {
            let (s, z) = ((i % bns) as i64 - 3, (i / bns) as i64 + 2);
            let v = if s >= 0 && z >= 0 && (s as usize) < ans && (z as usize) < anz {
                a[z as usize * ans + s as usize]
            } else {
                next()
            };
            if i % 13 == 5 { f32::NAN } else { v }
        })
        .collect();
    let full = (TextureGrid::sampled(&a, ans, anz, 1, 0, 0), TextureGrid::sampled(&b, bns, bnz, 1, 0, 0));
    let (peak, _) = ncc_grids(&full.0, &full.1, 3, -2, 20);
    assert!((peak - 1.0).abs() < 1e-6, "{peak}");
    let coarse = (StrideTwo::new(&a, (ans, anz)), StrideTwo::new(&b, (bns, bnz)));
    for off_s in -4..=5i64 {
        for off_z in -3..=4i64 {
            let want = brute_ncc(&a, (ans, anz), &b, (bns, bnz), (off_s, off_z), 1);
            let (got, _) = ncc_grids(&full.0, &full.1, off_s, off_z, 20);
            assert!((got - want).abs() < 1e-5, "full ({off_s}, {off_z}): {got} vs {want}");
            // One pass over the twelve rows or six passes (and AVX2, where there is one): the
            // same sums, bit for bit, so the choice of loop never moves a registration.
            let six_passes = overlap_sums(&full.0, &full.1, off_s, off_z, false);
            assert_eq!(overlap_sums(&full.0, &full.1, off_s, off_z, true), six_passes);
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the processor has AVX2 (checked just above).
                assert_eq!(unsafe { overlap_sums_avx2(&full.0, &full.1, off_s, off_z) }, six_passes);
            }
            let want = brute_ncc(&a, (ans, anz), &b, (bns, bnz), (off_s, off_z), 2);
            let (got, _) = StrideTwo::ncc(&coarse.0, &coarse.1, off_s, off_z, 20);
            assert!((got - want).abs() < 1e-5, "stride 2 ({off_s}, {off_z}): {got} vs {want}");
        }
    }
}

#[test]
fn the_lattice_divides_the_turn_and_carries_a_neighbour_across_angle_zero() {
    let lattice = Lattice::new(57.15, 0.041);
    assert_eq!(lattice.cells_around % 2, 0);
    assert!((lattice.cell_arc_mm * lattice.cells_around as f64 - TAU * 57.15).abs() < 1e-9);
    assert!((lattice.cell_arc_mm - 0.041).abs() < 0.041 / lattice.cells_around as f64);
    let turn = |a_deg: f64, b_deg: f64| lattice.turn_cells(a_deg.to_radians(), b_deg.to_radians());
    assert_eq!(turn(8.0, 16.0), 0);
    // b at 0° is a's neighbour at 360°: its indices move up a turn, and back the other way.
    assert_eq!(turn(352.0, 0.0), lattice.cells_around);
    assert_eq!(turn(0.0, 352.0), -lattice.cells_around);
    assert_eq!(turn(-8.0, 352.0), -lattice.cells_around);
    // A point seen at 359.9° by b and 359.9° − 360° by a lands in the same cell of a's turn.
    let cell = |deg: f64| (deg.to_radians() * lattice.radius_ref_mm / lattice.cell_arc_mm).floor() as i64;
    assert_eq!(cell(359.9) + turn(-8.0, 352.0), cell(-0.1));
}

#[test]
fn a_view_without_trusted_points_is_left_where_the_encoder_put_it() {
    let lattice = Lattice::new(57.15, 0.041);
    let poses: Vec<ViewPose> =
        // 352°, 0° and 8°: the first pair spans angle 0.
        [352.0, 0.0, 8.0].map(|angle_deg| ViewPose { angle_deg, axial_mm: 10.0, lens_radius_mm: 200.0 }).into();
    let grids: Vec<ViewGrid> = poses
        .iter()
        .map(|p| view_grid(std::iter::empty(), p.angle_deg.to_radians(), &lattice, false, &mut GridScratch::default()))
        .collect();
    let registration = register(&grids, &poses, &lattice, 7.0, 17.0, 5.08, &RegisterOptions::default());
    assert!(registration.pairs.is_empty());
    assert!(registration.corrections.iter().all(|c| *c == PoseCorrection::default()));
}

#[test]
fn neighbours_include_the_wrap_around_pair() {
    let poses: Vec<ViewPose> =
        (0..8).map(|i| ViewPose { angle_deg: i as f64 * 45.0, axial_mm: 10.0, lens_radius_mm: 200.0 }).collect();
    let pairs = overlapping_pairs(&poses, 30.0, 15.0);
    assert_eq!(pairs.len(), 8);
    assert!(pairs.contains(&(0, 7)));
}

#[test]
fn views_overlapping_narrowly_are_still_candidates() {
    // 16 views 22.5° apart with footprints of 25.5°: neighbours share 3° (12% of a footprint),
    // the least overlap a station may have; views two apart share nothing.
    let poses: Vec<ViewPose> =
        (0..16).map(|i| ViewPose { angle_deg: i as f64 * 22.5, axial_mm: 10.0, lens_radius_mm: 200.0 }).collect();
    let pairs = overlapping_pairs(&poses, 25.5 / 2.0, 15.0);
    assert_eq!(pairs.len(), 16, "{pairs:?}");
    assert!(pairs.iter().all(|&(a, b)| b - a == 1 || (a, b) == (0, 15)), "{pairs:?}");
    // Footprints that just miss each other are not.
    assert!(overlapping_pairs(&poses, 22.0 / 2.0, 15.0).is_empty());
    // Two axial rows 28 mm apart with 30 mm footprints along the axis overlap by 2 mm.
    let rows: Vec<ViewPose> =
        [0.0, 28.0].iter().map(|&z| ViewPose { angle_deg: 0.0, axial_mm: z, lens_radius_mm: 200.0 }).collect();
    assert_eq!(overlapping_pairs(&rows, 12.75, 15.0), vec![(0, 1)]);
}

#[test]
fn views_whose_texture_does_not_register_are_placed_radially_by_their_overlap() {
    // Two views 8° apart (footprints 14° wide) of a buttress-like thread without grain: flats
    // 0.75 mm above and below the mean on a 1/32 taper. View b's lens stands 0.2 mm farther out
    // than its pose says, which puts its points 0.2 mm nearer the axis, and its encoder errs by
    // 0.25 mm axially: the texture cannot register them, the overlap's radius can.
    let lattice = Lattice::new(57.15, 0.041);
    let pitch_mm = 5.08;
    let surface = |z: f64| {
        let phase = (z / pitch_mm).rem_euclid(1.0);
        55.5 + z / 32.0 + if phase < 0.5 { 0.75 } else { -0.75 }
    };
    let points = |view_deg: f64, radial_error_mm: f64, axial_error_mm: f64| {
        let (arc_cells, z_cells) = (340, 700);
        (0..arc_cells).flat_map(move |i| {
            (0..z_cells).map(move |k| {
                let theta = (view_deg - 7.0 + 14.0 * i as f64 / arc_cells as f64).to_radians();
                let z = 1.0 + 0.041 * k as f64;
                let r = surface(z) - radial_error_mm;
                SurfacePoint {
                    position: nalgebra::Point3::new(r * theta.cos(), r * theta.sin(), z + axial_error_mm),
                    rgb: [0.5; 3],
                    weight: 2.0,
                    pixel: [0, 0],
                }
            })
        })
    };
    let poses: Vec<ViewPose> =
        [0.0, 8.0].map(|angle_deg| ViewPose { angle_deg, axial_mm: 15.0, lens_radius_mm: 200.0 }).into();
    let grids: Vec<ViewGrid> = [points(0.0, 0.0, 0.0).collect::<Vec<_>>(), points(8.0, 0.2, 0.25).collect()]
        .into_iter()
        .zip(&poses)
        .map(|(p, pose)| view_grid(p, pose.angle_deg.to_radians(), &lattice, false, &mut GridScratch::default()))
        .collect();
    let registration = register(&grids, &poses, &lattice, 7.0, 15.0, pitch_mm, &RegisterOptions::default());
    assert!(registration.pairs.is_empty(), "{:?}", registration.candidates);
    assert_eq!(registration.unregistered_views, [0, 1]);
    let candidate = &registration.candidates[0];
    let shift_um = candidate.radius_shift_um.expect("the overlap's radius is read");
    // a's radius minus b's: 200 µm, within the taper over the axial error (8 µm).
    assert!((shift_um - 200.0).abs() < 12.0, "{shift_um}");
    assert_eq!(registration.placed_radially, [0, 1]);
    let c = &registration.corrections;
    assert!((c[1].lens_radius_mm - c[0].lens_radius_mm - 1e-3 * shift_um).abs() < 1e-9, "{c:?}");
    // Angle and axial position stay the encoders'.
    assert!(c.iter().all(|c| c.angle_deg == 0.0 && c.axial_mm == 0.0), "{c:?}");
}
