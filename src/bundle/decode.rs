//! Frame files: PNG or TIFF, 8 or 16 bits, gray or RGB; their header (probe) and their samples.

use super::*;

pub(super) fn is_tiff(path: &str) -> bool {
    let lower = path.to_ascii_lowercase();
    lower.ends_with(".tif") || lower.ends_with(".tiff")
}

pub(super) fn format_of(path: &str, color: image::ColorType) -> Result<FrameFormat, BundleError> {
    use image::ColorType::*;
    let (channels, bit_depth) = match color {
        L8 => (1, 8),
        L16 => (1, 16),
        Rgb8 => (3, 8),
        Rgb16 => (3, 16),
        other => {
            return Err(BundleError::UnreadableFrame {
                path: path.into(),
                message: format!("colour type {other:?}: frames must be 8- or 16-bit gray or RGB"),
            });
        }
    };
    Ok(FrameFormat { width: 0, height: 0, channels, bit_depth })
}

/// Reads a frame's header only.
pub(super) fn probe(path: &str, bytes: &[u8]) -> Result<FrameFormat, BundleError> {
    let unreadable = |e: image::ImageError| BundleError::UnreadableFrame { path: path.into(), message: e.to_string() };
    let ((width, height), color) = if is_tiff(path) {
        let d = image::codecs::tiff::TiffDecoder::new(Cursor::new(bytes)).map_err(unreadable)?;
        (d.dimensions(), d.color_type())
    } else {
        let d = image::codecs::png::PngDecoder::new(Cursor::new(bytes)).map_err(unreadable)?;
        (d.dimensions(), d.color_type())
    };
    if width == 0 || height == 0 {
        return Err(BundleError::UnreadableFrame { path: path.into(), message: "has no pixels".into() });
    }
    Ok(FrameFormat { width, height, ..format_of(path, color)? })
}

/// Decodes a frame (its samples at their stored depth; see [`Frame`]).
pub fn decode(path: &str, bytes: &[u8]) -> Result<Frame, BundleError> {
    let unreadable = |e: image::ImageError| BundleError::UnreadableFrame { path: path.into(), message: e.to_string() };
    let format = if is_tiff(path) { image::ImageFormat::Tiff } else { image::ImageFormat::Png };
    let image = image::load_from_memory_with_format(bytes, format).map_err(unreadable)?;
    let f = format_of(path, image.color())?;
    let (width, height) = (image.width(), image.height());
    let samples = match image {
        image::DynamicImage::ImageLuma8(img) => Samples::Eight(img.into_raw()),
        image::DynamicImage::ImageRgb8(img) => Samples::Eight(img.into_raw()),
        image::DynamicImage::ImageLuma16(img) => Samples::Sixteen(img.into_raw()),
        image::DynamicImage::ImageRgb16(img) => Samples::Sixteen(img.into_raw()),
        _ => unreachable!("format_of refused other colour types"),
    };
    Ok(Frame { width, height, channels: f.channels, samples })
}
