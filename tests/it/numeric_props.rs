//! Property tests for the numeric primitives: each invariant the stages rely on, over random input.

use crestscan::numeric::angle::{wrap_pi, wrap_turn};
use crestscan::numeric::runs::{grow_runs, run_spans};
use crestscan::numeric::sequence::{centred_median, median_of_five, trimmed_mean};
use crestscan::numeric::stats::{median, robust_scale};
use crestscan::numeric::union_find::components;
use proptest::prelude::*;
use std::f64::consts::{PI, TAU};

fn finite() -> impl Strategy<Value = f64> {
    -1e6f64..1e6
}

/// A gappy sequence: some bins measured, some not.
fn gappy(max_len: usize) -> impl Strategy<Value = Vec<Option<f64>>> {
    prop::collection::vec(prop::option::weighted(0.8, -2.0f64..2.0), 0..max_len)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn the_median_is_the_upper_middle_of_the_sorted_values(values in prop::collection::vec(finite(), 0..60)) {
        let mut sorted = values.clone();
        sorted.sort_by(f64::total_cmp);
        let mut scratch = values.clone();
        prop_assert_eq!(median(&mut scratch), sorted.get(sorted.len() / 2).copied());
    }

    #[test]
    fn the_robust_scale_scales_with_its_deviations(values in prop::collection::vec(-10.0f64..10.0, 1..60), k in 0.01f64..100.0) {
        let s = robust_scale(values.iter().copied()).unwrap();
        let scaled = robust_scale(values.iter().map(|v| -k * v)).unwrap();
        prop_assert!(s >= 0.0);
        prop_assert!((scaled - k * s).abs() <= 1e-9 * (1.0 + k * s), "{} vs {}", scaled, k * s);
    }

    #[test]
    fn run_spans_round_trip_and_are_maximal(bins in prop::collection::vec(any::<bool>(), 0..80)) {
        let spans = run_spans(&bins);
        let mut rebuilt = vec![false; bins.len()];
        for span in &spans {
            prop_assert!(!span.is_empty());
            rebuilt[span.clone()].iter_mut().for_each(|b| *b = true);
        }
        prop_assert_eq!(&rebuilt, &bins);
        // Maximal: no two spans touch.
        for pair in spans.windows(2) {
            prop_assert!(pair[0].end < pair[1].start);
        }
    }

    #[test]
    fn hysteresis_never_shrinks_a_seed_and_grows_only_over_bins_that_extend(
        seeds in prop::collection::vec(any::<bool>(), 0..80),
        extends in prop::collection::vec(any::<bool>(), 80),
        bridge in 0usize..3,
    ) {
        let grown = grow_runs(&seeds, |i| extends[i], bridge);
        prop_assert_eq!(grown.len(), seeds.len());
        for (i, (&s, &g)) in seeds.iter().zip(&grown).enumerate() {
            prop_assert!(!s || g, "seed {} lost", i);
        }
        // Without a bridge a run grows only over bins that extend it.
        if bridge == 0 {
            for (i, (&s, &g)) in seeds.iter().zip(&grown).enumerate() {
                prop_assert!(!g || s || extends[i], "bin {} joined a run without extending it", i);
            }
        }
        // Nothing extends: the seeds stay as they are.
        prop_assert_eq!(grow_runs(&seeds, |_| false, bridge), seeds.clone());
    }

    #[test]
    fn sequence_filters_keep_gaps_and_never_reach_outside_the_values(values in gappy(60), half in 0usize..6) {
        let lo = values.iter().flatten().copied().fold(f64::INFINITY, f64::min);
        let hi = values.iter().flatten().copied().fold(f64::NEG_INFINITY, f64::max);
        for filtered in [trimmed_mean(&values, half), median_of_five(&values)] {
            prop_assert_eq!(filtered.len(), values.len());
            for (v, f) in values.iter().zip(&filtered) {
                prop_assert_eq!(v.is_none(), f.is_none(), "a gap filled or a value dropped");
                if let Some(f) = f {
                    prop_assert!(*f >= lo - 1e-12 && *f <= hi + 1e-12);
                }
            }
        }
        // The centred median needs its whole window measured, inside the sequence.
        let m = centred_median(&values, half);
        for (i, value) in m.iter().enumerate() {
            let whole = i >= half && i + half < values.len() && values[i - half..=i + half].iter().all(Option::is_some);
            prop_assert_eq!(value.is_some(), whole, "bin {}", i);
        }
    }

    #[test]
    fn angle_wraps_land_in_their_half_open_ranges(theta in -40.0f64..40.0) {
        let t = wrap_turn(theta);
        prop_assert!((0.0..TAU).contains(&t));
        prop_assert_eq!(t.to_bits(), theta.rem_euclid(TAU).to_bits());
        let p = wrap_pi(theta);
        prop_assert!(p > -PI && p <= PI);
        prop_assert!(((theta - p) / TAU - ((theta - p) / TAU).round()).abs() < 1e-9, "differs by whole turns");
    }

    #[test]
    fn components_join_exactly_the_nodes_a_path_joins(n in 1usize..20, edges in prop::collection::vec((0usize..20, 0usize..20), 0..30)) {
        let edges: Vec<(usize, usize)> = edges.into_iter().map(|(a, b)| (a % n, b % n)).collect();
        let component = components(n, edges.iter().copied());
        // Reachability by repeated relaxation, as the reference.
        let mut reach: Vec<Vec<bool>> = (0..n).map(|i| (0..n).map(|j| i == j).collect()).collect();
        for _ in 0..n {
            for &(a, b) in &edges {
                for row in reach.iter_mut() {
                    if row[a] || row[b] {
                        (row[a], row[b]) = (true, true);
                    }
                }
            }
        }
        for i in 0..n {
            prop_assert!(component[i] <= i, "the root is the component's least node");
            for j in 0..n {
                prop_assert_eq!(component[i] == component[j], reach[i][j], "{} and {}", i, j);
            }
        }
    }
}
