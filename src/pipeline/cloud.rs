//! Back-projection: each view's depth map becomes 3D points in the pipe frame, through the
//! manifest's optics and the view's pose (perspective or telecentric alike, via the pixel ray).

use crate::domain::optics::{Optics, ViewPose};
use crate::pipeline::depth::DepthMap;
use nalgebra::{Point3, Vector3};

/// A surface point seen by a view, with its colour and trust.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    pub position: Point3<f64>,
    pub rgb: [f32; 3],
    /// Focus peak ratio (≥ 1): how sharply this depth was determined.
    pub weight: f32,
    pub pixel: [u32; 2],
}

impl SurfacePoint {
    pub fn radius_mm(&self) -> f64 {
        // Not f64::hypot, which guards against overflow and underflow at several times the cost:
        // coordinates here are millimetres, so the plain form is within an ulp.
        (self.position.x * self.position.x + self.position.y * self.position.y).sqrt()
    }
    pub fn theta_rad(&self) -> f64 {
        self.position.y.atan2(self.position.x)
    }
    /// Confidence weight: zero at a focus peak ratio of 1 (no peak), growing with sharpness.
    pub fn confidence(&self) -> f32 {
        (self.weight - 1.0).max(0.0)
    }
}

/// Room for every item an iterator may yield (its upper bound: pages never written cost nothing),
/// so that collecting a view's points does not copy them as the vector grows.
pub fn capacity_for<T>(items: &impl Iterator<Item = T>) -> usize {
    let (lower, upper) = items.size_hint();
    upper.unwrap_or(lower)
}

/// Points of one view at the given pose, one at a time in image order; pixels without a trusted
/// depth are skipped. The stages that reduce a view's points at once (registration's samples,
/// fusion's bins) take them as they come rather than from a cloud of every view held in memory
/// (about 50 bytes a point, half a gigabyte for a ring of views).
pub fn points_of<'a>(
    optics: &'a Optics,
    pose: &ViewPose,
    depth: &'a DepthMap,
) -> impl Iterator<Item = SurfacePoint> + 'a {
    let iso = pose.camera_to_pipe();
    let principal = optics.principal_point(depth.width as u32, depth.height as u32);
    let width = depth.width;
    // A pixel ray's x and z parts depend on its column only and its y parts on its row only, and
    // the pose is linear: R·(o + d·dir) + t splits into a column's rotated parts (with t) plus a
    // row's, taken once per column and row (the same rays `pixel_ray` gives per pixel), so each
    // point costs three multiplies and nine additions rather than a ray and a quaternion rotation.
    let rotation = iso.rotation.to_rotation_matrix().into_inner();
    let t = iso.translation.vector;
    let columns: Vec<(Vector3<f64>, Vector3<f64>)> = (0..depth.width)
        .map(|u| {
            let ray = optics.pixel_ray(u as f64, 0.0, principal, 0.0);
            (
                t + rotation * Vector3::new(ray.origin.x, 0.0, ray.origin.z),
                rotation * Vector3::new(ray.direction.x, 0.0, ray.direction.z),
            )
        })
        .collect();
    let step = depth.row_step.max(1);
    let rows: Vec<(Vector3<f64>, Vector3<f64>)> = (0..depth.rows())
        .map(|r| {
            let ray = optics.pixel_ray(0.0, (r * step) as f64, principal, 0.0);
            (rotation * Vector3::new(0.0, ray.origin.y, 0.0), rotation * Vector3::new(0.0, ray.direction.y, 0.0))
        })
        .collect();
    depth.depth_mm.iter().enumerate().filter(|(_, d)| d.is_finite()).map(move |(i, &d)| {
        let (u, r) = (i % width, i / width);
        let ((origin_u, direction_u), (origin_r, direction_r)) = (&columns[u], &rows[r]);
        SurfacePoint {
            position: Point3::from(origin_u + origin_r + (direction_u + direction_r) * d as f64),
            rgb: depth.colour(i),
            weight: depth.peak_ratio[i],
            pixel: [u as u32, (r * step) as u32],
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::optics::Projection;

    /// The per-column and per-row split of the pose gives each pixel's ray, at its depth, through
    /// the view's pose, for both projections and every second row.
    #[test]
    fn points_are_the_pixel_rays_at_their_depths_through_the_pose() {
        for projection in [Projection::Perspective, Projection::Telecentric] {
            let optics = Optics {
                projection,
                focal_length_mm: Some(50.0),
                f_number: 4.0,
                focus_distance_mm: 220.0,
                pixel_pitch_um: 5.5,
                principal_point_px: None,
                magnification: Some(0.3),
            };
            let (w, h, step) = (7usize, 6usize, 2usize);
            let rows = h.div_ceil(step);
            let depth = DepthMap {
                width: w,
                height: h,
                row_step: step,
                depth_mm: (0..w * rows).map(|i| if i == 3 { f32::NAN } else { 218.0 + 0.37 * i as f32 }).collect(),
                peak_ratio: vec![2.0; w * rows],
                all_in_focus: vec![32768; 3 * w * rows],
                end_edges: Vec::new(),
                frame_noise: None,
                prefiltered: false,
            };
            let pose = ViewPose { angle_deg: 231.7, axial_mm: 12.5, lens_radius_mm: 277.3 };
            let points: Vec<SurfacePoint> = points_of(&optics, &pose, &depth).collect();
            assert_eq!(points.len(), w * rows - 1, "the pixel without depth is skipped");
            let principal = optics.principal_point(w as u32, h as u32);
            for p in &points {
                let [u, v] = p.pixel;
                let i = (v as usize / step) * w + u as usize;
                let want = pose.camera_to_pipe()
                    * optics.pixel_ray(u as f64, v as f64, principal, 0.0).at(depth.depth_mm[i] as f64);
                assert!((p.position - want).norm() < 1e-10, "{projection:?} pixel {u},{v}: {} vs {want}", p.position);
            }
        }
    }

    #[test]
    fn a_pixel_on_the_axis_lands_on_the_view_line() {
        let optics = Optics { principal_point_px: Some([1.5, 1.5]), ..Optics::standard_camera() };
        let depth = DepthMap {
            width: 3,
            height: 3,
            row_step: 1,
            depth_mm: vec![220.0; 9],
            peak_ratio: vec![2.0; 9],
            all_in_focus: vec![32768; 27],
            end_edges: Vec::new(),
            frame_noise: None,
            prefiltered: false,
        };
        let pose = ViewPose { angle_deg: 90.0, axial_mm: 10.0, lens_radius_mm: 277.0 };
        let points: Vec<SurfacePoint> = points_of(&optics, &pose, &depth).collect();
        assert_eq!(points.len(), 9);
        // Pixel (1, 1) has its centre at the principal point: straight down the optical axis.
        let centre = points[4];
        assert!((centre.radius_mm() - 57.0).abs() < 1e-9);
        assert!((centre.theta_rad().to_degrees() - 90.0).abs() < 1e-9);
        assert!((centre.position.z - 10.0).abs() < 1e-9);
        // Columns grow toward the pipe body (+z).
        assert!(points[5].position.z > centre.position.z);
    }
}
