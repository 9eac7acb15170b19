//! Surface mesh: Delaunay triangulation (spade) of the fused map over the unrolled (z, arc) domain,
//! lifted back to 3D. The surface is 2.5D over that domain, so the planar triangulation is exact
//! where the seed needed a learned 3D method. A vertex budget bounds the mesh: cells where the
//! profile bends (flank edges, crest and root corners, data borders) are kept, flat regions are
//! thinned on a regular stride chosen to fit the budget. Triangles longer than the stride allows
//! (bridging unseen regions) are dropped. The strip is triangulated in a fixed number of column
//! bands in parallel, which share their boundary columns. Binary PLY (with colour), binary STL and
//! binary glTF (GLB) writers are a few lines each, so they are written here rather than pulled in
//! as crates; the tests read the GLB back with the `gltf` crate.

use crate::fuse::UnrolledMap;
use rayon::prelude::*;
use spade::{DelaunayTriangulation, HasPosition, Point2, Triangulation};
use std::io::{self, Write};

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MeshOptions {
    pub max_vertices: usize,
    /// Radius change between neighbouring cells (second difference along z) that marks a feature.
    pub feature_mm: f32,
}

impl Default for MeshOptions {
    fn default() -> Self {
        Self { max_vertices: 400_000, feature_mm: 0.01 }
    }
}

#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<[f32; 3]>,
    pub colors: Vec<[u8; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

struct Site {
    position: Point2<f64>,
    index: u32,
}

impl HasPosition for Site {
    type Scalar = f64;
    fn position(&self) -> Point2<f64> {
        self.position
    }
}

#[derive(Debug, thiserror::Error)]
#[error("triangulation failed: {0}")]
pub struct MeshError(String);

pub fn build(map: &UnrolledMap, options: &MeshOptions) -> Result<Mesh, MeshError> {
    let g = &map.grid;
    let finite = |iz: usize, it: usize| map.radius_mm[map.index(iz, it)].is_finite();
    let feature = |iz: usize, it: usize| -> bool {
        if iz == 0 || iz + 1 >= g.nz || !finite(iz - 1, it) || !finite(iz + 1, it) {
            return true;
        }
        let (a, b, c) = (
            map.radius_mm[map.index(iz - 1, it)],
            map.radius_mm[map.index(iz, it)],
            map.radius_mm[map.index(iz + 1, it)],
        );
        (a - 2.0 * b + c).abs() > options.feature_mm
    };
    let mut features = Vec::new();
    let mut flats = Vec::new();
    for iz in 0..g.nz {
        for it in 0..g.ntheta {
            if finite(iz, it) {
                if feature(iz, it) { features.push((iz, it)) } else { flats.push((iz, it)) }
            }
        }
    }
    // The smallest stride that fits the budget (features thinned too if they alone exceed it).
    let mut stride = 1;
    let count = |s: usize| {
        let keep = |&&(iz, it): &&(usize, usize)| iz % s == 0 && it % s == 0;
        let fs = if features.len() > options.max_vertices / 2 {
            features.iter().filter(keep).count()
        } else {
            features.len()
        };
        fs + flats.iter().filter(keep).count()
    };
    while count(stride) > options.max_vertices {
        stride += 1;
    }
    let thin_features = features.len() > options.max_vertices / 2;
    let chosen: Vec<(usize, usize)> = features
        .into_iter()
        .filter(|&(iz, it)| !thin_features || (iz % stride == 0 && it % stride == 0))
        .chain(flats.into_iter().filter(|&(iz, it)| iz % stride == 0 && it % stride == 0))
        .collect();
    let radius_ref = map.radius_mm.iter().filter(|r| r.is_finite()).fold(0f32, |m, &r| m.max(r)) as f64;
    let arc_per_column = std::f64::consts::TAU * radius_ref / g.ntheta as f64;
    let mut mesh = Mesh::default();
    let mut sites = Vec::with_capacity(chosen.len());
    for (k, &(iz, it)) in chosen.iter().enumerate() {
        let i = map.index(iz, it);
        let (z, theta) = (g.z_at(iz), g.theta_deg_at(it).to_radians());
        let r = map.radius_mm[i] as f64;
        mesh.vertices.push([(r * theta.cos()) as f32, (r * theta.sin()) as f32, z as f32]);
        mesh.colors.push(map.rgb[i].map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8));
        // Sites on the grid are nudged by up to 1/20000 of a cell (a fixed hash of the index, so the
        // mesh is the same every run): the corners of every grid square are exactly cocircular, and
        // each such incircle test falls through to exact arithmetic (a fifth of the
        // triangulation's time). The nudge only picks one of a square's two diagonals; vertices
        // keep their grid positions.
        let (jz, js) = nudge(k as u64);
        sites.push(Site {
            position: Point2::new(z + jz * g.dz_mm, it as f64 * arc_per_column + js * arc_per_column),
            index: k as u32,
        });
    }
    let max_edge = 1.5 * (stride as f64 + 1.0) * g.dz_mm.max(arc_per_column);
    // The strip is triangulated in TILES bands of columns, in parallel; neighbouring bands share
    // their boundary column (a multiple of the stride, so flats have sites there), whose sites on
    // both sides give the same edges between them. The count is fixed, not taken from the cores,
    // so that every machine builds the same mesh.
    const TILES: usize = 8;
    let bounds: Vec<usize> =
        (0..=TILES).map(|t| if t == TILES { g.ntheta } else { t * g.ntheta / TILES / stride * stride }).collect();
    let tiles: Vec<Vec<[u32; 3]>> = bounds
        .windows(2)
        .collect::<Vec<_>>()
        .into_par_iter()
        .map(|w| {
            let (first, last) = (w[0], w[1]);
            let tile: Vec<Site> = chosen
                .iter()
                .zip(&sites)
                .filter(|((_, it), _)| (first..=last).contains(it))
                .map(|(_, site)| Site { position: site.position, index: site.index })
                .collect();
            triangulate(tile, &chosen, max_edge)
        })
        .collect::<Result<_, MeshError>>()?;
    mesh.triangles = tiles.concat();
    Ok(mesh)
}

/// The triangles of one tile's sites, less those bridging unseen regions (an edge over
/// `max_edge`) and slivers along data borders.
fn triangulate(sites: Vec<Site>, chosen: &[(usize, usize)], max_edge: f64) -> Result<Vec<[u32; 3]>, MeshError> {
    if sites.len() < 3 {
        return Ok(Vec::new());
    }
    let triangulation: DelaunayTriangulation<Site> =
        DelaunayTriangulation::bulk_load(sites).map_err(|e| MeshError(format!("{e:?}")))?;
    let mut triangles = Vec::with_capacity(triangulation.num_inner_faces());
    for face in triangulation.inner_faces() {
        let [a, b, c] = face.vertices();
        let (pa, pb, pc) = (a.position(), b.position(), c.position());
        let long = |p: Point2<f64>, q: Point2<f64>| (p.x - q.x).hypot(p.y - q.y) > max_edge;
        if long(pa, pb) || long(pb, pc) || long(pc, pa) {
            continue;
        }
        let corners = [a.data().index, b.data().index, c.data().index];
        // Three sites in a row on the grid (along a data border) make a sliver once nudged: its
        // vertices, on their grid positions, are collinear. (Exact: the grid indices are integers.)
        let [(z0, t0), (z1, t1), (z2, t2)] = corners.map(|k| chosen[k as usize]).map(|(iz, it)| (iz as i64, it as i64));
        if (z1 - z0) * (t2 - t0) == (z2 - z0) * (t1 - t0) {
            continue;
        }
        triangles.push(corners);
    }
    Ok(triangles)
}

/// Two offsets in [−0.5e-4, 0.5e-4) from a site's index (Weyl sequence bits: cheap, fixed).
fn nudge(index: u64) -> (f64, f64) {
    let h = (index + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    let unit = |bits: u64| (bits >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
    (1e-4 * unit(h), 1e-4 * unit(h.rotate_left(29)))
}

/// The header [`write_ply`] writes for `vertices` and `faces`.
fn ply_header(vertices: usize, faces: usize) -> String {
    format!(
        "ply\nformat binary_little_endian 1.0\ncomment crestscan fused thread surface (mm, pipe frame)\n\
         element vertex {vertices}\nproperty float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\n\
         element face {faces}\nproperty list uchar int vertex_indices\nend_header\n"
    )
}

/// Binary little-endian PLY with per-vertex colour.
pub fn write_ply(mesh: &Mesh, mut out: impl Write) -> io::Result<()> {
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

/// Binary STL (no colour).
pub fn write_stl(mesh: &Mesh, mut out: impl Write) -> io::Result<()> {
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

/// Binary glTF 2.0 (GLB): one triangle mesh with per-vertex colour. Vertices stay in the pipe
/// frame's millimetres (z along the pipe axis) and the node scales them by 1/1000, since glTF's
/// unit is the metre. Colours are RGB bytes padded to four (vertex attributes are 4-byte aligned).
pub fn write_glb(mesh: &Mesh, mut out: impl Write) -> io::Result<()> {
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

/// A stored mesh that is not a PLY file as [`write_ply`] writes it.
#[derive(Debug, thiserror::Error)]
#[error("not a crestscan PLY mesh: {0}")]
pub struct PlyError(String);

/// Reads back a PLY file as [`write_ply`] writes it, and no other layout: this is for meshes this
/// program stored (the service serves its GLB from the stored PLY rather than keep a third copy).
pub fn read_ply(bytes: &[u8]) -> Result<Mesh, PlyError> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fuse::GridSpec;

    fn map() -> UnrolledMap {
        let form = crate::thread::ThreadForm::api_buttress(5.08, 1.5748, 0.0508, 0.0625).unwrap();
        let grid = GridSpec { z0_mm: 0.0, dz_mm: 0.05, nz: 200, ntheta: 720 };
        let mut radius = Vec::new();
        for iz in 0..grid.nz {
            for it in 0..grid.ntheta {
                // A 90° sector seen, the rest not.
                let seen = it < 180;
                let r = 55.0 + form.height_at(grid.z_at(iz) - 5.08 * grid.theta_deg_at(it) / 360.0);
                radius.push(if seen { r as f32 } else { f32::NAN });
            }
        }
        let cells = radius.len();
        UnrolledMap { grid, radius_mm: radius, weight: vec![1.0; cells], rgb: vec![[0.5; 3]; cells] }
    }

    #[test]
    fn mesh_respects_the_budget_and_stays_on_the_seen_surface() {
        let map = map();
        let mesh = build(&map, &MeshOptions { max_vertices: 10_000, ..Default::default() }).unwrap();
        assert!(mesh.vertices.len() <= 10_000 && mesh.vertices.len() > 5_000, "{}", mesh.vertices.len());
        assert!(mesh.triangles.len() > mesh.vertices.len(), "{}", mesh.triangles.len());
        for t in &mesh.triangles {
            for &i in t {
                let v = mesh.vertices[i as usize];
                let theta = (v[1] as f64).atan2(v[0] as f64).to_degrees();
                assert!((-0.5..90.5).contains(&theta), "a vertex off the seen sector at {theta}°");
            }
        }
        let mut ply = Vec::new();
        write_ply(&mesh, &mut ply).unwrap();
        let header_end = ply.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        assert_eq!(ply.len() - header_end, mesh.vertices.len() * 15 + mesh.triangles.len() * 13);
        let mut stl = Vec::new();
        write_stl(&mesh, &mut stl).unwrap();
        assert_eq!(stl.len(), 84 + 50 * mesh.triangles.len());
        assert_eq!(u32::from_le_bytes(stl[80..84].try_into().unwrap()) as usize, mesh.triangles.len());
    }

    #[test]
    fn the_glb_reads_back_through_a_gltf_reader_as_the_same_mesh_in_metres() {
        let mesh = build(&map(), &MeshOptions { max_vertices: 10_000, ..Default::default() }).unwrap();
        let mut glb = Vec::new();
        write_glb(&mesh, &mut glb).unwrap();
        assert_eq!(u32::from_le_bytes(glb[8..12].try_into().unwrap()) as usize, glb.len());
        // `from_slice` validates the document (required bounds, alignment, indices in range).
        let gltf = gltf::Gltf::from_slice(&glb).unwrap();
        let blob = gltf.blob.clone().unwrap();
        let node = gltf.nodes().next().unwrap();
        assert_eq!(node.transform().decomposed().2, [0.001; 3]);
        let primitive = node.mesh().unwrap().primitives().next().unwrap();
        assert_eq!(primitive.mode(), gltf::mesh::Mode::Triangles);
        let reader = primitive.reader(|_| Some(&blob));
        let positions: Vec<[f32; 3]> = reader.read_positions().unwrap().collect();
        assert_eq!(positions, mesh.vertices);
        let colors: Vec<[u8; 3]> = reader.read_colors(0).unwrap().into_rgb_u8().collect();
        assert_eq!(colors, mesh.colors);
        let indices: Vec<u32> = reader.read_indices().unwrap().into_u32().collect();
        assert_eq!(indices, mesh.triangles.iter().flatten().copied().collect::<Vec<_>>());
        let bounds = primitive.bounding_box();
        for k in 0..3 {
            assert_eq!(bounds.min[k], mesh.vertices.iter().map(|v| v[k]).fold(f32::INFINITY, f32::min));
            assert_eq!(bounds.max[k], mesh.vertices.iter().map(|v| v[k]).fold(f32::NEG_INFINITY, f32::max));
        }
    }

    #[test]
    fn a_stored_ply_reads_back_as_the_mesh_and_a_damaged_one_is_refused() {
        let mesh = build(&map(), &MeshOptions { max_vertices: 10_000, ..Default::default() }).unwrap();
        let mut ply = Vec::new();
        write_ply(&mesh, &mut ply).unwrap();
        assert_eq!(read_ply(&ply).unwrap(), mesh);
        let message = |bytes: &[u8]| read_ply(bytes).unwrap_err().to_string();
        assert!(message(&ply[..ply.len() - 1]).contains("bytes of data"), "{}", message(&ply[..ply.len() - 1]));
        let ascii = String::from_utf8_lossy(&ply[..200]).replace("binary_little_endian", "ascii").into_bytes();
        assert!(message(&[ascii.as_slice(), &ply[200..]].concat()).contains("header"));
        // A face pointing past the last vertex.
        let mut bad = ply.clone();
        let last_index = bad.len() - 4;
        bad[last_index..].copy_from_slice(&(mesh.vertices.len() as i32).to_le_bytes());
        assert!(message(&bad).contains("refers to a vertex"), "{}", message(&bad));
        assert!(message(b"solid not a ply").contains("end_header"));
        // glTF has no empty accessors: a mesh without triangles is refused, not written invalid.
        assert!(write_glb(&Mesh::default(), Vec::new()).is_err());
    }

    #[test]
    fn a_full_grid_is_split_into_two_triangles_per_square() {
        // Every square's corners are cocircular; the nudged sites still give each square one
        // diagonal, and the same mesh every time.
        let grid = GridSpec { z0_mm: 0.0, dz_mm: 0.05, nz: 20, ntheta: 360 };
        let cells = grid.nz * grid.ntheta;
        let map =
            UnrolledMap { grid, radius_mm: vec![55.0; cells], weight: vec![1.0; cells], rgb: vec![[0.5; 3]; cells] };
        let mesh = build(&map, &MeshOptions::default()).unwrap();
        assert_eq!(mesh.vertices.len(), cells);
        // The last column is not joined back to the first (the unrolled domain is a strip).
        assert_eq!(mesh.triangles.len(), 2 * 19 * 359);
        assert_eq!(build(&map, &MeshOptions::default()).unwrap(), mesh);
    }
}
