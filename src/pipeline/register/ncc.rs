//! Normalised cross-correlation of two views' textures over their overlap, with an AVX2 path for
//! the overlap sums, and the sub-cell peak.

/// A texture grid laid out for correlation: missing cells are zero in the values and their
/// squares and 0 in the mask, so that the sums over a shifted overlap need no branches (and run
/// eight cells at a time). Stored by arc column (z fastest): an overlap between neighbours is long
/// in z and short in arc, and long rows keep the per-row overhead small.
#[derive(Default)]
pub(super) struct TextureGrid {
    /// Arc cells (rows of the layout) and z cells (along a row).
    ns: usize,
    nz: usize,
    value: Vec<f32>,
    square: Vec<f32>,
    mask: Vec<f32>,
}

impl TextureGrid {
    /// Every `step`-th cell of the (z-major) `field` starting at (s_phase, z_phase).
    pub(super) fn sampled(field: &[f32], ns: usize, nz: usize, step: usize, s_phase: usize, z_phase: usize) -> Self {
        let mut grid = Self::default();
        grid.sample(field, ns, nz, step, s_phase, z_phase);
        grid
    }

    /// [`TextureGrid::sampled`] into this grid's buffers.
    pub(super) fn sample(&mut self, field: &[f32], ns: usize, nz: usize, step: usize, s_phase: usize, z_phase: usize) {
        let (gs, gz) = (ns.saturating_sub(s_phase).div_ceil(step), nz.saturating_sub(z_phase).div_ceil(step));
        let cells = gs * gz;
        let grid = self;
        (grid.ns, grid.nz) = (gs, gz);
        for buffer in [&mut grid.value, &mut grid.square, &mut grid.mask] {
            buffer.clear();
            buffer.resize(cells, 0.0);
        }
        for s in 0..gs {
            for z in 0..gz {
                let v = field[(z_phase + z * step) * ns + s_phase + s * step];
                if v.is_finite() {
                    let i = s * gz + z;
                    (grid.value[i], grid.square[i], grid.mask[i]) = (v, v * v, 1.0);
                }
            }
        }
    }
}

/// Every other cell of a grid in each of the four parities (s, z), for the coarse search: a's
/// even cells are met by b's cells in the parity a shift brings onto them.
pub(super) struct StrideTwo {
    parities: [TextureGrid; 4],
}

impl StrideTwo {
    pub(super) fn new(field: &[f32], (ns, nz): (usize, usize)) -> Self {
        let at = |p: usize| TextureGrid::sampled(field, ns, nz, 2, p % 2, p / 2);
        Self { parities: [at(0), at(1), at(2), at(3)] }
    }

    /// NCC over a's even cells (s, z) against b's (s + off_s, z + off_z): a's cell 2i meets b's
    /// cell 2i + off = 2(i + off.div_euclid(2)) + off.rem_euclid(2).
    pub(super) fn ncc(a: &StrideTwo, b: &StrideTwo, off_s: i64, off_z: i64, min_cells: usize) -> (f64, usize) {
        let phase = (off_s.rem_euclid(2) + 2 * off_z.rem_euclid(2)) as usize;
        ncc_grids(&a.parities[0], &b.parities[phase], off_s.div_euclid(2), off_z.div_euclid(2), min_cells)
    }
}

/// Σ a·b over equal-length slices, in eight f32 lanes (one pass per product vectorises cleanly;
/// six products in one loop spill registers).
pub(super) fn dot(a: &[f32], b: &[f32]) -> f64 {
    const LANES: usize = 8;
    let (a_chunks, a_rest) = a.as_chunks::<LANES>();
    let (b_chunks, b_rest) = b.as_chunks::<LANES>();
    let mut lanes = [0f32; LANES];
    for (x, y) in a_chunks.iter().zip(b_chunks) {
        for l in 0..LANES {
            lanes[l] += x[l] * y[l];
        }
    }
    let rest: f32 = a_rest.iter().zip(b_rest).map(|(x, y)| x * y).sum();
    lanes.iter().map(|&v| v as f64).sum::<f64>() + rest as f64
}

/// The six sums of [`ncc_grids`] over the overlap: per column, the dot products of (mask a, mask
/// b), (a, mask b), (mask a, b), (a², mask b), (mask a, b²) and (a, b), accumulated in f64.
#[inline(always)]
pub(super) fn overlap_sums(a: &TextureGrid, b: &TextureGrid, off_s: i64, off_z: i64, one_pass: bool) -> [f64; 6] {
    let (s_lo, s_hi) = ((-off_s).max(0), (b.ns as i64 - off_s).min(a.ns as i64));
    let (z_lo, z_hi) = ((-off_z).max(0), (b.nz as i64 - off_z).min(a.nz as i64));
    let mut total = [0f64; 6];
    if z_lo >= z_hi {
        return total;
    }
    let len = (z_hi - z_lo) as usize;
    for s in s_lo..s_hi {
        let (ia, ib) = (s as usize * a.nz + z_lo as usize, (s + off_s) as usize * b.nz + (z_lo + off_z) as usize);
        let (xa, qa, ma) = (&a.value[ia..ia + len], &a.square[ia..ia + len], &a.mask[ia..ia + len]);
        let (xb, qb, mb) = (&b.value[ib..ib + len], &b.square[ib..ib + len], &b.mask[ib..ib + len]);
        let pairs = [(ma, mb), (xa, mb), (ma, xb), (qa, mb), (ma, qb), (xa, xb)];
        if one_pass {
            // The same eight lanes per product, added in the same order as `dot` adds them (so the
            // sums are bit for bit those of six passes), in one pass over the twelve rows: with
            // sixteen 256-bit registers the six accumulators and the loads fit.
            const LANES: usize = 8;
            let mut lanes = [[0f32; LANES]; 6];
            let chunks = len / LANES;
            for c in 0..chunks {
                let at = c * LANES;
                for (acc, (u, v)) in lanes.iter_mut().zip(pairs) {
                    let (u, v) = (&u[at..at + LANES], &v[at..at + LANES]);
                    for l in 0..LANES {
                        acc[l] += u[l] * v[l];
                    }
                }
            }
            for ((t, acc), (u, v)) in total.iter_mut().zip(&lanes).zip(pairs) {
                let rest: f32 = u[chunks * LANES..].iter().zip(&v[chunks * LANES..]).map(|(x, y)| x * y).sum();
                *t += acc.iter().map(|&v| v as f64).sum::<f64>() + rest as f64;
            }
        } else {
            for (t, (u, v)) in total.iter_mut().zip(pairs) {
                *t += dot(u, v);
            }
        }
    }
    total
}

/// [`overlap_sums`] compiled for AVX2, where the one-pass form fits in registers.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(super) fn overlap_sums_avx2(a: &TextureGrid, b: &TextureGrid, off_s: i64, off_z: i64) -> [f64; 6] {
    overlap_sums(a, b, off_s, off_z, true)
}

/// NCC of a's values with b's where a's cell (s, z) meets b's cell (s + off_s, z + off_z), over
/// the cells where both have data; (−1, n) when fewer than `min_cells` meet. Returns (ncc, cells).
///
/// The build targets baseline x86-64 (SSE2), so the binary runs anywhere; this loop, registration's
/// largest, takes AVX2 where the processor has it (the same sums either way). Only loops measured
/// faster that way have two copies (see also `depth::measure`): the whole program built for
/// x86-64-v3 was slower (docs/notebook/accuracy.md, Speed).
pub(super) fn ncc_grids(a: &TextureGrid, b: &TextureGrid, off_s: i64, off_z: i64, min_cells: usize) -> (f64, usize) {
    #[cfg(target_arch = "x86_64")]
    let total = if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the processor has AVX2 (checked just above).
        unsafe { overlap_sums_avx2(a, b, off_s, off_z) }
    } else {
        overlap_sums(a, b, off_s, off_z, false)
    };
    #[cfg(not(target_arch = "x86_64"))]
    let total = overlap_sums(a, b, off_s, off_z, false);
    let [n, sa, sb, saa, sbb, sab] = total;
    let cells = n.round() as usize;
    if cells < min_cells {
        return (-1.0, cells);
    }
    let cov = sab - sa * sb / n;
    let var = (saa - sa * sa / n) * (sbb - sb * sb / n);
    (if var > 0.0 { cov / var.sqrt() } else { -1.0 }, cells)
}

/// Vertex offset in (−0.5, 0.5) of the parabola through three equally spaced samples.
pub(super) fn sub_cell(left: f64, centre: f64, right: f64) -> f64 {
    let denom = left - 2.0 * centre + right;
    if denom < 0.0 { (0.5 * (left - right) / denom).clamp(-0.5, 0.5) } else { 0.0 }
}

/// Centre offset in (−0.5, 0.5) of the Gaussian through three equally spaced samples (the
/// parabola through their logarithms), exact for a Gaussian peak, where a parabola's estimate is
/// pulled toward the centre cell; the parabola's when a neighbour is not positive.
pub(super) fn sub_cell_gaussian(left: f64, centre: f64, right: f64) -> f64 {
    if left > 0.0 && centre > 0.0 && right > 0.0 {
        sub_cell(left.ln(), centre.ln(), right.ln())
    } else {
        sub_cell(left, centre, right)
    }
}
