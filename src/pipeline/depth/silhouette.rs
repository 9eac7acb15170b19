//! The end face's silhouette in one frame: per row whose first columns are background, the first
//! lit column, and how sharp the silhouette is. Measured per frame beside the focus measure;
//! [`crate::pipeline::register::anchor`] turns it into the ring's absolute z after registration.

/// One frame's view of the end: rows (y, first lit column) and how sharp the silhouette is.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameEdge {
    pub offset_mm: f64,
    pub focus: f64,
    pub rows: Vec<(u32, u32)>,
}

/// Columns at the image's −z side that must be background for a row to count.
const BACKGROUND_COLUMNS: usize = 3;

/// The end's silhouette in one frame (gray, on the frame's own grid), if at
/// least half the rows show background at the −z side and the part within the first quarter of
/// the width. Background is darker than a tenth of the frame's mean brightness.
pub fn frame_edge(gray: &[f32], w: usize, h: usize, offset_mm: f64) -> Option<FrameEdge> {
    if w < 4 * BACKGROUND_COLUMNS || h == 0 {
        return None;
    }
    // Summed in eight lanes: one running f32 sum is a chain of dependent adds, as long as the frame.
    let (chunks, rest) = gray.as_chunks::<8>();
    let lanes = chunks.iter().fold([0f32; 8], |mut acc, c| {
        for l in 0..8 {
            acc[l] += c[l];
        }
        acc
    });
    let bar = 0.1 * (lanes.iter().sum::<f32>() + rest.iter().sum::<f32>()) / gray.len() as f32;
    let mut rows = Vec::new();
    // The focus is read on the middle third of the rows: the corner circle recedes from the lens
    // away from the middle row, and the depth it gives is the middle row's.
    let (mut focus, mut middle) = (0f64, 0usize);
    for y in 0..h {
        let row = &gray[y * w..(y + 1) * w];
        if row[..BACKGROUND_COLUMNS].iter().any(|&g| g >= bar) {
            continue;
        }
        if let Some(u) = row[..w / 4].iter().position(|&g| g >= bar) {
            rows.push((y as u32, u as u32));
            if 3 * y >= h && 3 * y < 2 * h {
                // The silhouette's sharpness: its steepest step near the first lit column (a box
                // of focus measure there would also see the chamfer behind the corner).
                let steepest = (u.max(1)..(u + 3).min(w)).map(|j| row[j] - row[j - 1]).fold(0f32, f32::max);
                focus += steepest as f64;
                middle += 1;
            }
        }
    }
    (2 * rows.len() >= h && middle > 0).then(|| FrameEdge { offset_mm, focus: focus / middle as f64, rows })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_silhouette_is_found_after_the_background_columns() {
        let (w, h) = (64, 6);
        let gray: Vec<f32> = (0..w * h).map(|i| if i % w >= 7 + i / w { 0.5 } else { 0.001 }).collect();
        let edge = frame_edge(&gray, w, h, -1.0).expect("background then part on every row");
        assert_eq!(edge.rows, (0..h as u32).map(|y| (y, 7 + y)).collect::<Vec<_>>());
        // A frame the part fills from its first column shows no end.
        assert!(frame_edge(&vec![0.5; w * h], w, h, -1.0).is_none());
    }
}
