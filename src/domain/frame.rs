//! Views and their frames: what a station recorded, decoded, and the trait through which the
//! pipeline reads frames without knowing where they are stored.

use crate::domain::optics::{Optics, ViewPose};
use crate::domain::part::Part;
use crate::problem::{Code, ErrorCode};
use serde::{Deserialize, Serialize};

/// Pixel layout shared by every frame of a view.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct FrameFormat {
    pub width: u32,
    pub height: u32,
    /// 1 (gray) or 3 (RGB).
    pub channels: u8,
    /// 8 or 16.
    pub bit_depth: u8,
}

#[derive(Clone, Debug, PartialEq)]
pub struct View {
    pub id: String,
    pub pose: ViewPose,
    pub frames: Vec<FrameEntry>,
    pub format: FrameFormat,
}

/// A decoded frame: its interleaved samples as the file holds them (8 or 16 bits), read as
/// values in [0, 1]. Kept at the file's depth rather than widened to f32: a colour frame is a
/// quarter the size, which is what the depth stage's window of recent frames holds per view in
/// flight, and decoding needs no second pass.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    pub channels: u8,
    pub samples: Samples,
}

/// A frame's samples at their stored depth.
#[derive(Clone, Debug, PartialEq)]
pub enum Samples {
    Eight(Vec<u8>),
    Sixteen(Vec<u16>),
    /// Values already in [0, 1] (frames made in memory).
    Float(Vec<f32>),
}

/// Each 8-bit sample's value, v / 255 exactly as a division gives it (a multiply by 1/255 would
/// differ in the last bit for some v), looked up rather than divided per read.
const EIGHT_BIT_VALUES: [f32; 256] = {
    let mut table = [0f32; 256];
    let mut v = 0;
    while v < 256 {
        table[v] = v as f32 / 255.0;
        v += 1;
    }
    table
};

/// A stored sample type and what it reads as, in [0, 1]: the one place the scales live.
pub trait SampleValue: Copy {
    fn value(self) -> f32;
}

impl SampleValue for u8 {
    #[inline]
    fn value(self) -> f32 {
        EIGHT_BIT_VALUES[self as usize]
    }
}

impl SampleValue for u16 {
    #[inline]
    fn value(self) -> f32 {
        self as f32 / 65535.0
    }
}

impl SampleValue for f32 {
    #[inline]
    fn value(self) -> f32 {
        self
    }
}

impl Samples {
    /// Sample i as a value in [0, 1].
    #[inline]
    pub fn value(&self, i: usize) -> f32 {
        match self {
            Samples::Eight(s) => s[i].value(),
            Samples::Sixteen(s) => s[i].value(),
            Samples::Float(s) => s[i].value(),
        }
    }

    pub fn len(&self) -> usize {
        match self {
            Samples::Eight(s) => s.len(),
            Samples::Sixteen(s) => s.len(),
            Samples::Float(s) => s.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Every sample as a value in [0, 1].
    pub fn values(&self) -> Vec<f32> {
        (0..self.len()).map(|i| self.value(i)).collect()
    }
}

/// Luminance of a linear RGB sample (Rec. 709 weights): what a monochrome sensor integrates and what
/// every gray view of a colour frame in this crate uses.
#[inline]
pub fn luminance(rgb: [f32; 3]) -> f32 {
    0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]
}

/// [`Frame::gray_into`] of 8-bit samples: v / 255 divided here rather than looked up
/// ([`EIGHT_BIT_VALUES`] holds the same quotients), so that the loop vectorises (the table's
/// gathers do not); in the luminance's order, so bit for bit the table's values.
fn eight_bit_gray(out: &mut Vec<f32>, samples: &[u8], channels: u8) {
    #[inline(always)]
    fn body(out: &mut Vec<f32>, samples: &[u8], channels: u8) {
        let v = |x: u8| x as f32 / 255.0;
        match channels {
            1 => out.extend(samples.iter().map(|&x| v(x))),
            _ => out.extend(samples.as_chunks::<3>().0.iter().map(|p| luminance([v(p[0]), v(p[1]), v(p[2])]))),
        }
    }
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn body_avx2(out: &mut Vec<f32>, samples: &[u8], channels: u8) {
        body(out, samples, channels)
    }
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the processor has AVX2 (checked just above).
        return unsafe { body_avx2(out, samples, channels) };
    }
    body(out, samples, channels)
}

impl Frame {
    /// Luminance per pixel (the samples themselves for gray frames).
    pub fn gray(&self) -> Vec<f32> {
        let mut out = Vec::new();
        self.gray_into(&mut out);
        out
    }

    /// [`Frame::gray`] into a buffer that is reused from frame to frame.
    pub fn gray_into(&self, out: &mut Vec<f32>) {
        out.clear();
        fn fill<T: SampleValue>(out: &mut Vec<f32>, samples: &[T], channels: u8) {
            match channels {
                1 => out.extend(samples.iter().map(|v| v.value())),
                _ => out.extend(samples.chunks_exact(3).map(|p| luminance([p[0].value(), p[1].value(), p[2].value()]))),
            }
        }
        match &self.samples {
            Samples::Eight(s) => eight_bit_gray(out, s, self.channels),
            Samples::Sixteen(s) => fill(out, s, self.channels),
            Samples::Float(s) => fill(out, s, self.channels),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct FrameEntry {
    /// The frame's path in the bundle (PNG or TIFF, 8 or 16 bits, grey or RGB); at most 255 characters.
    #[schema(min_length = 1, max_length = 255)]
    pub file: String,
    /// How far the camera moved away from the pipe for this frame, mm.
    pub offset_mm: f64,
}

/// A frame that could not be read, as the source describes it (code, message, the file at fault).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{detail}")]
pub struct FrameError {
    pub code: Code,
    pub detail: String,
    pub culprit: Option<String>,
}

impl FrameError {
    pub fn of(e: &impl ErrorCode) -> Self {
        Self { code: e.code(), detail: e.to_string(), culprit: e.culprit() }
    }
}

impl ErrorCode for FrameError {
    fn code(&self) -> Code {
        self.code
    }

    fn culprit(&self) -> Option<String> {
        self.culprit.clone()
    }
}

/// Where the pipeline reads frames from: a bundle (directory, zip, tar), or frames in memory. The
/// pipeline never opens a file itself.
pub trait FrameSource: Sync {
    /// Decodes frame `frame` of view `view`.
    fn read_frame(&self, view: usize, frame: usize) -> Result<Frame, FrameError>;
}

/// What a station recorded for one inspection: the part, the optics, the views, and their frames.
/// The pipeline takes this; the bundle reader (and a test's frames in memory) provide it.
pub trait Recording: FrameSource {
    fn part(&self) -> &Part;
    fn optics(&self) -> &Optics;
    fn views(&self) -> &[View];
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The vectorised 8-bit gray is bit for bit the table's values through [`luminance`], for every
    /// sample value in each channel and a row length that leaves a remainder after the vector body.
    #[test]
    fn eight_bit_gray_is_the_tables_luminance() {
        let rgb: Vec<u8> =
            (0..1001usize).flat_map(|j| [j % 256, (7 * j + 3) % 256, (13 * j + 5) % 256].map(|v| v as u8)).collect();
        let mut fast = Vec::new();
        eight_bit_gray(&mut fast, &rgb, 3);
        let table: Vec<f32> =
            rgb.chunks_exact(3).map(|p| luminance([p[0].value(), p[1].value(), p[2].value()])).collect();
        assert_eq!(
            fast.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            table.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
        );
        assert!(
            (0..3).all(|c| (0..256).all(|v| rgb.iter().skip(c).step_by(3).any(|&s| s as usize == v))),
            "every value in each channel"
        );
        let mut gray = Vec::new();
        let samples: Vec<u8> = (0..=255).collect();
        eight_bit_gray(&mut gray, &samples, 1);
        assert!(gray.iter().zip(&samples).all(|(g, &v)| g.to_bits() == v.value().to_bits()));
    }
}
