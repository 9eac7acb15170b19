//! The end-face anchor: absolute z from the pipe end's silhouette.
//!
//! Registration fixes the views relative to each other, but a common axial shift of the whole ring
//! is invisible in the overlaps, so the reconstruction inherits the encoders' mean axial error, and
//! along the helix every 14 µm of z is a degree (it moves where arcs are cut at Lc). The contract
//! puts z = 0 at the end face. A view that sees the end shows, left of the part, background; the
//! part begins at the corner where the end face meets the chamfer (the outermost point of the end,
//! the first that a ray from the lens grazes). Per frame the depth stage records, for every row
//! whose first columns are background, the first lit column and the focus measure there
//! ([`crate::pipeline::depth::frame_edge`]). Here the frame sequence gives the corner's depth (the focus curve of the edge
//! pixels), the frame focused on it gives the corner's column per row, each row's ray is followed
//! through the refined pose to the corner circle; the mean z over a view's rows, and the median of
//! that over the views that see the end, is the ring's axial offset ([`anchor`]).

use crate::domain::optics::{Optics, Projection, ViewPose};
use crate::pipeline::depth::FrameEdge;
use serde::{Deserialize, Serialize};

/// The ring's axial offset found on the end face: the z the reconstruction gives the corner.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
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

/// Each view's corner as that view alone reconstructs it: (z, radius), where it saw the end.
pub fn corners(
    optics: &Optics,
    poses: &[ViewPose],
    edges: &[&[FrameEdge]],
    width: u32,
    height: u32,
) -> Vec<Option<(f64, f64)>> {
    poses.iter().zip(edges).map(|(pose, e)| corner_z(optics, pose, e, width, height)).collect()
}

/// The ring's axial offset from the views that saw the end among those `ring` marks (the views
/// registration tied together), the median of their `corners`; None unless at least `min_views`
/// did and their values agree within `max_scatter_um` (robust scatter).
pub fn anchor(corners: &[Option<(f64, f64)>], ring: &[bool], min_views: usize, max_scatter_um: f64) -> Option<EndFace> {
    let found: Vec<(f64, f64)> = corners.iter().zip(ring).filter(|(_, r)| **r).filter_map(|(v, _)| *v).collect();
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
    fn a_rings_common_axial_offset_is_found_on_the_corner() {
        // Eight views whose poses all sit 0.03 mm too low in z (what registration cannot see); the
        // corner circle (r 54.07 mm) is in focus at offset −1.55 mm in each stack.
        let optics = Optics::standard_camera();
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
        let corners = corners(&optics, &believed, &edges, w, h);
        let end = anchor(&corners, &[true; 8], 3, 20.0).expect("every view sees the end");
        assert_eq!(end.views, 8);
        // Pixel-centre sampling places each row's edge within half a pixel (20 µm); the rows of a
        // view and the views average it down.
        assert!((end.z_offset_mm + 0.03).abs() < 0.006, "{end:?}");
        assert!((end.corner_radius_mm - r).abs() < 0.05, "{end:?}");
        // Each view's own corner, for placing a view its overlaps could not.
        assert!(corners.iter().all(|c| c.is_some_and(|(z, _)| (z + 0.03).abs() < 0.02)), "{corners:?}");
        // Only the ring's views make the ring's offset: one view 0.3 mm off, outside the ring,
        // does not move it.
        let mut off = corners.clone();
        off[3] = off[3].map(|(z, r)| (z + 0.3, r));
        let ring: Vec<bool> = (0..8).map(|v| v != 3).collect();
        let end = anchor(&off, &ring, 3, 20.0).unwrap();
        assert!((end.z_offset_mm + 0.03).abs() < 0.006 && end.views == 7, "{end:?}");
    }
}
