//! PNG exports of the fused map: the unrolled height map (radius above the local minimum, 16-bit
//! gray, z down the rows, θ across) and the unrolled all-in-focus mosaic (8-bit RGB).

use crate::pipeline::surface::UnrolledMap;
use std::path::Path;

#[derive(Debug, thiserror::Error)]
#[error("{path}: {message}")]
pub struct ImageError {
    path: String,
    message: String,
}

fn save(path: &Path, image: image::DynamicImage) -> Result<(), ImageError> {
    image.save(path).map_err(|e| ImageError { path: path.display().to_string(), message: e.to_string() })
}

fn png_bytes(image: image::DynamicImage) -> Result<Vec<u8>, ImageError> {
    let mut out = std::io::Cursor::new(Vec::new());
    image
        .write_to(&mut out, image::ImageFormat::Png)
        .map_err(|e| ImageError { path: "(memory)".into(), message: e.to_string() })?;
    Ok(out.into_inner())
}

pub fn write_height_map(map: &UnrolledMap, path: &Path) -> Result<(), ImageError> {
    save(path, height_map(map))
}

pub fn height_map_png(map: &UnrolledMap) -> Result<Vec<u8>, ImageError> {
    png_bytes(height_map(map))
}

pub fn write_mosaic(map: &UnrolledMap, path: &Path) -> Result<(), ImageError> {
    save(path, mosaic(map))
}

pub fn mosaic_png(map: &UnrolledMap) -> Result<Vec<u8>, ImageError> {
    png_bytes(mosaic(map))
}

/// Radius relative to its range, 16-bit; unseen cells are 0.
fn height_map(map: &UnrolledMap) -> image::DynamicImage {
    let (lo, hi) =
        map.radius_mm.iter().filter(|r| r.is_finite()).fold((f32::MAX, f32::MIN), |(l, h), &r| (l.min(r), h.max(r)));
    let span = (hi - lo).max(1e-6);
    let pixels: Vec<u16> = map
        .radius_mm
        .iter()
        .map(|&r| if r.is_finite() { (1.0 + (r - lo) / span * 65534.0) as u16 } else { 0 })
        .collect();
    let buffer =
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(map.grid.ntheta as u32, map.grid.nz as u32, pixels)
            .expect("one value per cell");
    buffer.into()
}

fn mosaic(map: &UnrolledMap) -> image::DynamicImage {
    let pixels: Vec<u8> = map.rgb.iter().flat_map(|c| c.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)).collect();
    let buffer =
        image::RgbImage::from_raw(map.grid.ntheta as u32, map.grid.nz as u32, pixels).expect("one colour per cell");
    buffer.into()
}
