//! The output edge: the mesh as PLY, STL and GLB, the unrolled maps as PNG, the report as a
//! self-contained HTML page, the results as a QIF 3.0 document.

pub mod glb;
pub mod html;
pub mod json;
pub mod ply;
pub mod png;
pub mod qif;
pub mod stl;

#[cfg(test)]
mod tests {
    use crate::export::{glb, ply, stl};
    use crate::pipeline::mesh::{self, Mesh, MeshOptions};

    #[test]
    fn ply_and_stl_hold_every_vertex_and_triangle() {
        let mesh = mesh::build(&mesh::tests::sector_map(), &MeshOptions { max_vertices: 10_000, ..Default::default() })
            .unwrap();
        let mut ply = Vec::new();
        ply::write(&mesh, &mut ply).unwrap();
        let header_end = ply.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        assert_eq!(ply.len() - header_end, mesh.vertices.len() * 15 + mesh.triangles.len() * 13);
        let mut stl = Vec::new();
        stl::write(&mesh, &mut stl).unwrap();
        assert_eq!(stl.len(), 84 + 50 * mesh.triangles.len());
        assert_eq!(u32::from_le_bytes(stl[80..84].try_into().unwrap()) as usize, mesh.triangles.len());
    }

    #[test]
    fn the_glb_reads_back_through_a_gltf_reader_as_the_same_mesh_in_metres() {
        let mesh = mesh::build(&mesh::tests::sector_map(), &MeshOptions { max_vertices: 10_000, ..Default::default() })
            .unwrap();
        let mut glb = Vec::new();
        glb::write(&mesh, &mut glb).unwrap();
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
        let mesh = mesh::build(&mesh::tests::sector_map(), &MeshOptions { max_vertices: 10_000, ..Default::default() })
            .unwrap();
        let mut ply = Vec::new();
        ply::write(&mesh, &mut ply).unwrap();
        assert_eq!(ply::read(&ply).unwrap(), mesh);
        let message = |bytes: &[u8]| ply::read(bytes).unwrap_err().to_string();
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
        assert!(glb::write(&Mesh::default(), Vec::new()).is_err());
    }
}
