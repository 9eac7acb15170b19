//! Runs of set bins along a sequence: their spans, and hysteresis (seeds grown over weaker bins).

/// Hysteresis along the helix: every run of `seeds` grows in both directions over the bins for
/// which `extends` holds, and over up to `bridge` bins for which it does not when the bin beyond
/// them extends the run again.
pub fn grow_runs(seeds: &[bool], extends: impl Fn(usize) -> bool, bridge: usize) -> Vec<bool> {
    let mut on = seeds.to_vec();
    let n = seeds.len();
    for span in run_spans(seeds) {
        let (mut lo, mut hi) = (span.start, span.end - 1);
        // The nearest bin within `bridge + 1` steps that extends the run, if no run is in the way.
        let next = |from: usize, step: isize, on: &[bool]| -> Option<usize> {
            (1..=bridge as isize + 1)
                .map(|k| from as isize + step * k)
                .take_while(|&i| i >= 0 && (i as usize) < n && !on[i as usize])
                .find(|&i| extends(i as usize))
                .map(|i| i as usize)
        };
        while let Some(i) = next(lo, -1, &on) {
            lo = i;
        }
        while let Some(i) = next(hi, 1, &on) {
            hi = i;
        }
        on[lo..=hi].iter_mut().for_each(|b| *b = true);
    }
    on
}

/// The maximal runs of set bins, as index ranges.
pub fn run_spans(runs: &[bool]) -> Vec<std::ops::Range<usize>> {
    let mut spans = Vec::new();
    let mut i = 0;
    while i < runs.len() {
        if runs[i] {
            let end = runs[i..].iter().position(|r| !r).map_or(runs.len(), |n| i + n);
            spans.push(i..end);
            i = end;
        } else {
            i += 1;
        }
    }
    spans
}
