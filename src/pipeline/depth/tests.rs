use super::*;
use crate::domain::frame::Samples;
use crate::pipeline::depth::measure::{focus_measure, focus_measures_avx2, focus_measures_body};

#[test]
fn options_stored_before_the_flat_window_existed_still_load_with_its_default() {
    let old = r#"{"window_radius_px": 3, "min_peak_ratio": 1.6, "peak_fraction": 0.3}"#;
    let options: DepthOptions = serde_json::from_str(old).unwrap();
    assert_eq!((options.window_radius_px, options.flat_window_radius_px), (3, 5));
    assert!(options.equalize_phase);
    assert_eq!(options.row_step, 1);
    assert_eq!(options.edge_window_radius_px, 1);
}

#[test]
fn at_a_steep_edge_the_small_box_picks_which_of_two_peaks_is_the_pixels_own() {
    // A big box straddling a crest edge: the crest's peak at frame 4 (stronger texture) and
    // the root's at frame 11, a thread's height further; floor 1.
    let two_peaks = [1.0, 1.2, 3.0, 8.0, 10.0, 8.0, 3.0, 1.3, 1.5, 2.5, 4.5, 5.0, 4.0, 2.0, 1.1, 1.0];
    // The pixel's own 3×3 box is sharpest on the root: the root's peak is its own.
    assert_eq!(own_peak(&two_peaks, 4, 11, 1.0), 11);
    // Within a frame of it counts too (the small box is noisier than the big one).
    assert_eq!(own_peak(&two_peaks, 4, 10, 1.0), 11);
    assert_eq!(own_peak(&two_peaks, 4, 12, 1.0), 11);
    // The small box agrees with the big one, or sits on the same peak's plateau: unchanged.
    assert_eq!(own_peak(&two_peaks, 4, 4, 1.0), 4);
    assert_eq!(own_peak(&two_peaks, 4, 6, 1.0), 4);
    // One curve with a single peak: a small box sharpest far from it (noise on a dull
    // surface) finds no peak of the big curve there, so the maximum stands.
    let one_peak = [1.0, 1.2, 3.0, 8.0, 10.0, 8.0, 3.0, 1.5, 1.2, 1.1, 1.1, 1.0, 1.0, 1.0, 1.0, 1.0];
    assert_eq!(own_peak(&one_peak, 4, 10, 1.0), 4);
    // A second peak too faint to be a surface (under 30% of the maximum's height above the
    // floor): the maximum stands.
    let faint = [1.0, 1.2, 3.0, 8.0, 10.0, 8.0, 3.0, 1.3, 1.5, 2.5, 3.4, 3.6, 3.0, 2.0, 1.1, 1.0];
    assert_eq!(own_peak(&faint, 4, 11, 1.0), 4);
    // The small box at the stack's ends (no frame to spare for the shoulders): unchanged.
    assert_eq!(own_peak(&two_peaks, 4, 15, 1.0), 4);
    assert_eq!(own_peak(&two_peaks, 11, 1, 1.0), 11);
}

#[test]
fn keeping_the_sharpest_frame_by_masks_matches_the_branches_and_their_ties() {
    // Measures on a coarse lattice so that ties are frequent; 37 pixels (not a lane multiple).
    let frames: Vec<Vec<f32>> =
        (0..9u32).map(|k| (0..37u32).map(|x| ((x * 7 + k * 13) % 5) as f32 * 0.5).collect()).collect();
    for ties in [Ties::KeepEarlier, Ties::TakeLater] {
        let (mut best, mut best_frame) = (frames[0].clone(), vec![0u32; 37]);
        let (mut want, mut want_frame) = (frames[0].clone(), vec![0u32; 37]);
        for (k, measures) in frames.iter().enumerate().skip(1) {
            keep_sharpest(measures, k as u32, &mut best, &mut best_frame, ties);
            for x in 0..37 {
                let sharper = if ties == Ties::TakeLater { measures[x] >= want[x] } else { measures[x] > want[x] };
                if sharper {
                    (want[x], want_frame[x]) = (measures[x], k as u32);
                }
            }
        }
        assert_eq!((&best, &best_frame), (&want, &want_frame));
    }
    // The tie rule decides between equal peaks in frames 1 and 3.
    let curve = [[0.0f32], [2.0], [1.0], [2.0]];
    for (ties, frame) in [(Ties::KeepEarlier, 1), (Ties::TakeLater, 3)] {
        let (mut best, mut best_frame) = ([curve[0][0]], [0u32]);
        for (k, m) in curve.iter().enumerate().skip(1) {
            keep_sharpest(m, k as u32, &mut best, &mut best_frame, ties);
        }
        assert_eq!((best, best_frame), ([2.0], [frame]));
    }
}

#[test]
fn flat_topped_curve_centre_moves_smoothly_with_focus() {
    let offsets: Vec<f64> = (0..12).map(|k| -1.5 + 0.25 * k as f64).collect();
    // A plateau 0.5 mm wide with symmetric shoulders, centred at `c`.
    let curve = |c: f64| -> Vec<f32> {
        offsets.iter().map(|&o| (1.0 / (1.0 + (((o - c).abs() - 0.25).max(0.0) / 0.2).powi(2))) as f32 + 0.05).collect()
    };
    for c in [-0.4, -0.33, -0.2, 0.0, 0.11, 0.3] {
        let column = curve(c);
        let k_best = (0..column.len()).max_by(|&a, &b| column[a].total_cmp(&column[b])).unwrap();
        let got = peak_offset(&column, &offsets, k_best, 0.05, 0.3).unwrap();
        assert!((got - c).abs() < 0.03, "centre {c}: {got}");
    }
    // A peak at the end of the stack is not bracketed.
    let column = curve(1.4);
    assert!(peak_offset(&column, &offsets, 11, 0.05, 0.3).is_none());
}

/// The estimate's error depends on where the true focus falls between two frames. This pins
/// down its size on a model curve (plateau ±0.25 mm, Lorentzian shoulders): about ±20 µm at the
/// presets' 0.25 mm frame step, under 3 µm at 0.1 mm: what [`equalize_sub_frame_phase`] exists
/// to remove.
#[test]
fn sub_frame_bias_depends_on_the_frame_step() {
    let shape = |o: f64, c: f64| (1.0 / (1.0 + (((o - c).abs() - 0.25).max(0.0) / 0.2).powi(2))) as f32 + 0.05;
    let worst = |step: f64| -> f64 {
        let offsets: Vec<f64> = (0..=(3.0 / step).round() as usize).map(|k| -1.5 + step * k as f64).collect();
        (0..=120)
            .map(|i| -0.3 + 0.005 * i as f64)
            .map(|c| {
                let column: Vec<f32> = offsets.iter().map(|&o| shape(o, c)).collect();
                let k_best = (0..column.len()).max_by(|&a, &b| column[a].total_cmp(&column[b])).unwrap();
                (peak_offset(&column, &offsets, k_best, 0.05, 0.3).unwrap() - c).abs()
            })
            .fold(0.0, f64::max)
    };
    let (coarse, fine) = (worst(0.25), worst(0.1));
    assert!((0.015..0.03).contains(&coarse), "0.25 mm step: {coarse}");
    assert!(fine < 0.003, "0.1 mm step: {fine}");
}

/// The pruned network selects the median of every 0/1 input up to n = 12 (so, by the 0/1
/// principle, of every input), and finds what `select_nth_unstable(n / 2)` finds on random
/// rows with many ties.
#[test]
fn median_network_matches_selection() {
    for n in 1..=12usize {
        for bits in 0u32..(1 << n) {
            let mut rows: Vec<f32> = (0..n).map(|k| ((bits >> k) & 1) as f32).collect();
            let mut expected = rows.clone();
            expected.sort_by(f32::total_cmp);
            let network = MedianNetwork::new(n);
            network.apply(&mut rows, 1);
            assert_eq!(rows[n / 2], expected[n / 2], "n {n}, input {bits:b}");
        }
    }
    let mut state = 12345u64;
    let mut next = || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        // Few distinct values, so that ties are common.
        ((state >> 33) % 17) as f32 * 0.25
    };
    for n in [3, 7, 8, 16, 20, 21, 31, 40, 64] {
        let w = 37;
        let network = MedianNetwork::new(n);
        let mut rows: Vec<f32> = (0..n * w).map(|_| next()).collect();
        let expected: Vec<f32> = (0..w)
            .map(|x| {
                let mut column: Vec<f32> = (0..n).map(|k| rows[k * w + x]).collect();
                *column.select_nth_unstable_by(n / 2, f32::total_cmp).1
            })
            .collect();
        network.apply(&mut rows, w);
        assert_eq!(&rows[network.rank * w..(network.rank + 1) * w], &expected[..], "n {n}");
    }
}

/// The row resampling by spans gives, bit for bit, the bilinear sample through each column's
/// own taps, for frames scaled up and down about centres inside and outside the row (taps
/// clamped at either edge).
#[test]
fn resampling_by_spans_matches_tap_by_tap() {
    let w = 97;
    let above: Vec<f32> = (0..w).map(|i| ((i * 37) % 23) as f32 / 7.0).collect();
    let below: Vec<f32> = (0..w).map(|i| ((i * 11) % 19) as f32 / 5.0).collect();
    for (centre, scale) in [(48.5, 1.011), (48.5, 0.989), (10.0, 1.05), (90.0, 0.95), (-20.0, 1.0), (48.5, 1.0)] {
        let xs = axis_taps(w, centre, scale);
        let fxs: Vec<f32> = xs.iter().map(|t| t.2).collect();
        let spans = tap_spans(&xs);
        assert_eq!(spans.iter().map(|s| s.len).sum::<usize>(), w);
        let mut out = vec![0f32; w];
        resample_row(&above, &below, 0.3, &xs, &spans, &fxs, &mut out);
        for (x, &(x0, x1, fx)) in xs.iter().enumerate() {
            let a = above[x0] * (1.0 - fx) + above[x1] * fx;
            let b = below[x0] * (1.0 - fx) + below[x1] * fx;
            assert_eq!(out[x], a * (1.0 - 0.3) + b * 0.3, "centre {centre}, scale {scale}, column {x}");
        }
    }
}

/// The same frames stored as 8-bit, 16-bit (v·257, the same value v / 255) and f32 samples,
/// gray and RGB, give the same depth map, confidence and all-in-focus colour bit for bit.
#[test]
fn every_sample_depth_gives_the_same_depth_map() {
    let (w, h, n) = (40usize, 24usize, 7usize);
    // A checkerboard whose contrast peaks at frame 3 on the left half and frame 4 on the right.
    let level = |x: usize, y: usize, k: usize| -> u8 {
        let peak = if x < w / 2 { 3.0 } else { 4.0 };
        let contrast = (-(k as f32 - peak).powi(2) / 2.0).exp();
        let checker = if (x + y).is_multiple_of(2) { 1.0 } else { -1.0 };
        (255.0 * (0.45 + 0.02 * k as f32 + 0.3 * contrast * checker)).round() as u8
    };
    let optics = Optics {
        projection: Projection::Perspective,
        focal_length_mm: Some(50.0),
        f_number: 2.8,
        focus_distance_mm: 220.0,
        pixel_pitch_um: 12.0,
        principal_point_px: None,
        magnification: None,
    };
    for channels in [1u8, 3] {
        let values = |k: usize| -> Vec<u8> {
            (0..w * h)
                .flat_map(|i| {
                    let v = level(i % w, i / w, k);
                    [v, v / 2, 255 - v].into_iter().take(channels as usize)
                })
                .collect()
        };
        let frames_as = |samples: &dyn Fn(Vec<u8>) -> Samples| -> Vec<Frame> {
            (0..n).map(|k| Frame { width: w as u32, height: h as u32, channels, samples: samples(values(k)) }).collect()
        };
        let view = View {
            id: "v".into(),
            pose: crate::domain::optics::ViewPose { angle_deg: 0.0, axial_mm: 0.0, lens_radius_mm: 250.0 },
            frames: (0..n)
                .map(|k| crate::domain::frame::FrameEntry {
                    file: format!("{k}.png"),
                    offset_mm: -0.75 + 0.25 * k as f64,
                })
                .collect(),
            format: crate::domain::frame::FrameFormat { width: w as u32, height: h as u32, channels, bit_depth: 8 },
        };
        let depth_of = |frames: Vec<Frame>| {
            depth_from_focus(&optics, &view, &DepthOptions::default(), |k| Ok(frames[k].clone()), &|| false)
                .unwrap()
                .unwrap()
        };
        let eight = depth_of(frames_as(&Samples::Eight));
        let sixteen = depth_of(frames_as(&|v| Samples::Sixteen(v.iter().map(|&v| v as u16 * 257).collect())));
        let float = depth_of(frames_as(&|v| Samples::Float(v.iter().map(|&v| v as f32 / 255.0).collect())));
        assert!(eight.depth_mm.iter().any(|d| d.is_finite()), "some pixels are in focus");
        let bits = |m: &DepthMap| -> Vec<u32> {
            let colours = m.all_in_focus.iter().map(|&v| v as u32);
            m.depth_mm.iter().chain(&m.peak_ratio).map(|v| v.to_bits()).chain(colours).collect()
        };
        assert_eq!(bits(&eight), bits(&sixteen), "{channels} channels: 8 vs 16 bits");
        assert_eq!(bits(&eight), bits(&float), "{channels} channels: 8 bits vs f32");

        // Depth on every row and on every second or third row: the sparser maps are the full
        // map's rows 0, step, 2·step, … bit for bit (the focus measure still sees every row).
        let frames = frames_as(&Samples::Eight);
        let with_step = |row_step: usize| {
            let options = DepthOptions { row_step, ..DepthOptions::default() };
            depth_from_focus(&optics, &view, &options, |k| Ok(frames[k].clone()), &|| false).unwrap().unwrap()
        };
        let full = with_step(1);
        assert_eq!(full.rows(), h);
        for step in [2, 3] {
            let sparse = with_step(step);
            assert_eq!((sparse.width, sparse.height, sparse.row_step, sparse.rows()), (w, h, step, h.div_ceil(step)));
            let rows_of = |m: &DepthMap, values: &[u32], per: usize| -> Vec<Vec<u32>> {
                values.chunks_exact(per * m.width).map(<[u32]>::to_vec).collect()
            };
            let bits = |v: &[f32]| v.iter().map(|v| v.to_bits()).collect::<Vec<u32>>();
            let colours = |m: &DepthMap| m.all_in_focus.iter().map(|&v| v as u32).collect::<Vec<u32>>();
            for (values_full, values_sparse, per) in [
                (bits(&full.depth_mm), bits(&sparse.depth_mm), 1),
                (bits(&full.peak_ratio), bits(&sparse.peak_ratio), 1),
                (colours(&full), colours(&sparse), 3),
            ] {
                let want: Vec<Vec<u32>> = rows_of(&full, &values_full, per).into_iter().step_by(step).collect();
                assert_eq!(rows_of(&sparse, &values_sparse, per), want, "{channels} channels, step {step}");
            }
            assert!(sparse.depth_mm.iter().any(|d| d.is_finite()), "step {step}");
        }
    }
}

/// The all-in-focus colour of each pixel is its sharpest frame's, whether that frame is the
/// first, one in the middle, the last, or the higher of two peaks. Frame k's gray level
/// carries k (0.3 + 0.05·k) under a checkerboard whose contrast per column band peaks at
/// the band's frame.
#[test]
fn all_in_focus_takes_each_pixel_from_its_sharpest_frame() {
    let (w, h, n) = (48usize, 20usize, 7usize);
    // Contrast of band b (12 columns each) in frame k.
    let contrast = |band: usize, k: usize| -> f32 {
        let peaks: [&[f32]; 4] = [
            &[1.0, 0.6, 0.3, 0.2, 0.1, 0.1, 0.1],
            &[0.1, 0.3, 0.6, 1.0, 0.6, 0.3, 0.1],
            &[0.1, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0],
            &[0.2, 0.7, 0.3, 0.2, 0.5, 0.9, 0.4],
        ];
        peaks[band][k]
    };
    let sharpest = [0usize, 3, 6, 5];
    let frames: Vec<Frame> = (0..n)
        .map(|k| Frame {
            width: w as u32,
            height: h as u32,
            channels: 1,
            samples: Samples::Float(
                (0..w * h)
                    .map(|i| {
                        let (x, y) = (i % w, i / w);
                        let checker = if (x + y).is_multiple_of(2) { 1.0 } else { -1.0 };
                        0.3 + 0.05 * k as f32 + 0.1 * contrast(x / 12, k) * checker
                    })
                    .collect(),
            ),
        })
        .collect();
    let optics = Optics {
        projection: Projection::Telecentric,
        focal_length_mm: Some(50.0),
        f_number: 8.0,
        focus_distance_mm: 100.0,
        pixel_pitch_um: 10.0,
        principal_point_px: None,
        magnification: Some(0.5),
    };
    let view = View {
        id: "v".into(),
        pose: crate::domain::optics::ViewPose { angle_deg: 0.0, axial_mm: 0.0, lens_radius_mm: 150.0 },
        frames: (0..n)
            .map(|k| crate::domain::frame::FrameEntry { file: format!("{k}.png"), offset_mm: 0.25 * k as f64 })
            .collect(),
        format: crate::domain::frame::FrameFormat { width: w as u32, height: h as u32, channels: 1, bit_depth: 8 },
    };
    let map = depth_from_focus(&optics, &view, &DepthOptions::default(), |k| Ok(frames[k].clone()), &|| false)
        .unwrap()
        .unwrap();
    // Pixels clear of the band edges by more than the focus window, on the map's rows.
    assert_eq!(map.row_step, DepthOptions::default().row_step);
    for y in (5..h - 5).filter(|y| y.is_multiple_of(map.row_step)) {
        let i = (y / map.row_step) * w;
        for x in (0..w).filter(|&x| (6..=7).contains(&(x % 12)) || (1..4).contains(&x)) {
            let k = sharpest[x / 12];
            let expected = frames[k].samples.value(y * w + x);
            assert_eq!(&map.all_in_focus[3 * (i + x)..3 * (i + x) + 3], &unorm16([expected; 3]), "({x}, {y})");
        }
    }
}

#[test]
fn box_sum_matches_brute_force() {
    // A field several boxes wide, and frames narrower or shorter than one box (a bundle may
    // hold frames of a few pixels: they give no depth, and must not fail).
    for (w, h, r) in [(13, 9, 2), (3, 3, 5), (2, 160, 5), (384, 2, 5), (1, 1, 4), (7, 4, 5)] {
        let gray: Vec<f32> = (0..w * h).map(|i| ((i * 37) % 11) as f32 / 11.0).collect();
        let mut scratch = vec![0f32; w * h];
        let mut out = vec![0f32; w * h];
        focus_measure(&gray, w, h, r, &mut scratch, &mut out);
        let lap = |x: usize, y: usize| {
            if x == 0 || y == 0 || x + 1 == w || y + 1 == h {
                return 0.0;
            }
            let i = y * w + x;
            let l = 4.0 * gray[i] - gray[i - 1] - gray[i + 1] - gray[i - w] - gray[i + w];
            l * l
        };
        for y in 0..h {
            for x in 0..w {
                let mut s = 0.0;
                for yy in y.saturating_sub(r)..=(y + r).min(h - 1) {
                    for xx in x.saturating_sub(r)..=(x + r).min(w - 1) {
                        s += lap(xx, yy);
                    }
                }
                assert!((out[y * w + x] - s).abs() < 1e-4, "{w}×{h} ({x},{y}) {} vs {s}", out[y * w + x]);
            }
        }
    }
    // The baseline and the AVX2 copy give the same measure, bit for bit (a frame-sized field,
    // with rows longer than the vector loops' blocks; the edge box's size, and both of the
    // big box's).
    let (w, h) = (203, 37);
    let gray: Vec<f32> = (0..w * h).map(|i| ((i * 7919) % 257) as f32 / 257.0).collect();
    let mut scratch = vec![0f32; w * h];
    let mut baseline = vec![0f32; w * h];
    for r in [1, 5, 4] {
        focus_measures_body::<false>(&gray, w, h, r, &mut scratch, &mut baseline, None);
        let mut dispatched = vec![0f32; w * h];
        focus_measure(&gray, w, h, r, &mut scratch, &mut dispatched);
        assert_eq!(dispatched, baseline, "r {r}");
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            let mut wide = vec![0f32; w * h];
            // SAFETY: the processor has AVX2 (checked just above).
            unsafe { focus_measures_avx2(&gray, w, h, r, &mut scratch, &mut wide, None) };
            assert_eq!(wide, baseline, "r {r}");
        }
    }
    let r = 4;
    // Both boxes from one Laplacian: each the same as its own measure, bit for bit.
    let (mut big, mut small, mut small_alone) = (vec![0f32; w * h], vec![0f32; w * h], vec![0f32; w * h]);
    focus_measures(&gray, w, h, r, &mut scratch, &mut big, Some((1, &mut small)));
    focus_measure(&gray, w, h, 1, &mut scratch, &mut small_alone);
    assert_eq!(big, baseline);
    assert_eq!(small, small_alone);
}

/// A depth map whose estimates carry an odd sub-frame bias (as the centroid's) over depths
/// that fall at every phase: equalising the phases removes most of it.
#[test]
fn phase_equalisation_removes_an_odd_sub_frame_bias() {
    let (origin, step, big_f) = (-2.5, 0.25, 220.0);
    let (w, h) = (400, 100);
    let true_offset = |i: usize| -1.0 + 2.0 * ((i * 7919) % (w * h)) as f64 / (w * h) as f64;
    let bias = |o: f64| {
        let phase = ((o - origin) / step).rem_euclid(1.0);
        0.012 * (std::f64::consts::TAU * phase).sin()
    };
    let depth: Vec<f32> = (0..w * h).map(|i| (big_f - true_offset(i) - bias(true_offset(i))) as f32).collect();
    let map = DepthMap {
        width: w,
        height: h,
        row_step: 1,
        depth_mm: depth,
        peak_ratio: vec![5.0; w * h],
        all_in_focus: vec![32768; 3 * w * h],
        end_edges: Vec::new(),
        frame_noise: None,
        prefiltered: false,
    };
    let worst = |maps: &[DepthMap]| {
        (0..w * h).map(|i| (maps[0].depth_mm[i] as f64 - (big_f - true_offset(i))).abs()).fold(0.0, f64::max)
    };
    let mut maps = vec![map.clone()];
    let before = worst(&maps);
    let grid = even_frame_grid(&(0..21).map(|k| origin + step * k as f64).collect::<Vec<_>>());
    assert_eq!(grid, Some((origin, step)));
    equalize_sub_frame_phase(&mut maps, &[grid], big_f);
    let after = worst(&maps);
    assert!(before > 0.011 && after < 0.002, "before {before}, after {after}");
    // A flat surface whose depths all sit within a third of a frame: not equalised.
    let flat: Vec<f32> = (0..w * h).map(|i| (big_f - 0.3 - 0.08 * (i % 97) as f64 / 97.0) as f32).collect();
    let flat_map = DepthMap { depth_mm: flat.clone(), ..map.clone() };
    let mut maps = vec![flat_map];
    equalize_sub_frame_phase(&mut maps, &[grid], big_f);
    assert_eq!(maps[0].depth_mm, flat);
    // A stack that is not on one even grid is left alone.
    let mut untouched = vec![map.clone()];
    let uneven = even_frame_grid(&[-1.0, -0.7, -0.5, 0.0]);
    assert_eq!(uneven, None);
    equalize_sub_frame_phase(&mut untouched, &[uneven], big_f);
    assert_eq!(untouched[0].depth_mm, map.depth_mm);
}

#[test]
fn the_envelope_ends_where_the_noise_pre_filter_starts() {
    // The domain layer cannot read the depth stage's options, so the bound is written twice: the
    // suites measured unfiltered depth only, and a bundle the pre-filter would take is outside.
    let bound = crate::domain::station::MEASURED.frame_noise_percent.1;
    assert_eq!(bound, 100.0 * DepthOptions::default().prefilter_min_noise);
}

#[test]
fn the_box_is_refined_where_form_and_optics_put_it_across_a_flank() {
    use crate::domain::thread::ConnectionTable;
    let table = ConnectionTable::api5b();
    let form = |name: &str| table.get(name).unwrap().form();
    let (buttress, round) = (form("BC 4-1/2"), form("LC 4-1/2"));
    // The standard station's optics (0.041 mm on the part).
    let standard = Optics::standard_camera();
    // The standard station's 11-pixel box (0.2 mm on the part) and its blur of the other surface
    // (0.13 mm) stay within a buttress flat's unread margin (0.47 mm)…
    assert!(!box_reaches_across_flanks(&buttress, &standard, 5));
    // …but not within a round crest's (0.18 mm), whose arcs the 9-pixel box spans.
    assert!(box_reaches_across_flanks(&round, &standard, 4));
    // The same box at coarse-survey's optics (0.12 mm pixels, f/0.57) reaches across a buttress
    // flank; a box of no size at sharp optics does not.
    let coarse = Optics {
        focal_length_mm: Some(100.0),
        f_number: 0.5714,
        focus_distance_mm: 350.0,
        pixel_pitch_um: 48.0,
        ..standard.clone()
    };
    assert!(box_reaches_across_flanks(&buttress, &coarse, 5));
    let sharp = Optics { f_number: 16.0, ..standard.clone() };
    assert!(!box_reaches_across_flanks(&buttress, &sharp, 0));
    // for_part keeps the refinement only where the box reaches across, and only with a small box.
    let options = DepthOptions::default();
    assert!(!options.for_part(&buttress, &standard).refine_now);
    // At fine pixels (the standard station's 0.041 mm) it is not refined even where the box
    // reaches across.
    assert!(!options.for_part(&round, &standard).refine_now);
    assert!(options.for_part(&round, &coarse).refine_now);
    assert!(options.for_part(&buttress, &coarse).refine_now);
    let no_small_box = DepthOptions { edge_window_radius_px: 0, ..DepthOptions::default() };
    assert!(!no_small_box.for_part(&buttress, &coarse).refine_now);
    let off = DepthOptions { refine_across_flanks: false, ..DepthOptions::default() };
    assert!(!off.for_part(&buttress, &coarse).refine_now);
    // Options stored before it existed refine where for_part finds the box across a flank;
    // options not resolved for a part never do.
    let old: DepthOptions =
        serde_json::from_str(r#"{"window_radius_px": 4, "min_peak_ratio": 1.6, "peak_fraction": 0.3}"#).unwrap();
    assert!(old.refine_across_flanks && !old.refine_now);
    assert!(old.for_part(&buttress, &coarse).refine_now);
}

#[test]
fn the_small_box_locates_its_own_peak_next_to_the_big_box_s_and_only_a_trusted_one() {
    let offsets: Vec<f64> = (0..12).map(|k| k as f64 * 0.3).collect();
    let mut sorted = vec![0f32; 12];
    // A symmetric peak centred between frames 5 and 6 (offset 1.65 mm).
    let small = [1.0, 1.0, 1.0, 1.1, 2.0, 6.0, 6.0, 2.0, 1.1, 1.0, 1.0, 1.0];
    let at = |k_best| small_box_offset(&small, &mut sorted.clone(), &offsets, k_best, 1.6, 0.3);
    for k_best in [4, 5, 6, 7] {
        let o = at(k_best).unwrap();
        assert!((o - 1.65).abs() < 1e-9, "{k_best}: {o}");
    }
    // The big box's peak two frames off: the small box's highest frame within one of it is a
    // shoulder, and the located offset is the same curve's (the caller's step bound rejects it
    // where it lies a step away).
    assert!(at(3).is_some());
    // A curve that does not rise 1.6 times over its floor is noise: not used.
    let flat = [1.0, 1.1, 1.0, 1.2, 1.3, 1.4, 1.3, 1.2, 1.1, 1.0, 1.0, 1.0];
    assert_eq!(small_box_offset(&flat, &mut sorted, &offsets, 5, 1.6, 0.3), None);
    // A peak at the stack's end has no shoulder there: none.
    let end = [6.0, 6.0, 2.0, 1.1, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0];
    assert_eq!(small_box_offset(&end, &mut sorted, &offsets, 0, 1.6, 0.3), None);
}
