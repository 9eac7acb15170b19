//! The focus measure: the squared Laplacian, box-summed over a window (vertical then horizontal
//! running sums, with an AVX2 path for the horizontal sums that is bit for bit the scalar one).

/// [`focus_measures`] with one box.
#[cfg(test)]
pub(super) fn focus_measure(gray: &[f32], w: usize, h: usize, r: usize, scratch: &mut [f32], out: &mut [f32]) {
    focus_measures(gray, w, h, r, scratch, out, None)
}

/// Squared Laplacian, box-summed over (2r+1)², written into `out`; with `edge` = (r_edge, plane),
/// the same Laplacian summed over the box of half size r_edge into that plane as well (one
/// Laplacian for both). `scratch` is reused.
///
/// Every pass runs along whole rows so that it vectorises: the Laplacian, a running sum of rows
/// (the vertical box), then the horizontal box as 2r+1 shifted row additions (a running sum along
/// a row is one long dependency chain).
pub fn focus_measures(
    gray: &[f32],
    w: usize,
    h: usize,
    r: usize,
    scratch: &mut [f32],
    out: &mut [f32],
    edge: Option<(usize, &mut [f32])>,
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the processor has AVX2 (checked just above).
        return unsafe { focus_measures_avx2(gray, w, h, r, scratch, out, edge) };
    }
    focus_measures_body::<false>(gray, w, h, r, scratch, out, edge)
}

/// [`focus_measures_body`] compiled for AVX2. The build targets baseline x86-64 (SSE2), so the
/// binary runs anywhere; these passes are element-wise, so either copy gives the same numbers
/// (unit-tested). Only the loops that measured faster with AVX2 have a second copy; the median
/// network, the argmax over frames and a whole x86-64-v3 build measured slower (the figures:
/// docs/notebook/accuracy.md, Speed).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(super) fn focus_measures_avx2(
    gray: &[f32],
    w: usize,
    h: usize,
    r: usize,
    scratch: &mut [f32],
    out: &mut [f32],
    edge: Option<(usize, &mut [f32])>,
) {
    focus_measures_body::<true>(gray, w, h, r, scratch, out, edge)
}

/// `AVX2`: the horizontal box by [`horizontal_box_row_avx2`] (only where the processor has it).
#[inline(always)]
pub(super) fn focus_measures_body<const AVX2: bool>(
    gray: &[f32],
    w: usize,
    h: usize,
    r: usize,
    scratch: &mut [f32],
    out: &mut [f32],
    edge: Option<(usize, &mut [f32])>,
) {
    if w == 0 || h == 0 {
        return;
    }
    match edge {
        None => {
            laplacian_squared(gray, w, h, out);
            vertical_box(out, w, h, r, scratch);
            horizontal_box::<AVX2>(scratch, w, h, r, out);
        }
        Some((r_edge, edge_out)) => {
            laplacian_squared(gray, w, h, edge_out);
            vertical_box(edge_out, w, h, r, scratch);
            horizontal_box::<AVX2>(scratch, w, h, r, out);
            vertical_box(edge_out, w, h, r_edge, scratch);
            horizontal_box::<AVX2>(scratch, w, h, r_edge, edge_out);
        }
    }
}

/// The squared Laplacian (4-neighbour), zero on the frame's border.
#[inline(always)]
pub(super) fn laplacian_squared(gray: &[f32], w: usize, h: usize, out: &mut [f32]) {
    out[..w].fill(0.0);
    out[(h - 1) * w..].fill(0.0);
    for y in 1..h.saturating_sub(1) {
        let (up, mid, down) = (&gray[(y - 1) * w..y * w], &gray[y * w..(y + 1) * w], &gray[(y + 1) * w..(y + 2) * w]);
        let row = &mut out[y * w..(y + 1) * w];
        row[0] = 0.0;
        row[w - 1] = 0.0;
        let inner = w.saturating_sub(2);
        let (left, centre, right) = (&mid[..inner], &mid[1..inner + 1], &mid[2..inner + 2]);
        let (up, down) = (&up[1..inner + 1], &down[1..inner + 1]);
        for (i, o) in row[1..inner + 1].iter_mut().enumerate() {
            let lap = 4.0 * centre[i] - left[i] - right[i] - up[i] - down[i];
            *o = lap * lap;
        }
    }
}

/// The vertical box of half size r: a running sum of rows, `src` → `dst`.
#[inline(always)]
pub(super) fn vertical_box(src: &[f32], w: usize, h: usize, r: usize, dst: &mut [f32]) {
    let mut acc = vec![0f32; w];
    for y in 0..r.min(h) {
        for (a, &v) in acc.iter_mut().zip(&src[y * w..(y + 1) * w]) {
            *a += v;
        }
    }
    for y in 0..h {
        if y + r < h {
            for (a, &v) in acc.iter_mut().zip(&src[(y + r) * w..(y + r + 1) * w]) {
                *a += v;
            }
        }
        if y > r {
            for (a, &v) in acc.iter_mut().zip(&src[(y - r - 1) * w..(y - r) * w]) {
                *a -= v;
            }
        }
        dst[y * w..(y + 1) * w].copy_from_slice(&acc);
    }
}

/// The horizontal box of half size r, `src` → `dst`, as 2r+1 shifted row additions; clamped at
/// zero (the running sums' rounding can leave a hair below it).
#[inline(always)]
pub(super) fn horizontal_box<const AVX2: bool>(src: &[f32], w: usize, h: usize, r: usize, dst: &mut [f32]) {
    for y in 0..h {
        let (src, dst) = (&src[y * w..(y + 1) * w], &mut dst[y * w..(y + 1) * w]);
        #[cfg(target_arch = "x86_64")]
        if AVX2 {
            // SAFETY: AVX2 is only asked for from `focus_measures_avx2`, which runs where the
            // processor has it.
            unsafe { horizontal_box_row_avx2(src, r, dst) };
            continue;
        }
        dst.fill(0.0);
        for d in 0..=2 * r {
            // dst[x] += src[x + d − r] wherever both are in the row.
            let (from, to) = if d >= r { (d - r, 0) } else { (0, r - d) };
            let len = w.saturating_sub(from.max(to));
            if len == 0 {
                continue; // a row narrower than the box: this shift reaches no pixel
            }
            for (o, &v) in dst[to..to + len].iter_mut().zip(&src[from..from + len]) {
                *o += v;
            }
        }
        for o in dst.iter_mut() {
            *o = o.max(0.0);
        }
    }
}

/// One row of [`horizontal_box`] with each output's 2r + 1 terms added into one AVX2 accumulator,
/// eight outputs at a time, in the same order as the shifted row additions (bit for bit the same
/// sums): the row additions store and reload the row 2r + 1 times. Written with intrinsics because
/// the compiler turned the overlapping loads of plain slices into shuffles.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(super) fn horizontal_box_row_avx2(src: &[f32], r: usize, dst: &mut [f32]) {
    use std::arch::x86_64::{_mm256_add_ps, _mm256_loadu_ps, _mm256_max_ps, _mm256_setzero_ps, _mm256_storeu_ps};
    const LANES: usize = 8;
    let w = src.len().min(dst.len());
    // The terms within the row, left to right from 0 (the row additions' order where the box
    // reaches past an end).
    let at_edge = |x: usize| src[x.saturating_sub(r)..=(x + r).min(w - 1)].iter().fold(0f32, |a, &v| a + v).max(0.0);
    let inner_end = w.saturating_sub(r); // every x in r..inner_end has its whole box in the row
    let mut x = 0;
    while x < r.min(w) {
        dst[x] = at_edge(x);
        x += 1;
    }
    // Four blocks at a time: four independent chains of additions, not one waiting on the last.
    while x + 4 * LANES <= inner_end {
        // SAFETY: as below, for each of the four blocks.
        unsafe {
            let p = src.as_ptr().add(x - r);
            let (mut a0, mut a1, mut a2, mut a3) =
                (_mm256_setzero_ps(), _mm256_setzero_ps(), _mm256_setzero_ps(), _mm256_setzero_ps());
            for d in 0..=2 * r {
                a0 = _mm256_add_ps(a0, _mm256_loadu_ps(p.add(d)));
                a1 = _mm256_add_ps(a1, _mm256_loadu_ps(p.add(d + LANES)));
                a2 = _mm256_add_ps(a2, _mm256_loadu_ps(p.add(d + 2 * LANES)));
                a3 = _mm256_add_ps(a3, _mm256_loadu_ps(p.add(d + 3 * LANES)));
            }
            let out = dst.as_mut_ptr().add(x);
            for (k, a) in [a0, a1, a2, a3].into_iter().enumerate() {
                _mm256_storeu_ps(out.add(k * LANES), _mm256_max_ps(a, _mm256_setzero_ps()));
            }
        }
        x += 4 * LANES;
    }
    while x + LANES <= inner_end {
        // SAFETY: x − r + d + 7 ≤ x + r + 7 < inner_end + r = w for every d ≤ 2r, and x + 7 < w.
        unsafe {
            let mut acc = _mm256_setzero_ps();
            for d in 0..=2 * r {
                acc = _mm256_add_ps(acc, _mm256_loadu_ps(src.as_ptr().add(x - r + d)));
            }
            // The sums are never −0 (they start at +0), so maxps and f32::max agree.
            _mm256_storeu_ps(dst.as_mut_ptr().add(x), _mm256_max_ps(acc, _mm256_setzero_ps()));
        }
        x += LANES;
    }
    while x < w {
        dst[x] = at_edge(x);
        x += 1;
    }
}
