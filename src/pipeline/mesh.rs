//! Surface mesh: Delaunay triangulation (spade) of the fused map over the unrolled (z, arc) domain,
//! lifted back to 3D. The surface is 2.5D over that domain, so the planar triangulation is exact
//! where the seed needed a learned 3D method. A vertex budget bounds the mesh: cells where the
//! profile bends (flank edges, crest and root corners, data borders) are kept, flat regions are
//! thinned on a regular stride chosen to fit the budget. Triangles longer than the stride allows
//! (bridging unseen regions) are dropped. The strip is triangulated in a fixed number of column
//! bands in parallel, which share their boundary columns. Binary PLY (with colour), binary STL and
//! binary glTF (GLB) writers are a few lines each, so they are written here rather than pulled in
//! as crates; the tests read the GLB back with the `gltf` crate.

use crate::pipeline::surface::UnrolledMap;
use rayon::prelude::*;
use spade::{DelaunayTriangulation, HasPosition, Point2, Triangulation};

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
    // The smallest stride that fits the budget (features thinned too if they alone exceed it). At
    // a stride past the grid's larger side only one cell is left, so the search ends there
    // whatever the budget.
    let mut stride = 1;
    let widest_stride = g.nz.max(g.ntheta).max(1);
    let count = |s: usize| {
        let keep = |&&(iz, it): &&(usize, usize)| iz % s == 0 && it % s == 0;
        let fs = if features.len() > options.max_vertices / 2 {
            features.iter().filter(keep).count()
        } else {
            features.len()
        };
        fs + flats.iter().filter(keep).count()
    };
    while stride <= widest_stride && count(stride) > options.max_vertices {
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

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::pipeline::surface::GridSpec;

    /// A buttress thread's unrolled surface with a 90° sector seen, the rest not.
    pub(crate) fn sector_map() -> UnrolledMap {
        let form = crate::domain::thread::ThreadForm::api_buttress(5.08, 1.5748, 0.0508, 0.0625).unwrap();
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
        let map = sector_map();
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
    }

    /// A budget no stride can meet ends the search (it once looped for ever: the grid's first cell
    /// is on every stride).
    #[test]
    fn a_budget_below_one_vertex_ends_with_the_fewest_vertices() {
        let map = sector_map();
        for max_vertices in [0, 1] {
            match build(&map, &MeshOptions { max_vertices, ..Default::default() }) {
                Ok(mesh) => assert!(mesh.vertices.len() <= 2, "{}", mesh.vertices.len()),
                Err(e) => assert!(!e.to_string().is_empty()),
            }
        }
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
