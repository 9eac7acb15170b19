//! Arcs of a turn, in degrees [start, end] with 0 ≤ start < end ≤ 360: their union, intersection,
//! total angle and length on the pipe.

/// Merges overlapping or touching intervals.
pub fn union_arcs(mut arcs: Vec<[f64; 2]>) -> Vec<[f64; 2]> {
    arcs.retain(|a| a[1] > a[0]);
    arcs.sort_by(|a, b| a[0].total_cmp(&b[0]));
    let mut merged: Vec<[f64; 2]> = Vec::with_capacity(arcs.len());
    for arc in arcs {
        match merged.last_mut() {
            Some(last) if arc[0] <= last[1] + 1e-9 => last[1] = last[1].max(arc[1]),
            _ => merged.push(arc),
        }
    }
    merged
}

/// The parts of `arcs` that lie within `within` (both lists of [from, to] in degrees).
pub fn intersect_arcs(arcs: &[[f64; 2]], within: &[[f64; 2]]) -> Vec<[f64; 2]> {
    let within = union_arcs(within.to_vec());
    let pieces = arcs.iter().flat_map(|a| within.iter().map(move |w| [a[0].max(w[0]), a[1].min(w[1])])).collect();
    union_arcs(pieces)
}

/// Degrees the arcs span (arcs as [`union_arcs`] leaves them: not overlapping).
pub fn arcs_deg(arcs: &[[f64; 2]]) -> f64 {
    arcs.iter().map(|a| a[1] - a[0]).sum()
}

pub fn arc_length_mm(arcs: &[[f64; 2]], circumference_mm: f64) -> f64 {
    arcs_deg(arcs) / 360.0 * circumference_mm
}
