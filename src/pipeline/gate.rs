//! Cells of the fused map that no thread of the part's form can explain: a radius more than a
//! thread height from the bin's mean line (half a height beyond its crest or root) is a focus
//! peak on noise or clipping, not a surface. Such cells are dropped before the profile and the
//! mesh read the map, and counted for the report.

use crate::domain::thread::ThreadForm;
use crate::numeric::lsq::fit_line;
use crate::pipeline::surface::UnrolledMap;
use rayon::prelude::*;

/// Half width of the band kept about each bin's mean line, in thread heights: the crest and root
/// lie about half a height either side of it, so a cell is dropped where it is half a height
/// beyond them.
pub const BAND_HALF_HEIGHTS: f64 = 1.0;

/// A bin's line is only fitted where its cells span this many pitches along z (over fewer, the
/// mean line of crests and roots is not defined).
const MIN_SPAN_PITCHES: f64 = 2.0;

/// Drops (sets to NaN, weight 0) every cell whose radius lies more than [`BAND_HALF_HEIGHTS`]
/// thread heights from its 1° bin's mean line r = a + b·z, fitted by least squares and refitted
/// twice without the cells outside the band. Returns how many cells were dropped.
pub fn drop_implausible(map: &mut UnrolledMap, form: &ThreadForm) -> usize {
    let g = map.grid.clone();
    let band_mm = BAND_HALF_HEIGHTS * form.height_mm;
    let per_bin: Vec<Vec<usize>> = (0..360)
        .into_par_iter()
        .map(|bin| {
            let mut cells: Vec<(usize, f64, f64)> = Vec::new();
            let columns = g.bin_columns(bin);
            for iz in 0..g.nz {
                for it in columns.clone() {
                    let i = map.index(iz, it);
                    let r = map.radius_mm[i];
                    if r.is_finite() {
                        cells.push((i, g.z_at(iz), r as f64));
                    }
                }
            }
            let (lo, hi) = cells.iter().fold((f64::MAX, f64::MIN), |(l, h), c| (l.min(c.1), h.max(c.1)));
            if cells.len() < 8 || hi - lo < MIN_SPAN_PITCHES * form.pitch_mm {
                return Vec::new();
            }
            let mut keep = vec![true; cells.len()];
            for _ in 0..3 {
                let (z, r): (Vec<f64>, Vec<f64>) =
                    cells.iter().zip(&keep).filter(|(_, k)| **k).map(|(c, _)| (c.1, c.2)).unzip();
                if z.len() < 8 {
                    return Vec::new();
                }
                let line = fit_line(&z, &r);
                for (k, c) in keep.iter_mut().zip(&cells) {
                    *k = (c.2 - line.0 - line.1 * c.1).abs() <= band_mm;
                }
            }
            cells.iter().zip(&keep).filter(|(_, k)| !**k).map(|(c, _)| c.0).collect()
        })
        .collect();
    let mut dropped = 0;
    for i in per_bin.into_iter().flatten() {
        map.radius_mm[i] = f32::NAN;
        map.weight[i] = 0.0;
        dropped += 1;
    }
    dropped
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::surface::GridSpec;

    fn buttress() -> ThreadForm {
        ThreadForm::api_buttress(5.08, 1.5748, 0.0508, 0.0625).expect("a valid form")
    }

    #[test]
    fn far_outliers_are_dropped_and_the_thread_kept() {
        let form = buttress();
        let grid = GridSpec { z0_mm: 0.0, dz_mm: 0.1, nz: 300, ntheta: 3600 };
        let mut map = UnrolledMap {
            radius_mm: vec![f32::NAN; grid.nz * grid.ntheta],
            weight: vec![0.0; grid.nz * grid.ntheta],
            rgb: vec![[0.5; 3]; grid.nz * grid.ntheta],
            grid: grid.clone(),
        };
        let mut outliers = Vec::new();
        for iz in 0..grid.nz {
            for it in 0..36 {
                let (z, i) = (grid.z_at(iz), map.index(iz, it));
                // A square wave of the thread height about a tapered line.
                let phase = (z / form.pitch_mm).fract();
                let r = 57.0 + 0.03125 * z + if phase < 0.5 { 0.5 } else { -0.5 } * form.height_mm;
                map.radius_mm[i] = r as f32;
                map.weight[i] = 1.0;
                if (iz * 7 + it * 13) % 50 == 0 {
                    // A focus peak 3 mm off, either way.
                    map.radius_mm[i] = (r + if iz % 2 == 0 { 3.0 } else { -3.0 }) as f32;
                    outliers.push(i);
                }
            }
        }
        let dropped = drop_implausible(&mut map, &form);
        assert_eq!(dropped, outliers.len());
        assert!(outliers.iter().all(|&i| map.radius_mm[i].is_nan() && map.weight[i] == 0.0));
        let kept = map.radius_mm.iter().filter(|r| r.is_finite()).count();
        assert_eq!(kept, grid.nz * 36 - outliers.len());
    }

    #[test]
    fn a_bin_spanning_under_two_pitches_is_left_alone() {
        let form = buttress();
        let grid = GridSpec { z0_mm: 0.0, dz_mm: 0.1, nz: 60, ntheta: 360 };
        let mut map = UnrolledMap {
            radius_mm: (0..grid.nz * grid.ntheta).map(|i| if i % 17 == 0 { 90.0 } else { 57.0 }).collect(),
            weight: vec![1.0; grid.nz * grid.ntheta],
            rgb: vec![[0.5; 3]; grid.nz * grid.ntheta],
            grid,
        };
        assert_eq!(drop_implausible(&mut map, &form), 0);
    }
}
