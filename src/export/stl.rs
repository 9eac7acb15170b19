//! Binary STL (no colour).

use crate::pipeline::mesh::Mesh;
use std::io::{self, Write};

/// Binary STL (no colour).
pub fn write(mesh: &Mesh, mut out: impl Write) -> io::Result<()> {
    let mut buf = Vec::with_capacity(84 + 50 * mesh.triangles.len());
    let mut header = [0u8; 80];
    header[..37].copy_from_slice(b"crestscan fused thread surface, mm   ");
    buf.extend_from_slice(&header);
    buf.extend_from_slice(&(mesh.triangles.len() as u32).to_le_bytes());
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| nalgebra::Vector3::from(mesh.vertices[i as usize]));
        let n = (b - a).cross(&(c - a));
        let n = if n.norm() > 0.0 { n.normalize() } else { n };
        for v in [n, a, b, c] {
            for x in v.iter() {
                buf.extend_from_slice(&x.to_le_bytes());
            }
        }
        buf.extend_from_slice(&[0, 0]);
    }
    out.write_all(&buf)
}
