//! Dropping speckles: small regions of a depth map whose depths hang together but not with their
//! surroundings. Neighbouring pixels share all but a row or column of their focus windows, so a
//! focus peak on noise, on a clipped highlight or on another surface's edge is not one pixel but
//! a patch about a window wide, at a depth of its own; a surface the window resolved is a
//! connected region many windows wide. (The stereo literature's speckle filter, e.g. OpenCV's
//! `filterSpeckles`.)

use super::DepthMap;

/// Sets to NaN every 4-connected region of trusted pixels, linked where neighbours' depths differ
/// by at most `link_mm`, that holds fewer than `min_pixels`. Returns how many pixels it dropped.
pub fn drop_speckles(map: &mut DepthMap, link_mm: f32, min_pixels: usize) -> usize {
    let (w, rows) = (map.width, map.rows());
    let depth = &mut map.depth_mm;
    const UNSEEN: u32 = u32::MAX;
    let mut region = vec![UNSEEN; depth.len()];
    let (mut members, mut queue): (Vec<usize>, std::collections::VecDeque<usize>) = Default::default();
    let mut dropped = 0;
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
        if members.len() < min_pixels {
            for &i in &members {
                depth[i] = f32::NAN;
            }
            dropped += members.len();
        }
    }
    dropped
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
            all_in_focus: vec![0.5; 3 * w * h],
            end_edges: Vec::new(),
        }
    }

    #[test]
    fn a_patch_at_a_depth_of_its_own_is_dropped_and_the_surfaces_kept() {
        let (w, h) = (60, 40);
        // Two surfaces a thread height apart (a step at x = 30), each tilted a little, and a 5×5
        // patch 2 mm off on the first.
        let mut depth: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                200.0 + if x < 30 { 0.0 } else { 1.6 } + 0.001 * (x + y) as f32
            })
            .collect();
        for y in 10..15 {
            for x in 5..10 {
                depth[y * w + x] += 2.0;
            }
        }
        // An untrusted pixel inside the first surface does not split it.
        depth[20 * w + 20] = f32::NAN;
        let mut m = map(w, h, depth);
        assert_eq!(drop_speckles(&mut m, 0.1, 121), 25);
        for y in 0..h {
            for x in 0..w {
                let patch = (10..15).contains(&y) && (5..10).contains(&x);
                assert_eq!(m.depth_mm[y * w + x].is_nan(), patch || (x, y) == (20, 20), "{x},{y}");
            }
        }
    }
}
