//! Dropping speckles: small regions of a depth map whose depths hang together but not with their
//! surroundings. Neighbouring pixels share all but a row or column of their focus windows, so a
//! focus peak on noise, on a clipped highlight or on another surface's edge is not one pixel but
//! a patch about a window wide, at a depth of its own; a surface the window resolved is a
//! connected region many windows wide. (The stereo literature's speckle filter, e.g. OpenCV's
//! `filterSpeckles`.)

use super::DepthMap;

/// The share of a map's trusted pixels in speckles below which none is dropped: where speckles
/// are that rare they are mostly true detail and dropping them takes only data; where they are
/// common they are mostly gross errors (figures: docs/notebook/accuracy.md, "Figures moved from
/// code comments").
pub const MIN_SPECKLE_SHARE: f64 = 0.02;

/// Sets to NaN every 4-connected region of trusted pixels, linked where neighbours' depths differ
/// by at most `link_mm`, that holds fewer than `min_pixels`, where such regions hold at least
/// [`MIN_SPECKLE_SHARE`] of the trusted pixels. Returns how many pixels it dropped.
pub fn drop_speckles(map: &mut DepthMap, link_mm: f32, min_pixels: usize) -> usize {
    let (w, rows) = (map.width, map.rows());
    let depth = &mut map.depth_mm;
    const UNSEEN: u32 = u32::MAX;
    let mut region = vec![UNSEEN; depth.len()];
    let (mut members, mut queue): (Vec<usize>, std::collections::VecDeque<usize>) = Default::default();
    let (mut speckled, mut trusted) = (Vec::new(), 0usize);
    for start in 0..depth.len() {
        if region[start] != UNSEEN || !depth[start].is_finite() {
            continue;
        }
        members.clear();
        region[start] = start as u32;
        queue.push_back(start);
        while let Some(i) = queue.pop_front() {
            members.push(i);
            let (x, y) = (i % w, i / w);
            let neighbours = [
                (x > 0).then(|| i - 1),
                (x + 1 < w).then(|| i + 1),
                (y > 0).then(|| i - w),
                (y + 1 < rows).then(|| i + w),
            ];
            for j in neighbours.into_iter().flatten() {
                if region[j] == UNSEEN && depth[j].is_finite() && (depth[j] - depth[i]).abs() <= link_mm {
                    region[j] = start as u32;
                    queue.push_back(j);
                }
            }
        }
        trusted += members.len();
        if members.len() < min_pixels {
            speckled.extend_from_slice(&members);
        }
    }
    if (speckled.len() as f64) < MIN_SPECKLE_SHARE * trusted as f64 {
        return 0;
    }
    for &i in &speckled {
        depth[i] = f32::NAN;
    }
    speckled.len()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(w: usize, h: usize, depth_mm: Vec<f32>) -> DepthMap {
        DepthMap {
            width: w,
            height: h,
            row_step: 1,
            depth_mm,
            peak_ratio: vec![2.0; w * h],
            all_in_focus: vec![32768; 3 * w * h],
            end_edges: Vec::new(),
            frame_noise: None,
            prefiltered: false,
        }
    }

    /// Two surfaces a thread height apart (a step at x = 30), each tilted a little, with 5×5
    /// patches 2 mm off at the corners given, and one untrusted pixel inside the first surface.
    fn two_surfaces(w: usize, h: usize, patches: &[(usize, usize)]) -> DepthMap {
        let mut depth: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                200.0 + if x < 30 { 0.0 } else { 1.6 } + 0.001 * (x + y) as f32
            })
            .collect();
        for &(x0, y0) in patches {
            for y in y0..y0 + 5 {
                for x in x0..x0 + 5 {
                    depth[y * w + x] += 2.0;
                }
            }
        }
        depth[20 * w + 20] = f32::NAN;
        map(w, h, depth)
    }

    #[test]
    fn patches_at_a_depth_of_their_own_are_dropped_and_the_surfaces_kept() {
        let (w, h) = (60, 40);
        let patches = [(5, 10), (15, 25), (40, 5)];
        let mut m = two_surfaces(w, h, &patches);
        // 75 of 2399 trusted pixels: over MIN_SPECKLE_SHARE.
        assert_eq!(drop_speckles(&mut m, 0.1, 121), 75);
        for y in 0..h {
            for x in 0..w {
                let patch = patches.iter().any(|&(x0, y0)| (x0..x0 + 5).contains(&x) && (y0..y0 + 5).contains(&y));
                // The untrusted pixel did not split its surface into small regions.
                assert_eq!(m.depth_mm[y * w + x].is_nan(), patch || (x, y) == (20, 20), "{x},{y}");
            }
        }
    }

    #[test]
    fn where_speckles_are_rare_none_is_dropped() {
        // One 5×5 patch among 2399 trusted pixels: 1%, under MIN_SPECKLE_SHARE.
        let mut m = two_surfaces(60, 40, &[(5, 10)]);
        assert!(25.0 / 2399.0 < MIN_SPECKLE_SHARE);
        assert_eq!(drop_speckles(&mut m, 0.1, 121), 0);
        assert_eq!(m.depth_mm.iter().filter(|d| d.is_nan()).count(), 1);
    }
}
