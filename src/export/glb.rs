//! Binary glTF 2.0 (GLB) of the mesh, for viewers.

use crate::pipeline::mesh::Mesh;
use std::io::{self, Write};

/// Binary glTF 2.0 (GLB): one triangle mesh with per-vertex colour. Vertices stay in the pipe
/// frame's millimetres (z along the pipe axis) and the node scales them by 1/1000, since glTF's
/// unit is the metre. Colours are RGB bytes padded to four (vertex attributes are 4-byte aligned).
pub fn write(mesh: &Mesh, mut out: impl Write) -> io::Result<()> {
    let (v, t) = (mesh.vertices.len(), mesh.triangles.len());
    if t == 0 {
        // glTF accessors hold at least one element.
        return Err(io::Error::other("a mesh without triangles has no GLB form"));
    }
    let (positions_len, colors_len, indices_len) = (12 * v, 4 * v, 12 * t);
    let mut min = [f32::INFINITY; 3];
    let mut max = [f32::NEG_INFINITY; 3];
    for p in &mesh.vertices {
        for k in 0..3 {
            min[k] = min[k].min(p[k]);
            max[k] = max[k].max(p[k]);
        }
    }
    let json = serde_json::json!({
        "asset": { "version": "2.0", "generator": concat!("crestscan ", env!("CARGO_PKG_VERSION")) },
        "scene": 0,
        "scenes": [{ "nodes": [0] }],
        "nodes": [{ "mesh": 0, "name": "thread surface (pipe frame, mm)", "scale": [0.001, 0.001, 0.001] }],
        "meshes": [{ "primitives": [{ "attributes": { "POSITION": 0, "COLOR_0": 1 }, "indices": 2, "mode": 4 }] }],
        "buffers": [{ "byteLength": positions_len + colors_len + indices_len }],
        "bufferViews": [
            { "buffer": 0, "byteOffset": 0, "byteLength": positions_len, "byteStride": 12, "target": 34962 },
            { "buffer": 0, "byteOffset": positions_len, "byteLength": colors_len, "byteStride": 4, "target": 34962 },
            { "buffer": 0, "byteOffset": positions_len + colors_len, "byteLength": indices_len, "target": 34963 },
        ],
        "accessors": [
            { "bufferView": 0, "componentType": 5126, "count": v, "type": "VEC3", "min": min, "max": max },
            { "bufferView": 1, "componentType": 5121, "normalized": true, "count": v, "type": "VEC3" },
            { "bufferView": 2, "componentType": 5125, "count": 3 * t, "type": "SCALAR" },
        ],
    });
    let mut json = serde_json::to_vec(&json).map_err(io::Error::other)?;
    // Chunks are 4-byte aligned: JSON padded with spaces (the binary chunk already is).
    json.resize(json.len().next_multiple_of(4), b' ');
    let binary_len = positions_len + colors_len + indices_len;
    let total = 12 + 8 + json.len() + 8 + binary_len;
    let too_big = || io::Error::other("the mesh is too large for a GLB file (4 GiB)");
    let mut buf = Vec::with_capacity(total);
    buf.extend_from_slice(b"glTF");
    buf.extend_from_slice(&2u32.to_le_bytes());
    buf.extend_from_slice(&u32::try_from(total).map_err(|_| too_big())?.to_le_bytes());
    buf.extend_from_slice(&(json.len() as u32).to_le_bytes());
    buf.extend_from_slice(b"JSON");
    buf.extend_from_slice(&json);
    buf.extend_from_slice(&(binary_len as u32).to_le_bytes());
    buf.extend_from_slice(b"BIN\0");
    for p in &mesh.vertices {
        for x in p {
            buf.extend_from_slice(&x.to_le_bytes());
        }
    }
    for c in &mesh.colors {
        buf.extend_from_slice(&[c[0], c[1], c[2], 0]);
    }
    for tri in &mesh.triangles {
        for i in tri {
            buf.extend_from_slice(&i.to_le_bytes());
        }
    }
    out.write_all(&buf)
}
