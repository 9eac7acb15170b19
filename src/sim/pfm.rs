//! Portable float map (PFM, `Pf`): one float32 channel, rows bottom-to-top, negative scale for
//! little-endian. Hand-written: the format is a three-line header and raw floats, and the image
//! crate does not write it.

use std::io::{self, Write};

pub fn write(mut out: impl Write, width: usize, height: usize, values: &[f32]) -> io::Result<()> {
    assert_eq!(values.len(), width * height);
    write!(out, "Pf\n{width} {height}\n-1.0\n")?;
    let mut row = Vec::with_capacity(width * 4);
    for y in (0..height).rev() {
        row.clear();
        for v in &values[y * width..(y + 1) * width] {
            row.extend_from_slice(&v.to_le_bytes());
        }
        out.write_all(&row)?;
    }
    Ok(())
}

/// Reads a `Pf` map into top-to-bottom rows: (width, height, values).
pub fn read(bytes: &[u8]) -> Result<(usize, usize, Vec<f32>), String> {
    let mut fields = Vec::new();
    let mut pos = 0;
    while fields.len() < 4 {
        while pos < bytes.len() && bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        let start = pos;
        while pos < bytes.len() && !bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        if start == pos {
            return Err("truncated header".into());
        }
        fields.push(std::str::from_utf8(&bytes[start..pos]).map_err(|e| e.to_string())?.to_string());
    }
    pos += 1; // the single whitespace after the scale
    if fields[0] != "Pf" {
        return Err(format!("not a one-channel PFM: {}", fields[0]));
    }
    let width: usize = fields[1].parse().map_err(|_| "bad width")?;
    let height: usize = fields[2].parse().map_err(|_| "bad height")?;
    let scale: f32 = fields[3].parse().map_err(|_| "bad scale")?;
    let data = &bytes[pos..];
    if data.len() != width * height * 4 {
        return Err(format!("expected {} bytes of data, found {}", width * height * 4, data.len()));
    }
    let mut values = vec![0f32; width * height];
    for (k, chunk) in data.chunks_exact(4).enumerate() {
        let raw = [chunk[0], chunk[1], chunk[2], chunk[3]];
        let v = if scale < 0.0 { f32::from_le_bytes(raw) } else { f32::from_be_bytes(raw) };
        let (row_from_bottom, x) = (k / width, k % width);
        values[(height - 1 - row_from_bottom) * width + x] = v;
    }
    Ok((width, height, values))
}

#[cfg(test)]
mod tests {
    #[test]
    fn round_trip_keeps_orientation_and_nan() {
        let values = vec![1.0, 2.0, f32::NAN, 4.0, 5.0, 6.0];
        let mut bytes = Vec::new();
        super::write(&mut bytes, 3, 2, &values).unwrap();
        assert!(bytes.starts_with(b"Pf\n3 2\n-1.0\n"));
        // First stored row is the bottom one.
        assert_eq!(&bytes[12..16], &4.0f32.to_le_bytes());
        let (w, h, back) = super::read(&bytes).unwrap();
        assert_eq!((w, h), (3, 2));
        assert!(back[2].is_nan());
        assert_eq!(back[5], 6.0);
    }
}
