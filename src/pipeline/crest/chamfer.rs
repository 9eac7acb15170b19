//! The end chamfer: crests within 1.5 pitches of the end face are machined unless the crest at the
//! same angle beyond that zone is on the mill surface too.

/// Which crests of the chamfer zone (the first `zone_end` bins in helix order, `per_turn` bins a
/// turn) stand on the mill surface: those on a geometric run where the crest at the same angle
/// on the first turn beyond the zone is on the mill surface too (on a run, or dark). The cone
/// rises away from the end face while the mill surface keeps its radius along a few pitches, so a
/// crest at an angle where the mill surface stands below the cone has one below it at that angle
/// on every later turn, and a crest with a full one beyond it at its angle is not on the mill
/// surface. The chamfer (or a turned blank) cuts the first crests without any such crest beyond:
/// on the round presets it dips thread 1's crest by 10–26 µm a few degrees after the helix starts;
/// on the Table 1 case thread 1's crests sit 310–360 µm under the cone. Where the later crest is
/// not measured, the zone's crest is taken for the chamfer.
pub(super) fn mill_surface_in_chamfer_zone(
    runs: &[bool],
    dark: &[bool],
    zone_end: usize,
    per_turn: usize,
) -> Vec<bool> {
    (0..zone_end)
        .map(|i| {
            let beyond = (i..runs.len()).step_by(per_turn.max(1)).find(|&j| j >= zone_end);
            runs[i] && beyond.is_some_and(|j| runs[j] || dark[j])
        })
        .collect()
}
