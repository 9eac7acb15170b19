//! The report's plots as inline SVG, drawn here rather than with a plotting crate: each is a few
//! dozen lines of rectangles and paths, the developed surface needs run-merged cells to stay small,
//! and SVG written by hand prints at any size with no script.

use super::escape;
use crate::pipeline::report::{Report, ThreadReport};
use std::fmt::Write;

/// A diverging colour for a deviation from nominal as a fraction of the scale's half range
/// (−1 blue, 0 near white, +1 red), quantised to 21 steps so that neighbouring bins merge.
fn diverging(t: f64) -> (u8, u8, u8) {
    const LOW: (f64, f64, f64) = (33.0, 102.0, 172.0);
    const MID: (f64, f64, f64) = (247.0, 247.0, 247.0);
    const HIGH: (f64, f64, f64) = (178.0, 24.0, 43.0);
    let t = (t.clamp(-1.0, 1.0) * 10.0).round() / 10.0;
    let (from, to, s) = if t < 0.0 { (MID, LOW, -t) } else { (MID, HIGH, t) };
    let mix = |a: f64, b: f64| (a + (b - a) * s).round() as u8;
    (mix(from.0, to.0), mix(from.1, to.1), mix(from.2, to.2))
}

fn hex((r, g, b): (u8, u8, u8)) -> String {
    format!("#{r:02x}{g:02x}{b:02x}")
}

/// The crest's axial position along a thread's turn at `angle_deg` (the report gives the turn's
/// two ends; the helix is linear between them).
fn crest_z_at(t: &ThreadReport, angle_deg: f64) -> f64 {
    t.crest_z_mm[0] + (t.crest_z_mm[1] - t.crest_z_mm[0]) * angle_deg / 360.0
}

/// Thread × angle as a colour map of each 1° bin's height's deviation from nominal: a diverging
/// scale centred on nominal spanning ± twice the tolerance, the tolerance marked on its bar;
/// black-crest arcs outlined, Lc drawn where it crosses the threads, the chamfer zone (1.5 pitches
/// from the end face) shaded, unmeasured bins left blank on a hatched ground.
pub fn developed_surface(report: &Report) -> String {
    const CELL_W: f64 = 2.0;
    const ROW_H: f64 = 16.0;
    const LEFT: f64 = 44.0;
    const TOP: f64 = 10.0;
    let threads = &report.threads;
    let rows = threads.len().max(1) as f64;
    let (plot_w, plot_h) = (360.0 * CELL_W, rows * ROW_H);
    let (width, height) = (LEFT + plot_w + 90.0, TOP + plot_h + 40.0);
    let scale_mm = 2.0 * report.height_tolerance_mm.max(1e-6);
    let mut s = String::new();
    let _ = write!(
        s,
        r##"<svg class="plot" viewBox="0 0 {width} {height}" width="{width}" height="{height}" role="img" aria-label="Developed surface: height deviation from nominal by thread and angle">
<defs><pattern id="unmeasured" width="6" height="6" patternUnits="userSpaceOnUse" patternTransform="rotate(45)"><rect width="6" height="6" fill="#ffffff"/><line x1="0" y1="0" x2="0" y2="6" stroke="#d0d0d0" stroke-width="2"/></pattern></defs>
<rect x="{LEFT}" y="{TOP}" width="{plot_w}" height="{plot_h}" fill="url(#unmeasured)" stroke="#888"/>
"##
    );
    for (row, t) in threads.iter().enumerate() {
        let y = TOP + row as f64 * ROW_H;
        // Runs of bins with the same colour become one rectangle.
        let colour_at = |k: usize| -> Option<(u8, u8, u8)> {
            t.height_mm.values.get(k).copied().flatten().map(|h| diverging((h - report.nominal_height_mm) / scale_mm))
        };
        let n = t.height_mm.values.len().min(360);
        let mut k = 0;
        while k < n {
            let Some(c) = colour_at(k) else {
                k += 1;
                continue;
            };
            let start = k;
            while k < n && colour_at(k) == Some(c) {
                k += 1;
            }
            let _ = writeln!(
                s,
                r##"<rect x="{:.1}" y="{y:.1}" width="{:.1}" height="{ROW_H}" fill="{}"/>"##,
                LEFT + start as f64 * CELL_W,
                (k - start) as f64 * CELL_W,
                hex(c)
            );
        }
        for arc in &t.black_crest_arcs_deg {
            let _ = writeln!(
                s,
                r##"<rect class="black-arc" x="{:.1}" y="{:.1}" width="{:.1}" height="{:.1}" fill="none" stroke="#000" stroke-width="2.5"><title>thread {}: black crest {:.1}–{:.1}°</title></rect>"##,
                LEFT + arc[0] * CELL_W,
                y + 1.5,
                ((arc[1] - arc[0]) * CELL_W).max(1.0),
                ROW_H - 3.0,
                t.index,
                arc[0],
                arc[1]
            );
        }
        let _ = writeln!(
            s,
            r##"<text x="{:.1}" y="{:.1}" text-anchor="end" class="tick">{}</text>"##,
            LEFT - 4.0,
            y + ROW_H * 0.7,
            t.index
        );
    }
    // The chamfer zone and Lc, per angle at the fractional row where the crests' z reaches them.
    let row_at = |z_mm: f64, angle_deg: f64| -> Option<f64> {
        threads.windows(2).enumerate().find_map(|(i, w)| {
            let (a, b) = (crest_z_at(&w[0], angle_deg), crest_z_at(&w[1], angle_deg));
            ((a - z_mm) * (b - z_mm) <= 0.0 && a != b).then(|| i as f64 + 0.5 + (z_mm - a) / (b - a))
        })
    };
    let path_at = |z_mm: f64| -> String {
        let mut d = String::new();
        for angle in (0..=360).step_by(4) {
            if let Some(r) = row_at(z_mm, angle as f64) {
                let _ = write!(
                    d,
                    "{}{:.1},{:.1} ",
                    if d.is_empty() { "M" } else { "L" },
                    LEFT + angle as f64 * CELL_W,
                    TOP + r * ROW_H
                );
            }
        }
        d
    };
    let chamfer_mm = 1.5 * report.pitch_mm;
    let chamfer_rows: Vec<usize> =
        (0..threads.len()).filter(|&i| crest_z_at(&threads[i], 180.0) < chamfer_mm).collect();
    for i in chamfer_rows {
        let _ = writeln!(
            s,
            r##"<rect class="chamfer" x="{LEFT}" y="{:.1}" width="{plot_w}" height="{ROW_H}" fill="#000" fill-opacity="0.12"><title>chamfer zone: within 1.5 pitches of the end face</title></rect>"##,
            TOP + i as f64 * ROW_H
        );
    }
    let lc = path_at(report.lc_mm);
    if !lc.is_empty() {
        let _ = writeln!(
            s,
            r##"<path class="lc" d="{lc}" fill="none" stroke="#6a3d9a" stroke-width="2" stroke-dasharray="6 3"><title>Lc = {:.2} mm from the end face</title></path>"##,
            report.lc_mm
        );
    }
    // Axes.
    for angle in (0..=360).step_by(45) {
        let x = LEFT + angle as f64 * CELL_W;
        let _ = writeln!(
            s,
            r##"<text x="{x:.1}" y="{:.1}" text-anchor="middle" class="tick">{angle}°</text>"##,
            TOP + plot_h + 14.0
        );
    }
    let _ = writeln!(
        s,
        r##"<text x="{:.1}" y="{:.1}" text-anchor="middle" class="axis">angle</text><text x="10" y="{:.1}" class="axis" transform="rotate(-90 10 {:.1})" text-anchor="middle">thread</text>"##,
        LEFT + plot_w / 2.0,
        TOP + plot_h + 30.0,
        TOP + plot_h / 2.0,
        TOP + plot_h / 2.0
    );
    // The colour bar: ± twice the tolerance, the tolerance marked.
    let (bar_x, bar_h) = (LEFT + plot_w + 20.0, plot_h.max(120.0).min(height - TOP - 30.0));
    for step in 0..=20 {
        let t = 1.0 - step as f64 / 10.0;
        let _ = writeln!(
            s,
            r##"<rect x="{bar_x:.1}" y="{:.1}" width="14" height="{:.2}" fill="{}"/>"##,
            TOP + step as f64 * bar_h / 21.0,
            bar_h / 21.0 + 0.3,
            hex(diverging(t))
        );
    }
    let y_of = |t: f64| TOP + (1.0 - t) / 2.0 * bar_h;
    for (t, label) in [
        (1.0, format!("+{:.0} µm", 1e3 * scale_mm)),
        (0.5, format!("+{:.0} tol", 1e3 * report.height_tolerance_mm)),
        (0.0, "nominal".to_string()),
        (-0.5, format!("−{:.0} tol", 1e3 * report.height_tolerance_mm)),
        (-1.0, format!("−{:.0} µm", 1e3 * scale_mm)),
    ] {
        let y = y_of(t);
        let _ = writeln!(
            s,
            r##"<line x1="{bar_x:.1}" y1="{y:.1}" x2="{:.1}" y2="{y:.1}" stroke="{}" stroke-width="{}"/><text x="{:.1}" y="{:.1}" class="tick">{}</text>"##,
            bar_x + 18.0,
            if t.abs() == 0.5 { "#000" } else { "#888" },
            if t.abs() == 0.5 { 1.5 } else { 0.7 },
            bar_x + 20.0,
            y + 3.5,
            escape(&label)
        );
    }
    s.push_str("</svg>\n");
    s
}

/// One thread's height along the angle: the tolerance band, the uncertainty band (value ± U),
/// the values (gaps where no view saw the bin).
pub fn thread_heights(report: &Report, t: &ThreadReport) -> String {
    const W: f64 = 360.0;
    const H: f64 = 90.0;
    const LEFT: f64 = 46.0;
    const TOP: f64 = 6.0;
    let nominal = report.nominal_height_mm;
    let tol = report.height_tolerance_mm.max(1e-6);
    // The vertical range: three tolerances either side, or what the values and their U reach.
    let reach = t
        .height_mm
        .values
        .iter()
        .zip(t.height_mm.uncertainty_mm.iter().map(Some).chain(std::iter::repeat(None)))
        .filter_map(|(v, u)| v.map(|v| (v - nominal).abs() + u.copied().flatten().unwrap_or(0.0)))
        .fold(3.0 * tol, f64::max)
        .min(20.0 * tol);
    let y = |h: f64| TOP + H / 2.0 - (h - nominal).clamp(-reach, reach) / reach * (H / 2.0);
    let x = |a: f64| LEFT + a * W / 360.0;
    let mut s = String::new();
    let _ = writeln!(
        s,
        r##"<svg class="plot thread" viewBox="0 0 {} {}" width="{}" height="{}" role="img" aria-label="Thread {} height along the angle">"##,
        LEFT + W + 8.0,
        TOP + H + 18.0,
        LEFT + W + 8.0,
        TOP + H + 18.0,
        t.index
    );
    let _ = writeln!(
        s,
        r##"<rect x="{LEFT}" y="{:.1}" width="{W}" height="{:.1}" fill="#dbeedb"><title>nominal ± tolerance</title></rect><rect x="{LEFT}" y="{TOP}" width="{W}" height="{H}" fill="none" stroke="#888"/><line x1="{LEFT}" x2="{:.1}" y1="{:.1}" y2="{:.1}" stroke="#6a8" stroke-width="0.8"/>"##,
        y(nominal + tol),
        y(nominal - tol) - y(nominal + tol),
        LEFT + W,
        y(nominal),
        y(nominal)
    );
    // Runs of measured bins: the uncertainty band and the line.
    let values = &t.height_mm.values;
    let angles = &t.height_mm.angles_deg;
    let u_at = |k: usize| t.height_mm.uncertainty_mm.get(k).copied().flatten();
    let mut k = 0;
    while k < values.len() {
        if values[k].is_none() {
            k += 1;
            continue;
        }
        let start = k;
        while k < values.len() && values[k].is_some() {
            k += 1;
        }
        let run = start..k;
        if run.clone().all(|i| u_at(i).is_some()) {
            let mut d = String::new();
            for i in run.clone() {
                let _ = write!(
                    d,
                    "{}{:.1},{:.1} ",
                    if i == start { "M" } else { "L" },
                    x(angles[i]),
                    y(values[i].unwrap() + u_at(i).unwrap())
                );
            }
            for i in run.clone().rev() {
                let _ = write!(d, "L{:.1},{:.1} ", x(angles[i]), y(values[i].unwrap() - u_at(i).unwrap()));
            }
            let _ = writeln!(s, r##"<path class="u-band" d="{d}Z" fill="#9ecae1" fill-opacity="0.6"/>"##);
        }
        let points: String =
            run.map(|i| format!("{:.1},{:.1}", x(angles[i]), y(values[i].unwrap()))).collect::<Vec<_>>().join(" ");
        let _ = writeln!(s, r##"<polyline points="{points}" fill="none" stroke="#08519c" stroke-width="1.2"/>"##);
    }
    for arc in &t.black_crest_arcs_deg {
        let _ = writeln!(
            s,
            r##"<rect x="{:.1}" y="{:.1}" width="{:.1}" height="4" fill="#000"><title>black crest {:.1}–{:.1}°</title></rect>"##,
            x(arc[0]),
            TOP + H - 4.0,
            (x(arc[1]) - x(arc[0])).max(1.0),
            arc[0],
            arc[1]
        );
    }
    for (h, label) in [
        (nominal + tol, format!("+{:.0}", 1e3 * tol)),
        (nominal, "nom".into()),
        (nominal - tol, format!("−{:.0}", 1e3 * tol)),
    ] {
        let _ = writeln!(
            s,
            r##"<text x="{:.1}" y="{:.1}" text-anchor="end" class="tick">{label}</text>"##,
            LEFT - 3.0,
            y(h) + 3.5
        );
    }
    for a in (0..=360).step_by(90) {
        let _ = writeln!(
            s,
            r##"<text x="{:.1}" y="{:.1}" text-anchor="middle" class="tick">{a}°</text>"##,
            x(a as f64),
            TOP + H + 13.0
        );
    }
    s.push_str("</svg>\n");
    s
}

/// A thread's black-crest arcs on its circle, against the 25% of the circumference a buttress
/// thread may show (drawn from the top, for scale), or with no limit for round threads.
pub fn black_arcs_polar(index: u32, arcs_deg: &[[f64; 2]], limit_fraction: Option<f64>) -> String {
    const R: f64 = 38.0;
    const C: f64 = 50.0;
    let point = |deg: f64, r: f64| {
        let rad = (deg - 90.0).to_radians();
        (C + r * rad.cos(), C + r * rad.sin())
    };
    let arc_path = |from: f64, to: f64, r: f64| {
        let (x0, y0) = point(from, r);
        let (x1, y1) = point(to, r);
        let large = if to - from > 180.0 { 1 } else { 0 };
        format!("M{x0:.2},{y0:.2} A{r},{r} 0 {large} 1 {x1:.2},{y1:.2}")
    };
    let mut s = String::new();
    let _ = writeln!(
        s,
        r##"<svg class="plot polar" viewBox="0 0 100 112" width="130" height="146" role="img" aria-label="Thread {index}: black-crest arcs"><circle cx="{C}" cy="{C}" r="{R}" fill="none" stroke="#bbb" stroke-width="4"/>"##
    );
    if let Some(f) = limit_fraction {
        let _ = writeln!(
            s,
            r##"<path d="{}" fill="none" stroke="#fdae6b" stroke-width="3"><title>the limit: {:.0}% of the circumference</title></path>"##,
            arc_path(0.0, 360.0 * f, R + 6.0),
            100.0 * f
        );
    }
    let mut total = 0.0;
    for arc in arcs_deg {
        total += arc[1] - arc[0];
        let _ = writeln!(
            s,
            r##"<path d="{}" fill="none" stroke="#000" stroke-width="6"><title>{:.1}–{:.1}°</title></path>"##,
            arc_path(arc[0], arc[1].max(arc[0] + 0.5), R),
            arc[0],
            arc[1]
        );
    }
    let _ = writeln!(
        s,
        r##"<text x="{C}" y="{:.1}" text-anchor="middle" class="tick">{index}</text><text x="{C}" y="108" text-anchor="middle" class="tick">{:.0}% black</text></svg>"##,
        C + 4.0,
        100.0 * total / 360.0
    );
    s
}

/// crestscan against the CMM: a scatter with the identity line, and Bland–Altman (difference
/// against mean, the bias and the 95% limits of agreement).
pub fn cmm_plots(points: &[(f64, f64)], bias_mm: Option<f64>, limits_mm: Option<[f64; 2]>) -> String {
    const S: f64 = 220.0;
    const M: f64 = 44.0;
    let mut s = String::new();
    if points.is_empty() {
        return s;
    }
    let lo = points.iter().map(|p| p.0.min(p.1)).fold(f64::MAX, f64::min);
    let hi = points.iter().map(|p| p.0.max(p.1)).fold(f64::MIN, f64::max);
    let pad = ((hi - lo) * 0.08).max(0.005);
    let (lo, hi) = (lo - pad, hi + pad);
    let sx = |v: f64| M + (v - lo) / (hi - lo) * S;
    let sy = |v: f64| 8.0 + S - (v - lo) / (hi - lo) * S;
    let _ = writeln!(
        s,
        r##"<svg class="plot" viewBox="0 0 {0} {1}" width="{0}" height="{1}" role="img" aria-label="crestscan against CMM"><rect x="{M}" y="8" width="{S}" height="{S}" fill="none" stroke="#888"/><line x1="{2:.1}" y1="{3:.1}" x2="{4:.1}" y2="{5:.1}" stroke="#888" stroke-dasharray="4 3"><title>identity</title></line>"##,
        M + S + 10.0,
        S + 46.0,
        sx(lo),
        sy(lo),
        sx(hi),
        sy(hi)
    );
    for &(cmm, ours) in points {
        let _ = writeln!(s, r##"<circle cx="{:.1}" cy="{:.1}" r="2.5" fill="#08519c"/>"##, sx(cmm), sy(ours));
    }
    let height_ticks = nice_ticks(lo, hi, 4);
    let decimals = tick_decimals(&height_ticks);
    for &t in &height_ticks {
        let _ = writeln!(
            s,
            r##"<line x1="{0:.1}" x2="{0:.1}" y1="{1:.1}" y2="{2:.1}" stroke="#888"/><text x="{0:.1}" y="{3:.1}" text-anchor="middle" class="tick">{4:.5$}</text><line x1="{6:.1}" x2="{M}" y1="{7:.1}" y2="{7:.1}" stroke="#888"/><text x="{8:.1}" y="{9:.1}" text-anchor="end" class="tick">{4:.5$}</text>"##,
            sx(t),
            8.0 + S,
            8.0 + S + 4.0,
            8.0 + S + 15.0,
            t,
            decimals,
            M - 4.0,
            sy(t),
            M - 6.0,
            sy(t) + 3.5
        );
    }
    let _ = writeln!(
        s,
        r##"<text x="{:.1}" y="{:.1}" text-anchor="middle" class="axis">CMM height, mm</text><text x="12" y="{:.1}" transform="rotate(-90 12 {:.1})" text-anchor="middle" class="axis">crestscan, mm</text></svg>"##,
        M + S / 2.0,
        S + 40.0,
        8.0 + S / 2.0,
        8.0 + S / 2.0
    );
    // Bland–Altman.
    let diffs: Vec<(f64, f64)> = points.iter().map(|&(c, o)| ((c + o) / 2.0, o - c)).collect();
    let dmax = diffs
        .iter()
        .map(|d| d.1.abs())
        .chain(limits_mm.into_iter().flat_map(|l| l.map(f64::abs)))
        .fold(0.002, f64::max)
        * 1.15;
    let by = |d: f64| 8.0 + S / 2.0 - d / dmax * (S / 2.0);
    let _ = writeln!(
        s,
        r##"<svg class="plot" viewBox="0 0 {0} {1}" width="{0}" height="{1}" role="img" aria-label="Bland–Altman"><rect x="{M}" y="8" width="{S}" height="{S}" fill="none" stroke="#888"/><line x1="{M}" x2="{2}" y1="{3:.1}" y2="{3:.1}" stroke="#bbb"/>"##,
        M + S + 70.0,
        S + 46.0,
        M + S,
        by(0.0)
    );
    let mut line = |d: f64, label: String, dash: &str| {
        let _ = writeln!(
            s,
            r##"<line x1="{M}" x2="{:.1}" y1="{:.1}" y2="{:.1}" stroke="#b2182b" stroke-dasharray="{dash}"/><text x="{:.1}" y="{:.1}" class="tick">{}</text>"##,
            M + S,
            by(d),
            by(d),
            M + S + 3.0,
            by(d) + 3.5,
            escape(&label)
        );
    };
    if let Some(b) = bias_mm {
        line(b, format!("bias {:+.1} µm", 1e3 * b), "");
    }
    if let Some([a, b]) = limits_mm {
        line(a, format!("{:+.1} µm", 1e3 * a), "5 3");
        line(b, format!("{:+.1} µm", 1e3 * b), "5 3");
    }
    for &(mean, d) in &diffs {
        let _ = writeln!(s, r##"<circle cx="{:.1}" cy="{:.1}" r="2.5" fill="#08519c"/>"##, sx(mean), by(d));
    }
    for &t in &height_ticks {
        let _ = writeln!(
            s,
            r##"<line x1="{0:.1}" x2="{0:.1}" y1="{1:.1}" y2="{2:.1}" stroke="#888"/><text x="{0:.1}" y="{3:.1}" text-anchor="middle" class="tick">{4:.5$}</text>"##,
            sx(t),
            8.0 + S,
            8.0 + S + 4.0,
            8.0 + S + 15.0,
            t,
            decimals
        );
    }
    let diff_ticks_um = nice_ticks(-1e3 * dmax, 1e3 * dmax, 4);
    let diff_decimals = tick_decimals(&diff_ticks_um);
    for &t in &diff_ticks_um {
        let _ = writeln!(
            s,
            r##"<line x1="{0:.1}" x2="{M}" y1="{1:.1}" y2="{1:.1}" stroke="#888"/><text x="{2:.1}" y="{3:.1}" text-anchor="end" class="tick">{4:+.5$}</text>"##,
            M - 4.0,
            by(t / 1e3),
            M - 6.0,
            by(t / 1e3) + 3.5,
            t,
            diff_decimals
        );
    }
    let _ = writeln!(
        s,
        r##"<text x="{:.1}" y="{:.1}" text-anchor="middle" class="axis">mean of the two, mm</text><text x="10" y="{:.1}" transform="rotate(-90 10 {:.1})" text-anchor="middle" class="axis">crestscan − CMM, µm</text></svg>"##,
        M + S / 2.0,
        S + 40.0,
        8.0 + S / 2.0,
        8.0 + S / 2.0
    );
    s
}

/// Round tick values (1, 2 or 5 × 10ⁿ apart) inside [lo, hi], about `target` of them.
fn nice_ticks(lo: f64, hi: f64, target: usize) -> Vec<f64> {
    if !(hi > lo) || !lo.is_finite() || !hi.is_finite() {
        return Vec::new();
    }
    let rough = (hi - lo) / target.max(1) as f64;
    let magnitude = 10f64.powf(rough.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0].iter().map(|m| m * magnitude).find(|&st| st >= rough).unwrap_or(10.0 * magnitude);
    let first = (lo / step).ceil() as i64;
    let last = (hi / step).floor() as i64;
    (first..=last).map(|k| k as f64 * step).collect()
}

/// Decimals enough to tell the ticks apart.
fn tick_decimals(ticks: &[f64]) -> usize {
    match ticks {
        [a, b, ..] => (-(b - a).abs().log10().floor()).max(0.0) as usize,
        _ => 3,
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn ticks_are_round_and_inside_the_range() {
        let ticks = nice_ticks(1.55, 1.62, 4);
        assert_eq!(ticks.len(), 4, "{ticks:?}");
        for (t, want) in ticks.iter().zip([1.56, 1.58, 1.60, 1.62]) {
            assert!((t - want).abs() < 1e-9, "{ticks:?}");
        }
        assert_eq!(tick_decimals(&ticks), 2);
        assert_eq!(nice_ticks(-23.0, 23.0, 4), vec![-20.0, 0.0, 20.0]);
        assert_eq!(nice_ticks(-23.0, 23.0, 5), vec![-20.0, -10.0, 0.0, 10.0, 20.0]);
        assert_eq!(tick_decimals(&[-20.0, -10.0]), 0);
        assert!(nice_ticks(1.0, 1.0, 4).is_empty());
    }

    #[test]
    fn the_cmm_plots_carry_numeric_ticks_on_both_axes() {
        let points = [(1.57, 1.575), (1.58, 1.578), (1.59, 1.596)];
        let svg = cmm_plots(&points, Some(0.003), Some([-0.004, 0.01]));
        assert!(svg.contains(">1.58</text>"), "{svg}");
        assert!(svg.contains(">+0</text>") || svg.contains(">+5</text>"), "{svg}");
        assert!(svg.contains("crestscan − CMM, µm"));
    }

    use super::*;

    #[test]
    fn the_scale_is_white_at_nominal_and_saturates_beyond_its_range() {
        assert_eq!(diverging(0.0), (247, 247, 247));
        assert_eq!(diverging(1.0), (178, 24, 43));
        assert_eq!(diverging(-3.0), (33, 102, 172));
        assert_eq!(diverging(0.52), diverging(0.48));
        assert_ne!(diverging(0.5), diverging(-0.5));
    }

    #[test]
    fn a_polar_plot_draws_one_stroke_per_arc_and_the_limit() {
        let svg = black_arcs_polar(3, &[[10.0, 40.0], [200.0, 220.0]], Some(0.25));
        assert_eq!(svg.matches("stroke-width=\"6\"").count(), 2);
        assert!(svg.contains("25% of the circumference"));
        assert!(svg.contains("14% black"), "{svg}");
        assert!(!black_arcs_polar(3, &[], None).contains("the limit"));
    }
}
