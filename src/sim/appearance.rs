//! How the surfaces look under light coaxial with the camera: machined steel is bright with chaser
//! marks that follow the helix and a narrow specular lobe; mill scale is dark and grainy; a polished
//! crest looks like machined steel. Textures are deterministic functions of position and seed, and
//! band-limited to the pixel footprint so one sample per pixel does not alias.

use super::part::Material;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurfaceLook {
    /// Linear RGB albedo.
    pub rgb: [f64; 3],
    /// Relative albedo variation (value noise) and its finest cell size.
    pub albedo_variation: f64,
    pub grain_mm: f64,
    /// Specular lobe: strength and Phong exponent.
    pub specular: f64,
    pub shininess: f64,
    /// Micro-slope amplitude of tool marks along the helix (0 for none).
    pub tool_mark_slope: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Appearance {
    pub machined: SurfaceLook,
    pub mill_scale: SurfaceLook,
    pub polished: SurfaceLook,
    /// Wavelengths of the chaser marks.
    pub tool_mark_wavelengths_mm: Vec<f64>,
}

impl Default for Appearance {
    fn default() -> Self {
        Self {
            machined: SurfaceLook {
                rgb: [0.60, 0.61, 0.63],
                albedo_variation: 0.18,
                grain_mm: 0.05,
                specular: 0.55,
                shininess: 60.0,
                tool_mark_slope: 0.06,
            },
            mill_scale: SurfaceLook {
                rgb: [0.11, 0.095, 0.085],
                albedo_variation: 0.55,
                grain_mm: 0.05,
                specular: 0.04,
                shininess: 8.0,
                tool_mark_slope: 0.0,
            },
            polished: SurfaceLook {
                rgb: [0.58, 0.585, 0.60],
                albedo_variation: 0.12,
                grain_mm: 0.08,
                specular: 0.6,
                shininess: 50.0,
                tool_mark_slope: 0.03,
            },
            tool_mark_wavelengths_mm: vec![0.09, 0.14, 0.23],
        }
    }
}

impl Appearance {
    pub fn look(&self, material: Material) -> &SurfaceLook {
        match material {
            Material::Machined | Material::EndFace => &self.machined,
            Material::MillScale => &self.mill_scale,
            Material::Polished => &self.polished,
        }
    }
}

/// Hash of a lattice point to [0, 1).
fn lattice(ix: i64, iy: i64, seed: u64) -> f64 {
    let mut x =
        seed ^ (ix as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (iy as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
    x ^= x >> 30;
    x = x.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x ^= x >> 27;
    x = x.wrapping_mul(0x94D0_49BB_1331_11EB);
    x ^= x >> 31;
    (x >> 11) as f64 / (1u64 << 53) as f64
}

/// Smooth value noise in [−1, 1] at cell size `cell_mm`.
fn value_noise(a_mm: f64, b_mm: f64, cell_mm: f64, seed: u64) -> f64 {
    let (x, y) = (a_mm / cell_mm, b_mm / cell_mm);
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let (sx, sy) = (fx * fx * (3.0 - 2.0 * fx), fy * fy * (3.0 - 2.0 * fy));
    let (ix, iy) = (x0 as i64, y0 as i64);
    let v00 = lattice(ix, iy, seed);
    let v10 = lattice(ix + 1, iy, seed);
    let v01 = lattice(ix, iy + 1, seed);
    let v11 = lattice(ix + 1, iy + 1, seed);
    let top = v00 + (v10 - v00) * sx;
    let bottom = v01 + (v11 - v01) * sx;
    2.0 * (top + (bottom - top) * sy) - 1.0
}

/// Two octaves of value noise, the finer one dropped when it would alias at `footprint_mm`.
fn grain(a_mm: f64, b_mm: f64, cell_mm: f64, footprint_mm: f64, seed: u64) -> f64 {
    let cell = cell_mm.max(1.5 * footprint_mm);
    0.65 * value_noise(a_mm, b_mm, cell, seed) + 0.35 * value_noise(a_mm, b_mm, 2.0 * cell, seed ^ 0x5151)
}

/// Surface coordinates for texturing: `helical_mm` runs across the thread (constant along the
/// helix), `arc_mm` along the circumference.
#[derive(Clone, Copy, Debug)]
pub struct TexCoords {
    pub helical_mm: f64,
    pub arc_mm: f64,
}

/// Per-material texture at a point: albedo factor and micro-slope along the pipe axis.
pub fn texture(look: &SurfaceLook, marks_mm: &[f64], at: TexCoords, footprint_mm: f64, seed: u64) -> (f64, f64) {
    let albedo = 1.0 + look.albedo_variation * grain(at.helical_mm, at.arc_mm, look.grain_mm, footprint_mm, seed);
    let mut slope = 0.0;
    if look.tool_mark_slope > 0.0 {
        for (k, &wavelength) in marks_mm.iter().enumerate() {
            if wavelength < 2.5 * footprint_mm {
                continue;
            }
            // Marks wander slowly along the helix.
            let phase = lattice(k as i64, 7, seed) * std::f64::consts::TAU
                + 1.5 * value_noise(at.arc_mm, k as f64 * 3.1, 4.0, seed ^ 0xA5A5);
            slope += (std::f64::consts::TAU * at.helical_mm / wavelength + phase).cos();
        }
        slope *= look.tool_mark_slope / (marks_mm.len().max(1) as f64).sqrt();
    }
    (albedo.max(0.02), slope)
}

/// Radiance (linear, relative to a white diffuser facing the light) under a coaxial light:
/// `cos_view` is the cosine between the surface normal and the direction to the camera.
pub fn shade(look: &SurfaceLook, albedo_factor: f64, cos_view: f64) -> [f64; 3] {
    let c = cos_view.max(0.0);
    let diffuse = 0.1 + 0.9 * c;
    let specular = look.specular * c.powf(look.shininess);
    [0, 1, 2].map(|i| look.rgb[i] * albedo_factor * diffuse + specular)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_is_deterministic_and_bounded() {
        for i in 0..1000 {
            let (a, b) = (i as f64 * 0.0137, i as f64 * 0.071);
            let v = value_noise(a, b, 0.05, 42);
            assert!((-1.0..=1.0).contains(&v));
            assert_eq!(v, value_noise(a, b, 0.05, 42));
        }
        assert_ne!(value_noise(0.123, 0.456, 0.05, 1), value_noise(0.123, 0.456, 0.05, 2));
    }

    #[test]
    fn mill_scale_is_darker_than_machined_steel() {
        let look = Appearance::default();
        let machined = shade(&look.machined, 1.0, 0.9);
        let scale = shade(&look.mill_scale, 1.0, 0.9);
        assert!(machined[1] > 4.0 * scale[1]);
    }
}
