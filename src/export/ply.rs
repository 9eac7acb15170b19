//! Binary little-endian PLY with per-vertex colour, and reading back the PLY files this program
//! stored (the service serves its GLB from the stored PLY rather than keep a third copy).

use crate::pipeline::mesh::Mesh;
use std::io::{self, Write};

/// The header [`write`] writes for `vertices` and `faces`.
fn ply_header(vertices: usize, faces: usize) -> String {
    format!(
        "ply\nformat binary_little_endian 1.0\ncomment crestscan fused thread surface (mm, pipe frame)\n\
         element vertex {vertices}\nproperty float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\n\
         element face {faces}\nproperty list uchar int vertex_indices\nend_header\n"
    )
}

/// Binary little-endian PLY with per-vertex colour.
pub fn write(mesh: &Mesh, mut out: impl Write) -> io::Result<()> {
    out.write_all(ply_header(mesh.vertices.len(), mesh.triangles.len()).as_bytes())?;
    let mut buf = Vec::with_capacity(mesh.vertices.len() * 15 + mesh.triangles.len() * 13);
    for (v, c) in mesh.vertices.iter().zip(&mesh.colors) {
        for x in v {
            buf.extend_from_slice(&x.to_le_bytes());
        }
        buf.extend_from_slice(c);
    }
    for t in &mesh.triangles {
        buf.push(3);
        for i in t {
            buf.extend_from_slice(&(*i as i32).to_le_bytes());
        }
    }
    out.write_all(&buf)
}

/// A stored mesh that is not a PLY file as [`write`] writes it.
#[derive(Debug, thiserror::Error)]
#[error("not a crestscan PLY mesh: {0}")]
pub struct PlyError(String);

/// Reads back a PLY file as [`write`] writes it, and no other layout: this is for meshes this
/// program stored (the service serves its GLB from the stored PLY rather than keep a third copy).
pub fn read(bytes: &[u8]) -> Result<Mesh, PlyError> {
    let header_end =
        bytes.windows(11).position(|w| w == b"end_header\n").ok_or_else(|| PlyError("no end_header".into()))? + 11;
    let header = std::str::from_utf8(&bytes[..header_end]).map_err(|_| PlyError("the header is not text".into()))?;
    let count = |element: &str| -> Result<usize, PlyError> {
        header
            .lines()
            .find_map(|l| l.strip_prefix(element))
            .and_then(|n| n.trim().parse().ok())
            .ok_or_else(|| PlyError(format!("no {element}count")))
    };
    let (v, t) = (count("element vertex ")?, count("element face ")?);
    if header != ply_header(v, t) {
        return Err(PlyError("a header other than the one crestscan writes".into()));
    }
    let body = &bytes[header_end..];
    if Some(body.len()) != v.checked_mul(15).and_then(|a| t.checked_mul(13).and_then(|b| a.checked_add(b))) {
        return Err(PlyError(format!("{} bytes of data for {v} vertices and {t} faces", body.len())));
    }
    let (vertex_bytes, face_bytes) = body.split_at(15 * v);
    let f32_at = |b: &[u8]| f32::from_le_bytes(b.try_into().expect("4 bytes"));
    let (vertices, colors) = vertex_bytes
        .chunks_exact(15)
        .map(|b| ([f32_at(&b[0..4]), f32_at(&b[4..8]), f32_at(&b[8..12])], [b[12], b[13], b[14]]))
        .unzip();
    let triangles = face_bytes
        .chunks_exact(13)
        .enumerate()
        .map(|(k, b)| {
            let index = |j: usize| i32::from_le_bytes(b[1 + 4 * j..5 + 4 * j].try_into().expect("4 bytes"));
            let tri = [index(0), index(1), index(2)];
            if b[0] != 3 {
                Err(PlyError(format!("face {k} is not a triangle")))
            } else if tri.iter().any(|&i| i < 0 || i as usize >= v) {
                Err(PlyError(format!("face {k} refers to a vertex that is not there")))
            } else {
                Ok(tri.map(|i| i as u32))
            }
        })
        .collect::<Result<_, _>>()?;
    Ok(Mesh { vertices, colors, triangles })
}
