//! The fused surface: the unrolled cylindrical map r(z, θ) with its colour, on the grid every
//! stage after fusion shares. The pipe surface is 2.5D over (z, θ), so this grid is the natural
//! fused representation; the profile, crest and mesh stages and the PNG export read it.

use std::f64::consts::TAU;

#[derive(Clone, Debug, PartialEq)]
pub struct GridSpec {
    pub z0_mm: f64,
    pub dz_mm: f64,
    pub nz: usize,
    /// Columns over the full 360°.
    pub ntheta: usize,
}

impl GridSpec {
    /// A grid with cells of about `cell_mm` on a cylinder of `radius_mm`, whose first row starts at
    /// the least z of `z_range_mm` and whose rows reach its greatest; None for an empty range (least
    /// above greatest).
    pub fn spanning(z_range_mm: (f64, f64), cell_mm: f64, radius_mm: f64) -> Option<Self> {
        let (lo, hi) = z_range_mm;
        if lo > hi {
            return None;
        }
        let nz = ((hi - lo) / cell_mm).ceil() as usize + 1;
        let ntheta = (TAU * radius_mm / cell_mm).round().max(360.0) as usize;
        Some(Self { z0_mm: lo, dz_mm: cell_mm, nz, ntheta })
    }

    pub fn dtheta_deg(&self) -> f64 {
        360.0 / self.ntheta as f64
    }

    pub fn z_at(&self, iz: usize) -> f64 {
        self.z0_mm + (iz as f64 + 0.5) * self.dz_mm
    }

    pub fn theta_deg_at(&self, it: usize) -> f64 {
        (it as f64 + 0.5) * self.dtheta_deg()
    }

    /// The columns whose centres fall in the 1° bin [bin, bin + 1).
    pub fn bin_columns(&self, bin: usize) -> std::ops::Range<usize> {
        let per_bin = self.ntheta as f64 / 360.0;
        let start = (bin as f64 * per_bin).ceil() as usize;
        let end = (((bin + 1) as f64 * per_bin).ceil() as usize).min(self.ntheta);
        start..end
    }
}

/// The fused map, row-major by z (rows) then θ (columns).
#[derive(Clone, Debug)]
pub struct UnrolledMap {
    pub grid: GridSpec,
    /// NaN where no view saw the cell.
    pub radius_mm: Vec<f32>,
    pub weight: Vec<f32>,
    pub rgb: Vec<[f32; 3]>,
}

impl UnrolledMap {
    pub fn index(&self, iz: usize, it: usize) -> usize {
        iz * self.grid.ntheta + it
    }

    pub fn coverage(&self) -> f64 {
        self.radius_mm.iter().filter(|r| r.is_finite()).count() as f64 / self.radius_mm.len() as f64
    }

    pub fn gray(&self, i: usize) -> f32 {
        crate::domain::frame::luminance(self.rgb[i])
    }
}
