//! The hot kernels, each on a synthetic input of a standard-preset view's size: the focus measure
//! (Laplacian and box sums over one frame), registration of one overlapping pair (binning both
//! views, the NCC search and the pose solve), and fusion (binning a view's points and summing them
//! into the unrolled map), each beside the yardstick the benchmark suites use, decoding a frame
//! (one 864 × 320 RGB PNG): compare a kernel's time with the yardstick's of the same run, not with
//! another machine's. `cargo bench --bench kernels`; speed claims live here and in the benchmark
//! suites, never in tests.

use crestscan::domain::optics::ViewPose;
use crestscan::pipeline::cloud::SurfacePoint;
use crestscan::pipeline::depth::measure::focus_measures;
use crestscan::pipeline::fuse::Fusion;
use crestscan::pipeline::register::{self, GridScratch, Lattice, RegisterOptions};
use crestscan::pipeline::surface::GridSpec;
use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::Point3;
use std::hint::black_box;

/// A standard-preset frame: 864 × 320 pixels.
const FRAME: (usize, usize) = (864, 320);
const RADIUS_MM: f64 = 57.15;
const CELL_MM: f64 = 0.041;

/// A repeatable texture in [0, 1] (an integer hash), standing in for mill scale and chaser marks.
fn texture(i: i64, j: i64) -> f32 {
    let mut h = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
    h ^= h >> 29;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    (h >> 40) as f32 / (1u64 << 24) as f32
}

/// The points of a view centred at `angle_deg` that covers ±`half_arc_deg` and 13 mm along z, one
/// per lattice cell, coloured by the texture of the cell they fall in (so overlapping views see the
/// same surface).
fn view_points(angle_deg: f64, half_arc_deg: f64) -> Vec<SurfacePoint> {
    let arc_cells = (half_arc_deg.to_radians() * RADIUS_MM / CELL_MM) as i64;
    let centre = (angle_deg.to_radians() * RADIUS_MM / CELL_MM) as i64;
    let z_cells = (13.0 / CELL_MM) as i64;
    let mut points = Vec::with_capacity((2 * arc_cells as usize + 1) * z_cells as usize);
    for s in centre - arc_cells..=centre + arc_cells {
        let theta = (s as f64 + 0.5) * CELL_MM / RADIUS_MM;
        for k in 0..z_cells {
            let g = texture(s, k);
            points.push(SurfacePoint {
                position: Point3::new(RADIUS_MM * theta.cos(), RADIUS_MM * theta.sin(), (k as f64 + 0.5) * CELL_MM),
                rgb: [g; 3],
                weight: 3.0,
                pixel: [(s - centre + arc_cells) as u32, k as u32],
            });
        }
    }
    points
}

fn yardstick(c: &mut Criterion) {
    let (w, h) = FRAME;
    let rgb: Vec<u8> =
        (0..w * h * 3).map(|i| (255.0 * texture((i % (3 * w)) as i64, (i / (3 * w)) as i64)) as u8).collect();
    let mut png = Vec::new();
    image::RgbImage::from_raw(w as u32, h as u32, rgb)
        .expect("a frame")
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .expect("encodes");
    c.bench_function("yardstick: decode one 864×320 RGB PNG frame", |b| {
        b.iter(|| black_box(crestscan::bundle::decode("frame.png", black_box(&png)).expect("decodes")))
    });
}

fn focus_measure(c: &mut Criterion) {
    let (w, h) = FRAME;
    let gray: Vec<f32> = (0..w * h).map(|i| texture((i % w) as i64, (i / w) as i64)).collect();
    let (mut scratch, mut out, mut edge) = (vec![0f32; w * h], vec![0f32; w * h], vec![0f32; w * h]);
    c.bench_function("focus measure, 11×11 box and 3×3 edge box, 864×320", |b| {
        b.iter(|| {
            focus_measures(black_box(&gray), w, h, 5, &mut scratch, &mut out, Some((1, &mut edge)));
            black_box(&out);
        })
    });
}

fn register_pair(c: &mut Criterion) {
    let poses = [
        ViewPose { angle_deg: 0.0, axial_mm: 0.0, lens_radius_mm: 200.0 },
        ViewPose { angle_deg: 8.0, axial_mm: 0.0, lens_radius_mm: 200.0 },
    ];
    let views: Vec<Vec<SurfacePoint>> = poses.iter().map(|p| view_points(p.angle_deg, 5.5)).collect();
    let lattice = Lattice::new(RADIUS_MM, CELL_MM);
    let options = RegisterOptions::default();
    let mut scratch = GridScratch::default();
    c.bench_function("register one overlapping pair (bin, NCC search, solve)", |b| {
        b.iter(|| {
            let grids: Vec<_> = views
                .iter()
                .zip(&poses)
                .map(|(points, pose)| {
                    register::view_grid(
                        points.iter().copied(),
                        pose.angle_deg.to_radians(),
                        &lattice,
                        false,
                        &mut scratch,
                    )
                })
                .collect();
            // The pitch of a 5-threads-per-inch buttress thread (the texture has none).
            let registration = register::register(&grids, &poses, &lattice, 6.0, 7.0, 5.08, &options);
            assert_eq!(registration.pairs.len(), 1, "the pair is measured");
            black_box(registration)
        })
    });
}

fn fusion(c: &mut Criterion) {
    let points = view_points(0.0, 5.5);
    let grid = GridSpec::spanning((0.0, 13.0), 1.5 * CELL_MM, RADIUS_MM).expect("a grid");
    let mut buffer = Vec::new();
    c.bench_function("fuse one view (bin and sum its points)", |b| {
        b.iter(|| {
            let mut fusion = Fusion::new(grid.clone());
            fusion.bin_into(&mut buffer, points.iter().copied(), 0.0);
            fusion.accumulate_all(std::slice::from_ref(&buffer));
            black_box(fusion.finish())
        })
    });
}

criterion_group!(kernels, yardstick, focus_measure, register_pair, fusion);
criterion_main!(kernels);
