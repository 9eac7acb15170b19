//! PNG exports of the fused map: the unrolled height map (radius above the local minimum, 16-bit
//! gray, z down the rows, θ across) and the unrolled all-in-focus mosaic (8-bit RGB).

use crate::pipeline::surface::UnrolledMap;

#[derive(Debug, thiserror::Error)]
#[error("{path}: {message}")]
pub struct ImageError {
    path: String,
    message: String,
}

fn png_bytes(image: image::DynamicImage) -> Result<Vec<u8>, ImageError> {
    let mut out = std::io::Cursor::new(Vec::new());
    image
        .write_to(&mut out, image::ImageFormat::Png)
        .map_err(|e| ImageError { path: "(memory)".into(), message: e.to_string() })?;
    Ok(out.into_inner())
}

pub fn height_map_png(map: &UnrolledMap) -> Result<Vec<u8>, ImageError> {
    png_bytes(height_map(map))
}

pub fn mosaic_png(map: &UnrolledMap) -> Result<Vec<u8>, ImageError> {
    png_bytes(mosaic(map))
}

/// A smaller copy of one of these PNGs for a page, at most `max_width` pixels wide (its aspect
/// kept) and 8 bits deep: the full mosaic of a ring is megabytes, too much to inline.
pub fn preview_png(png: &[u8], max_width: u32) -> Result<Vec<u8>, ImageError> {
    let image = image::load_from_memory_with_format(png, image::ImageFormat::Png)
        .map_err(|e| ImageError { path: "(memory)".into(), message: e.to_string() })?;
    let image = if image.width() > max_width {
        let height = ((image.height() as f64 * max_width as f64 / image.width() as f64).round() as u32).max(1);
        image.resize_exact(max_width, height, image::imageops::FilterType::Triangle)
    } else {
        image
    };
    let image: image::DynamicImage =
        if image.color().has_color() { image.to_rgb8().into() } else { image.to_luma8().into() };
    png_bytes(image)
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
