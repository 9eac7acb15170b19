//! Fusion: every view's points, weighted by their focus confidence, averaged into one unrolled
//! cylindrical map r(z, θ) with its colour ([`UnrolledMap`], the type every later stage reads).

use crate::pipeline::cloud::SurfacePoint;
use crate::pipeline::surface::{GridSpec, UnrolledMap};
use std::f64::consts::TAU;

/// A point reduced to what fusion sums: its cell, weight, radius and colour.
#[derive(Clone, Copy, Debug)]
pub struct Binned {
    pub cell: u32,
    pub weight: f32,
    /// f32 resolves 4 nm at pipe radii: plenty, at half the memory.
    pub radius_mm: f32,
    pub rgb: [f32; 3],
}

/// One cell's weighted sums (kept together: a point touches one cache line, not five arrays).
#[derive(Clone, Copy, Debug, Default)]
struct CellSum {
    r: f64,
    w: f64,
    rgb: [f64; 3],
}

impl CellSum {
    #[inline]
    fn add(&mut self, b: &Binned) {
        let w = b.weight as f64;
        self.r += w * b.radius_mm as f64;
        self.w += w;
        for c in 0..3 {
            self.rgb[c] += w * b.rgb[c] as f64;
        }
    }
}

/// Accumulates views one at a time, so only the grid is held, never every view's points.
pub struct Fusion {
    grid: GridSpec,
    sums: Vec<CellSum>,
}

impl Fusion {
    pub fn new(grid: GridSpec) -> Self {
        let cells = grid.nz * grid.ntheta;
        Self { grid, sums: vec![CellSum::default(); cells] }
    }

    /// Each point's cell and weighted contributions, for points as they come (from
    /// [`crate::pipeline::cloud::points_of`]): the costly part (angle, radius), which views can compute in
    /// parallel before [`Fusion::accumulate_all`] sums them in order. `view_angle_rad` is the
    /// view's own angle: the points' angles are measured from it ([`crate::numeric::angle::AngleFrom`]; any
    /// angle gives the same bins, the view's own the cheapest). Written into `out`, which the
    /// caller reuses from view to view (its old contents are dropped): a view's binned points are
    /// tens of megabytes, and fresh ones cost a page fault per 4 kB.
    pub fn bin_into(&self, out: &mut Vec<Binned>, points: impl IntoIterator<Item = SurfacePoint>, view_angle_rad: f64) {
        let grid = &self.grid;
        let angle = crate::numeric::angle::AngleFrom::new(view_angle_rad);
        let points = points.into_iter();
        out.clear();
        out.reserve(crate::pipeline::cloud::capacity_for(&points));
        for p in points {
            let iz = crate::numeric::angle::floor_i64((p.position.z - grid.z0_mm) / grid.dz_mm);
            if iz < 0 || iz as usize >= grid.nz {
                continue;
            }
            let theta = crate::numeric::angle::wrap_turn(view_angle_rad + angle.of(p.position.x, p.position.y));
            let it = ((theta / TAU * grid.ntheta as f64) as usize).min(grid.ntheta - 1);
            out.push(Binned {
                cell: (iz as usize * grid.ntheta + it) as u32,
                weight: p.confidence(),
                radius_mm: p.radius_mm() as f32,
                rgb: p.rgb,
            });
        }
    }

    /// Adds binned points; views are summed in the order given, so the result does not depend on
    /// how the binning was scheduled.
    pub fn accumulate(&mut self, binned: &[Binned]) {
        for b in binned {
            self.sums[b.cell as usize].add(b);
        }
    }

    /// [`Fusion::accumulate`] of several views, in their order, with the grid split into bands of
    /// rows summed in parallel: each cell still receives its points in view order, so the sums are
    /// exactly the sequential ones.
    pub fn accumulate_all(&mut self, views: &[Vec<Binned>]) {
        use rayon::prelude::*;
        let bands = rayon::current_num_threads().clamp(1, 8);
        let band_cells = self.sums.len().div_ceil(bands).max(1);
        self.sums.par_chunks_mut(band_cells).enumerate().for_each(|(k, band)| {
            let start = k * band_cells;
            for b in views.iter().flatten() {
                if let Some(cell) = (b.cell as usize).checked_sub(start).and_then(|i| band.get_mut(i)) {
                    cell.add(b);
                }
            }
        });
    }

    pub fn finish(self) -> UnrolledMap {
        use rayon::prelude::*;
        let radius_mm = self.sums.par_iter().map(|s| if s.w > 0.0 { (s.r / s.w) as f32 } else { f32::NAN }).collect();
        let rgb = self
            .sums
            .par_iter()
            .map(|s| if s.w > 0.0 { [0, 1, 2].map(|k| (s.rgb[k] / s.w) as f32) } else { [0.0; 3] })
            .collect();
        let weight = self.sums.par_iter().map(|s| s.w as f32).collect();
        UnrolledMap { grid: self.grid, radius_mm, weight, rgb }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    fn bin(fusion: &Fusion, points: &[SurfacePoint]) -> Vec<Binned> {
        let mut binned = Vec::new();
        fusion.bin_into(&mut binned, points.iter().copied(), 0.0);
        binned
    }

    /// The views binned and summed one after the other: the sequential reference.
    fn fuse(views: &[&[SurfacePoint]], grid: GridSpec) -> UnrolledMap {
        let mut fusion = Fusion::new(grid);
        for v in views {
            let binned = bin(&fusion, v);
            fusion.accumulate(&binned);
        }
        fusion.finish()
    }

    fn point(z: f64, theta_deg: f64, r: f64, weight: f32) -> SurfacePoint {
        let t = theta_deg.to_radians();
        SurfacePoint { position: Point3::new(r * t.cos(), r * t.sin(), z), rgb: [0.5; 3], weight, pixel: [0, 0] }
    }

    /// The banded parallel sums are exactly the sequential ones (same additions per cell, in
    /// view order).
    #[test]
    fn banded_sums_equal_sequential_sums() {
        let grid = GridSpec { z0_mm: 0.0, dz_mm: 0.1, nz: 40, ntheta: 360 };
        let views: Vec<Vec<SurfacePoint>> = (0..5)
            .map(|v| {
                (0..3000)
                    .map(|i| {
                        let k = (i * 7919 + v * 104729) % 100_000;
                        let (z, t) = ((k % 397) as f64 / 100.0, (k % 3593) as f64 / 10.0);
                        point(z, t, 50.0 + (k % 13) as f64 * 0.001, 1.0 + (k % 7) as f32 * 0.37)
                    })
                    .collect()
            })
            .collect();
        let sequential = fuse(&views.iter().map(Vec::as_slice).collect::<Vec<_>>(), grid.clone());
        let mut banded = Fusion::new(grid);
        let binned: Vec<Vec<Binned>> = views.iter().map(|v| bin(&banded, v)).collect();
        banded.accumulate_all(&binned);
        let banded = banded.finish();
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&sequential.radius_mm), bits(&banded.radius_mm));
        assert_eq!(bits(&sequential.weight), bits(&banded.weight));
        assert!(sequential.coverage() > 0.5);
    }

    #[test]
    fn weighted_mean_per_cell() {
        let a = vec![point(1.0, 10.0, 50.0, 3.0), point(1.0, 10.0, 51.0, 2.0), point(1.0, 10.0, 99.0, 1.0)];
        let grid = GridSpec { z0_mm: 0.0, dz_mm: 0.5, nz: 4, ntheta: 360 };
        let map = fuse(&[&a], grid);
        let i = map.index(2, 10);
        // Weights 2 and 1; the point with peak ratio 1 carries none.
        assert!((map.radius_mm[i] - (2.0 * 50.0 + 51.0) / 3.0).abs() < 1e-4);
        assert!(map.radius_mm[map.index(0, 0)].is_nan());
        // Negative angles wrap.
        let b = vec![point(1.0, -0.5, 50.0, 2.0)];
        let map = fuse(&[&b], GridSpec { z0_mm: 0.0, dz_mm: 0.5, nz: 4, ntheta: 360 });
        assert!(map.radius_mm[map.index(2, 359)].is_finite());
    }
}
