//! Physically based rendering of one focal-stack frame: a pinhole (or telecentric) ray cast from the
//! frame's own lens position against the analytic part, coaxial shading, a spatially varying disc
//! blur whose diameter is the contract's circle of confusion, vignetting, shot and read noise and
//! quantisation.

use super::appearance::{self, Appearance, TexCoords};
use super::part::{Material, PartModel, SurfaceKernel};
use crate::domain::optics::{Optics, Projection};
use nalgebra::{Isometry3, Point3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

/// A ray–surface hit. `depth_mm` is the distance along the camera axis from the frame's lens centre.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    pub depth_mm: f64,
    pub point: Point3<f64>,
    pub material: Material,
}

/// Sphere tracing against the part's radius field r(z, θ), with a per-ray Lipschitz bound so that
/// no step can cross the surface.
pub struct Tracer<'a> {
    part: &'a PartModel,
    kernel: SurfaceKernel<'a>,
    outer_radius_mm: f64,
    inner_radius_mm: f64,
    slope_z: f64,
    slope_theta: f64,
}

const CONVERGED_MM: f64 = 1e-7;
const MAX_STEPS: usize = 4000;
/// Below this gap the march takes secant steps.
const SECANT_BELOW_MM: f64 = 0.02;

impl<'a> Tracer<'a> {
    pub fn new(part: &'a PartModel) -> Self {
        let outer = part.mill.max_radius().max(part.root_cone_radius(0.0) + part.form.height_mm) + 0.05;
        let inner = part.root_cone_radius(0.0).min(part.chamfer_radius_at_end_mm) - 0.5;
        Self {
            part,
            kernel: part.kernel(),
            outer_radius_mm: outer,
            inner_radius_mm: inner,
            slope_z: part.max_axial_slope(),
            slope_theta: part.max_angular_slope(),
        }
    }

    /// First hit of `origin + t·direction` (pipe frame) with t ≥ 0.
    pub fn intersect(&self, origin: &Point3<f64>, direction: &Vector3<f64>) -> Option<Hit> {
        self.intersect_from(origin, direction, 0.0)
    }

    /// As [`Tracer::intersect`], starting the march at `t_hint` when the ray is still outside the
    /// part there (a depth known to lie before the hit); falls back to the full march otherwise.
    pub fn intersect_from(&self, origin: &Point3<f64>, direction: &Vector3<f64>, t_hint: f64) -> Option<Hit> {
        let (ox, oy, dx, dy) = (origin.x, origin.y, direction.x, direction.y);
        let a = dx * dx + dy * dy;
        if a < 1e-18 {
            return None;
        }
        let b = 2.0 * (ox * dx + oy * dy);
        let c_out = ox * ox + oy * oy - self.outer_radius_mm.powi(2);
        let disc = b * b - 4.0 * a * c_out;
        if disc < 0.0 {
            return None;
        }
        let t_enter = ((-b - disc.sqrt()) / (2.0 * a)).max(0.0);
        let mut t = t_enter;
        if t_hint > t_enter {
            let p = origin + direction * t_hint;
            if p.z >= 0.0 && {
                let (surface_r, _, r) = self.kernel.surface_under(p.x, p.y, p.z);
                r > surface_r
            } {
                t = t_hint;
            }
        }
        let c_in = ox * ox + oy * oy - self.inner_radius_mm.powi(2);
        let disc_in = b * b - 4.0 * a * c_in;
        let t_limit = if disc_in >= 0.0 { (-b - disc_in.sqrt()) / (2.0 * a) } else { (-b) / (2.0 * a) };
        let speed_xy = a.sqrt();
        let lipschitz =
            speed_xy * (1.0 + self.slope_theta / self.inner_radius_mm) + self.slope_z * direction.z.abs() + 1e-9;
        // Last point known outside the part: sphere steps keep it; near the surface the march
        // switches to secant steps, and an overshoot is bracketed and refined by false position.
        let mut outside: Option<(f64, f64)> = None;
        for _ in 0..MAX_STEPS {
            let p = origin + direction * t;
            if p.z < 0.0 {
                // Beyond the end face: nothing until the plane z = 0, if the ray comes back at all.
                if direction.z <= 0.0 {
                    return None;
                }
                t = (0.0 - origin.z) / direction.z;
                if t > t_limit {
                    return None;
                }
                let q = origin + direction * t;
                let (surface_r, _, r) = self.kernel.surface_under(q.x, q.y, 0.0);
                if r <= surface_r {
                    return Some(Hit { depth_mm: t, point: q, material: Material::EndFace });
                }
                t += 1e-9;
                outside = None;
                continue;
            }
            let (surface_r, material, r) = self.kernel.surface_under(p.x, p.y, p.z);
            let gap = r - surface_r;
            if gap.abs() < CONVERGED_MM {
                return Some(Hit { depth_mm: t, point: p, material });
            }
            if gap < 0.0 {
                let (t_out, gap_out) = outside.expect("only a secant step can overshoot");
                return Some(self.refine(origin, direction, (t_out, gap_out), (t, gap)));
            }
            let sphere = gap / lipschitz;
            let step = match outside {
                Some((t_prev, gap_prev)) if gap < SECANT_BELOW_MM && gap_prev > gap => {
                    (gap * (t - t_prev) / (gap_prev - gap)).clamp(sphere, 50.0 * sphere)
                }
                _ => sphere,
            };
            outside = Some((t, gap));
            t += step;
            if t > t_limit {
                return None;
            }
        }
        let p = origin + direction * t;
        let material = self.kernel.surface_under(p.x, p.y, p.z.max(0.0)).1;
        Some(Hit { depth_mm: t, point: p, material })
    }

    /// False position (Illinois) between a point outside and one inside the part.
    fn refine(&self, origin: &Point3<f64>, direction: &Vector3<f64>, mut a: (f64, f64), mut b: (f64, f64)) -> Hit {
        let mut side = 0i8;
        for _ in 0..100 {
            let t = (a.0 * b.1 - b.0 * a.1) / (b.1 - a.1);
            let p = origin + direction * t;
            let (surface_r, material, r) = self.kernel.surface_under(p.x, p.y, p.z.max(0.0));
            let gap = r - surface_r;
            if gap.abs() < CONVERGED_MM || (b.0 - a.0).abs() < 1e-9 {
                return Hit { depth_mm: t, point: p, material };
            }
            if gap > 0.0 {
                a = (t, gap);
                if side == 1 {
                    b.1 /= 2.0;
                }
                side = 1;
            } else {
                b = (t, gap);
                if side == -1 {
                    a.1 /= 2.0;
                }
                side = -1;
            }
        }
        let p = origin + direction * a.0;
        Hit { depth_mm: a.0, point: p, material: self.kernel.surface_under(p.x, p.y, p.z.max(0.0)).1 }
    }

    /// Outward unit normal of the surface at a hit (central differences of r(z, θ)).
    pub fn normal(&self, hit: &Hit) -> Vector3<f64> {
        if hit.material == Material::EndFace {
            return -Vector3::z();
        }
        let p = hit.point;
        let (r, theta) = ((p.x * p.x + p.y * p.y).sqrt(), p.y.atan2(p.x));
        let (s, c) = (p.y / r, p.x / r);
        let h = 2e-4;
        let z = p.z.max(h);
        let radius = |z: f64, dtheta: f64| {
            // cos/sin of θ ± dθ by the angle-sum rule (dθ is tiny).
            let (ds, dc) = dtheta.sin_cos();
            self.kernel.surface(z, theta + dtheta, c * dc - s * ds, s * dc + c * ds).0
        };
        let dr_dz = (radius(z + h, 0.0) - radius(z - h, 0.0)) / (2.0 * h);
        let dtheta = h / r;
        let dr_ds = (radius(z, dtheta) - radius(z, -dtheta)) / (2.0 * h);
        let radial = Vector3::new(c, s, 0.0);
        let tangential = Vector3::new(-s, c, 0.0);
        (radial - Vector3::z() * dr_dz - tangential * dr_ds).normalize()
    }
}

/// Sensor model: electrons at the exposure that maps a white diffuser facing the light to
/// `white_level` of full scale.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sensor {
    pub full_well_e: f64,
    pub read_noise_e: f64,
    pub white_level: f64,
    /// Lens vignetting: relative illumination 1 − k·ρ² at normalised image radius ρ (on top of cos⁴).
    pub lens_vignetting: f64,
    pub bit_depth: u8,
    /// Gray frames (a monochrome sensor) instead of RGB.
    #[serde(default)]
    pub monochrome: bool,
}

impl Default for Sensor {
    fn default() -> Self {
        Self {
            full_well_e: 12_000.0,
            read_noise_e: 4.0,
            white_level: 0.75,
            lens_vignetting: 0.12,
            bit_depth: 8,
            monochrome: false,
        }
    }
}

/// One camera of a view: its true pose and image geometry.
pub struct Camera<'a> {
    pub optics: &'a Optics,
    /// Camera (offset 0) → pipe, the true pose.
    pub pose: Isometry3<f64>,
    pub width: u32,
    pub height: u32,
    /// The truth depth map once computed (a warm start for every frame's ray march).
    pub depth_map_cached: Vec<f32>,
}

/// Bound on how far focus breathing moves a point through the stack, in pixels: the image scale
/// changes by |offset| / depth, about 1% in the presets, so ≤ 5 px at the image corners.
const BREATHING_REACH_PX: usize = 7;

/// Minimum of the finite depths within `reach` pixels (separable min filter); NaN where none.
fn near_depth(depth: &[f32], w: usize, h: usize, reach: usize) -> Vec<f32> {
    if depth.is_empty() {
        return vec![f32::NAN; w * h];
    }
    let fmin = |a: f32, b: f32| {
        if a.is_nan() {
            b
        } else if b.is_nan() {
            a
        } else {
            a.min(b)
        }
    };
    let mut rows = vec![f32::NAN; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut m = f32::NAN;
            for xx in x.saturating_sub(reach)..(x + reach + 1).min(w) {
                m = fmin(m, depth[y * w + xx]);
            }
            rows[y * w + x] = m;
        }
    }
    let mut out = vec![f32::NAN; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut m = f32::NAN;
            for yy in y.saturating_sub(reach)..(y + reach + 1).min(h) {
                m = fmin(m, rows[yy * w + x]);
            }
            out[y * w + x] = m;
        }
    }
    out
}

impl Camera<'_> {
    pub fn ray(&self, u: u32, v: u32, offset_mm: f64) -> (Point3<f64>, Vector3<f64>) {
        let principal = self.optics.principal_point(self.width, self.height);
        let ray = self.optics.pixel_ray(u as f64, v as f64, principal, offset_mm);
        (self.pose * ray.origin, self.pose * ray.direction)
    }

    /// Depth (from the offset-0 lens centre) of every pixel; NaN where the ray misses the part.
    pub fn depth_map(&self, tracer: &Tracer) -> Vec<f32> {
        let mut depth = vec![f32::NAN; (self.width * self.height) as usize];
        for v in 0..self.height {
            for u in 0..self.width {
                let (o, d) = self.ray(u, v, 0.0);
                if let Some(hit) = tracer.intersect(&o, &d) {
                    depth[(v * self.width + u) as usize] = hit.depth_mm as f32;
                }
            }
        }
        depth
    }
}

/// Largest blur-circle radius rendered, in pixels: beyond it a point is spread so thin that it
/// carries no focus information; the cap bounds how far a pixel's disc reaches.
pub const MAX_BLUR_RADIUS_PX: f32 = 12.0;

/// Renders one frame to 8- or 16-bit samples, interleaved RGB or gray.
pub fn render_frame(
    camera: &Camera,
    tracer: &Tracer,
    look: &Appearance,
    sensor: &Sensor,
    offset_mm: f64,
    texture_seed: u64,
    noise_seed: u64,
) -> Vec<u16> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let optics = camera.optics;
    // Start each ray's march just before the nearest surface seen around it at offset 0, moved by
    // this frame's offset (focus breathing shifts the image by a few pixels at most).
    let start = near_depth(&camera.depth_map_cached, w, h, BREATHING_REACH_PX);
    let mut radiance = vec![0f32; w * h * 3];
    let mut radius_px = vec![0f32; w * h];
    let footprint = optics.object_pixel_mm(optics.focus_distance_mm);
    let marks = &look.tool_mark_wavelengths_mm;
    let pitch = tracer.part.form.pitch_mm;
    let arc_radius = tracer.part.pipe_od_mm / 2.0;
    for v in 0..h {
        for u in 0..w {
            let (origin, direction) = camera.ray(u as u32, v as u32, offset_mm);
            let hint = start[v * w + u];
            let hint = if hint.is_finite() { hint as f64 + offset_mm - 0.05 } else { 0.0 };
            let Some(hit) = tracer.intersect_from(&origin, &direction, hint) else { continue };
            let normal = tracer.normal(&hit);
            let to_camera = -direction.normalize();
            let theta = hit.point.y.atan2(hit.point.x);
            let at = TexCoords {
                helical_mm: hit.point.z - pitch * theta / std::f64::consts::TAU,
                arc_mm: theta * arc_radius,
            };
            let surface = look.look(hit.material);
            let (albedo, slope) = appearance::texture(surface, marks, at, footprint, texture_seed);
            let tilted = (normal + Vector3::z() * slope).normalize();
            let rgb = appearance::shade(surface, albedo, tilted.dot(&to_camera));
            let i = v * w + u;
            for c in 0..3 {
                radiance[3 * i + c] = rgb[c] as f32;
            }
            let depth = hit.depth_mm; // from this frame's lens centre (ray origin)
            radius_px[i] = (0.5 * optics.coc_px(depth) as f32).min(MAX_BLUR_RADIUS_PX);
        }
    }
    let blurred = disc_blur(&radiance, &radius_px, w, h);
    expose(&blurred, camera, sensor, noise_seed)
}

/// Weight of a pixel at distance `d` inside a disc of radius `r` (anti-aliased edge).
#[inline]
fn disc_weight(d: f32, r: f32) -> f32 {
    (r + 0.5 - d).clamp(0.0, 1.0)
}

const NORM_STEPS_PER_PX: f32 = 256.0;

fn disc_norm_exact(r: f32) -> f32 {
    let k = (r + 0.5).ceil() as i64;
    let mut sum = 0.0;
    for dy in -k..=k {
        for dx in -k..=k {
            sum += disc_weight(((dx * dx + dy * dy) as f32).sqrt(), r);
        }
    }
    sum
}

fn disc_norm_table() -> &'static [f32] {
    static TABLE: std::sync::OnceLock<Vec<f32>> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        let n = (MAX_BLUR_RADIUS_PX * NORM_STEPS_PER_PX) as usize + 2;
        (0..n).map(|i| disc_norm_exact(i as f32 / NORM_STEPS_PER_PX)).collect()
    })
}

/// The disc's weight sum, interpolated in the table (relative error < 1e-4).
fn disc_norm(table: &[f32], r: f32) -> f32 {
    let x = r * NORM_STEPS_PER_PX;
    let i = (x as usize).min(table.len() - 2);
    let f = x - i as f32;
    table[i] + (table[i + 1] - table[i]) * f
}

/// Scatter each source pixel over its own disc (energy preserving). Sources are visited in
/// row-major order, so each output pixel sums its contributions in the order a gather over its
/// window would; a source reaches only as far as its own radius, not the frame's largest.
pub fn disc_blur(radiance: &[f32], radius_px: &[f32], w: usize, h: usize) -> Vec<f32> {
    // Normalisation of each disc: the sum of its weights over the integer grid, tabulated.
    let table = disc_norm_table();
    let mut out = vec![0f32; radiance.len()];
    let (wi, hi) = (w as i64, h as i64);
    for sy in 0..hi {
        for sx in 0..wi {
            let s = (sy * wi + sx) as usize;
            let r = radius_px[s];
            let norm = disc_norm(table, r);
            let source = [radiance[3 * s], radiance[3 * s + 1], radiance[3 * s + 2]];
            let reach = (r + 0.5).ceil() as i64;
            for y in (sy - reach).max(0)..=(sy + reach).min(hi - 1) {
                let dy = (sy - y) as f32;
                for x in (sx - reach).max(0)..=(sx + reach).min(wi - 1) {
                    let dx = (sx - x) as f32;
                    let wgt = disc_weight((dx * dx + dy * dy).sqrt(), r);
                    if wgt > 0.0 {
                        let wn = wgt / norm;
                        let o = 3 * (y * wi + x) as usize;
                        out[o] += wn * source[0];
                        out[o + 1] += wn * source[1];
                        out[o + 2] += wn * source[2];
                    }
                }
            }
        }
    }
    out
}

/// Vignetting, shot and read noise, quantisation.
fn expose(radiance: &[f32], camera: &Camera, sensor: &Sensor, noise_seed: u64) -> Vec<u16> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let optics = camera.optics;
    let [cx, cy] = optics.principal_point(camera.width, camera.height);
    let p = optics.pixel_pitch_mm();
    let half_diag = ((w * w + h * h) as f64).sqrt() / 2.0;
    let max_code = ((1u32 << sensor.bit_depth) - 1) as f64;
    let electrons_per_unit = sensor.full_well_e * sensor.white_level;
    let mut rng = ChaCha8Rng::seed_from_u64(noise_seed);
    let channels = if sensor.monochrome { 1 } else { 3 };
    let mut out = vec![0u16; w * h * channels];
    for y in 0..h {
        for x in 0..w {
            let (dx, dy) = (x as f64 + 0.5 - cx, y as f64 + 0.5 - cy);
            let rho2 = (dx * dx + dy * dy) / (half_diag * half_diag);
            let natural = match optics.projection {
                Projection::Perspective => {
                    let di = optics.sensor_distance_mm();
                    let cos = di / (di * di + (dx * dx + dy * dy) * p * p).sqrt();
                    cos.powi(4)
                }
                Projection::Telecentric => 1.0,
            };
            let gain = natural * (1.0 - sensor.lens_vignetting * rho2);
            for c in 0..channels {
                let j = 3 * (y * w + x);
                // A monochrome sensor integrates the luminance.
                let value = if channels == 1 {
                    crate::domain::frame::luminance([radiance[j], radiance[j + 1], radiance[j + 2]])
                } else {
                    radiance[j + c]
                };
                let i = channels * (y * w + x) + c;
                let signal = value as f64 * gain * electrons_per_unit;
                let shot: f64 = StandardNormal.sample(&mut rng);
                let read: f64 = StandardNormal.sample(&mut rng);
                let e = signal + shot * signal.max(0.0).sqrt() + read * sensor.read_noise_e;
                let code = (e / sensor.full_well_e * max_code).round().clamp(0.0, max_code);
                out[i] = code as u16;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The blur as a gather over the frame's largest reach: what each output pixel sums, in
    /// row-major order of its sources.
    fn gather_blur(radiance: &[f32], radius_px: &[f32], w: usize, h: usize) -> Vec<f32> {
        let max_r = radius_px.iter().cloned().fold(0.0f32, f32::max);
        let reach = (max_r + 0.5).ceil() as i64;
        let table = disc_norm_table();
        let mut out = vec![0f32; radiance.len()];
        for y in 0..h as i64 {
            for x in 0..w as i64 {
                let mut acc = [0f32; 3];
                for sy in (y - reach).max(0)..=(y + reach).min(h as i64 - 1) {
                    for sx in (x - reach).max(0)..=(x + reach).min(w as i64 - 1) {
                        let s = (sy as usize) * w + sx as usize;
                        let (dx, dy) = ((sx - x) as f32, (sy - y) as f32);
                        let wgt = disc_weight((dx * dx + dy * dy).sqrt(), radius_px[s]);
                        if wgt > 0.0 {
                            let wn = wgt / disc_norm(table, radius_px[s]);
                            for c in 0..3 {
                                acc[c] += wn * radiance[3 * s + c];
                            }
                        }
                    }
                }
                let o = (y as usize * w + x as usize) * 3;
                out[o..o + 3].copy_from_slice(&acc);
            }
        }
        out
    }

    #[test]
    fn the_scatter_sums_what_a_gather_sums_bit_for_bit() {
        let (w, h) = (47, 29);
        let mut state = 0x2545_F491_4F6C_DD1Du64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let radiance: Vec<f32> = (0..w * h * 3).map(|_| next()).collect();
        // Radii from sharp to the cap, in patches and per pixel, so reaches differ across the frame.
        let radius: Vec<f32> =
            (0..w * h).map(|i| if (i / w) < h / 2 { next() * 1.5 } else { next() * MAX_BLUR_RADIUS_PX }).collect();
        let scattered = disc_blur(&radiance, &radius, w, h);
        let gathered = gather_blur(&radiance, &radius, w, h);
        assert!(gathered.iter().any(|&v| v > 0.0));
        let differing = scattered.iter().zip(&gathered).filter(|(a, b)| a.to_bits() != b.to_bits()).count();
        assert_eq!(differing, 0, "of {} values", gathered.len());
    }

    #[test]
    fn blur_preserves_energy_and_spreads_by_the_radius() {
        let (w, h) = (31, 31);
        let mut radiance = vec![0f32; w * h * 3];
        let centre = 15 * w + 15;
        radiance[3 * centre] = 1.0;
        let mut radius = vec![0f32; w * h];
        radius[centre] = 4.0;
        let out = disc_blur(&radiance, &radius, w, h);
        let total: f32 = out.iter().step_by(3).sum();
        assert!((total - 1.0).abs() < 1e-5, "{total}");
        assert!(out[3 * (15 * w + 19)] > 0.0, "reaches the radius");
        assert_eq!(out[3 * (15 * w + 21)], 0.0, "nothing beyond it");
        // A sharp source stays sharp.
        radius[centre] = 0.0;
        let out = disc_blur(&radiance, &radius, w, h);
        assert!((out[3 * centre] - 1.0).abs() < 1e-6);
    }
}
