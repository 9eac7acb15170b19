//! The end-face anchor: absolute z from the pipe end's silhouette.
//!
//! Registration fixes the views relative to each other, but a common axial shift of the whole ring
//! is invisible in the overlaps, so the reconstruction inherits the encoders' mean axial error, and
//! along the helix every 14 µm of z is a degree (it moves where arcs are cut at Lc). The contract
//! puts z = 0 at the end face. A view that sees the end shows, left of the part, background; the
//! part begins at the corner where the end face meets the chamfer (the outermost point of the end,
//! the first that a ray from the lens grazes). Per frame the depth stage records, for every row
//! whose first columns are background, the first lit column and the focus measure there
//! ([`frame_edge`]). Here the frame sequence gives the corner's depth (the focus curve of the edge
//! pixels), the frame focused on it gives the corner's column per row, each row's ray is followed
//! through the refined pose to the corner circle; the mean z over a view's rows, and the median of
//! that over the views that see the end, is the ring's axial offset ([`anchor`]).

use crate::domain::optics::{Optics, Projection, ViewPose};
use serde::{Deserialize, Serialize};

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

/// The ring's axial offset found on the end face: the z the reconstruction gives the corner.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EndFace {
    /// Views that saw the end.
    pub views: usize,
    /// Reconstructed z of the corner (median over the views; 0 when the poses are right), mm;
    /// subtract it.
    pub z_offset_mm: f64,
    /// Robust scatter of the per-view values (1.4826 MAD), µm.
    pub scatter_um: f64,
    /// Radius of the corner circle, mm.
    pub corner_radius_mm: f64,
}

/// Per view: the corner's reconstructed z, from the frames' edges and the view's (refined) pose.
fn corner_z(optics: &Optics, pose: &ViewPose, edges: &[FrameEdge], width: u32, height: u32) -> Option<(f64, f64)> {
    if optics.projection != Projection::Perspective || edges.len() < 3 {
        return None;
    }
    // The silhouette's sharpness through the stack is flat-topped (sharp within the depth of
    // field), so, as for the surface, focus is the midpoint of its shoulders.
    let k = (0..edges.len()).max_by(|&a, &b| edges[a].focus.total_cmp(&edges[b].focus))?;
    let sharpness: Vec<f32> = edges.iter().map(|e| e.focus as f32).collect();
    let offsets: Vec<f64> = edges.iter().map(|e| e.offset_mm).collect();
    let floor = crate::numeric::stats::median(&mut edges.iter().map(|e| e.focus).collect::<Vec<_>>())? as f32;
    let in_focus = crate::pipeline::depth::peak_offset(&sharpness, &offsets, k, floor, 0.3)?;
    let to_pipe = pose.camera_to_pipe();
    let principal = optics.principal_point(width, height);
    // The corner's radius: on the middle row's ray at the in-focus depth (from the offset-0 lens).
    let frame = &edges[k];
    let (_, u_mid) = frame.rows[frame.rows.len() / 2];
    let ray = optics.pixel_ray(u_mid as f64 - 0.5, principal[1] - 0.5, principal, 0.0);
    let corner = to_pipe * ray.at(optics.focus_distance_mm - in_focus);
    let radius = corner.coords.xy().norm();
    // Each row's edge, as the continuous column where the part begins (pixels are sampled at their
    // centres: the first lit centre is the first past the edge, on average half a pixel), on the
    // frame's own ray, meets the corner circle at the corner.
    let mut sum = 0.0;
    for &(y, u) in &frame.rows {
        let ray = optics.pixel_ray(u as f64 - 0.5, y as f64, principal, frame.offset_mm);
        let (origin, direction) = (to_pipe * ray.origin, to_pipe * ray.direction);
        // |origin.xy + t·direction.xy| = radius, the nearer root.
        let (p, d) = (origin.coords.xy(), direction.xy());
        let (qa, qb, qc) = (d.norm_squared(), 2.0 * p.dot(&d), p.norm_squared() - radius * radius);
        let disc = qb * qb - 4.0 * qa * qc;
        if disc < 0.0 {
            return None;
        }
        let t = (-qb - disc.sqrt()) / (2.0 * qa);
        sum += origin.z + t * direction.z;
    }
    Some((sum / frame.rows.len() as f64, radius))
}

/// The ring's axial offset from every view that saw the end (the median); None unless at least
/// `min_views` did and their values agree within `max_scatter_um` (robust scatter).
pub fn anchor(
    optics: &Optics,
    poses: &[ViewPose],
    edges: &[&[FrameEdge]],
    width: u32,
    height: u32,
    min_views: usize,
    max_scatter_um: f64,
) -> Option<EndFace> {
    let found: Vec<(f64, f64)> =
        poses.iter().zip(edges).filter_map(|(pose, e)| corner_z(optics, pose, e, width, height)).collect();
    if found.len() < min_views.max(1) {
        return None;
    }
    // Median and a robust scatter (1.4826 MAD): a view whose corner depth the sharpness curve got
    // wrong lands far off.
    let mut z: Vec<f64> = found.iter().map(|f| f.0).collect();
    let mut r: Vec<f64> = found.iter().map(|f| f.1).collect();
    let z_offset_mm = crate::numeric::stats::median(&mut z)?;
    let scatter_um = 1e3 * crate::numeric::stats::robust_scale(z.iter().map(|v| v - z_offset_mm))?;
    let corner_radius_mm = crate::numeric::stats::median(&mut r)?;
    (scatter_um <= max_scatter_um).then_some(EndFace { views: found.len(), z_offset_mm, scatter_um, corner_radius_mm })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rows' first lit columns for a corner circle of radius `r` at z = 0 seen from `pose` at
    /// frame offset `o`: the first pixel whose centre ray meets the circle at z ≥ 0.
    fn silhouette(optics: &Optics, pose: &ViewPose, r: f64, o: f64, w: u32, h: u32) -> Vec<(u32, u32)> {
        let principal = optics.principal_point(w, h);
        let to_pipe = pose.camera_to_pipe();
        (0..h)
            .filter_map(|y| {
                (0..w / 4)
                    .find(|&u| {
                        let ray = optics.pixel_ray(u as f64, y as f64, principal, o);
                        let (p, d) = ((to_pipe * ray.origin).coords, to_pipe * ray.direction);
                        let (a, b, c) =
                            (d.xy().norm_squared(), 2.0 * p.xy().dot(&d.xy()), p.xy().norm_squared() - r * r);
                        let disc = b * b - 4.0 * a * c;
                        disc >= 0.0 && p.z + d.z * (-b - disc.sqrt()) / (2.0 * a) >= 0.0
                    })
                    .map(|u| (y, u))
            })
            .collect()
    }

    #[test]
    fn the_silhouette_is_found_after_the_background_columns() {
        let (w, h) = (64, 6);
        let gray: Vec<f32> = (0..w * h).map(|i| if i % w >= 7 + i / w { 0.5 } else { 0.001 }).collect();
        let edge = frame_edge(&gray, w, h, -1.0).expect("background then part on every row");
        assert_eq!(edge.rows, (0..h as u32).map(|y| (y, 7 + y)).collect::<Vec<_>>());
        // A frame the part fills from its first column shows no end.
        assert!(frame_edge(&vec![0.5; w * h], w, h, -1.0).is_none());
    }

    #[test]
    fn a_rings_common_axial_offset_is_found_on_the_corner() {
        // Eight views whose poses all sit 0.03 mm too low in z (what registration cannot see); the
        // corner circle (r 54.07 mm) is in focus at offset −1.55 mm in each stack.
        let optics = crate::sim::presets::standard_optics();
        let (w, h, r) = (864u32, 320u32, 54.07);
        let truth: Vec<ViewPose> =
            (0..8).map(|i| ViewPose { angle_deg: 45.0 * i as f64, axial_mm: 17.3, lens_radius_mm: 275.6 }).collect();
        let offsets: Vec<f64> = (0..20).map(|k| -2.5 + 0.25 * k as f64).collect();
        let focus_at = 220.0 - (275.6 - r); // the offset at which the corner is at the focus distance
        let edges: Vec<Vec<FrameEdge>> = truth
            .iter()
            .map(|pose| {
                offsets
                    .iter()
                    .map(|&o| FrameEdge {
                        offset_mm: o,
                        // A flat-topped sharpness curve about the corner's focus.
                        focus: 1.0 / (1.0 + (((o - focus_at).abs() - 0.25).max(0.0) / 0.2).powi(2)) + 0.05,
                        rows: silhouette(&optics, pose, r, o, w, h),
                    })
                    .collect()
            })
            .collect();
        let believed: Vec<ViewPose> = truth.iter().map(|p| ViewPose { axial_mm: p.axial_mm - 0.03, ..*p }).collect();
        let edges: Vec<&[FrameEdge]> = edges.iter().map(Vec::as_slice).collect();
        let end = anchor(&optics, &believed, &edges, w, h, 3, 20.0).expect("every view sees the end");
        assert_eq!(end.views, 8);
        // Pixel-centre sampling places each row's edge within half a pixel (20 µm); the rows of a
        // view and the views average it down.
        assert!((end.z_offset_mm + 0.03).abs() < 0.006, "{end:?}");
        assert!((end.corner_radius_mm - r).abs() < 0.05, "{end:?}");
    }
}
