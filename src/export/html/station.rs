//! A station's page: its status, the fingerprint its study bound it to, the uncertainty
//! components, the correction per thread, and the gauge figures (bias before and after the
//! correction, repeatability, Cg/Cgk, %GRR, ndc), for the quality engineer who releases it.

use super::{STYLE, escape};
use crate::domain::qualification::Qualification;
use std::fmt::Write;

/// What the page shows of a station besides its qualification.
pub struct StationPage<'a> {
    pub name: &'a str,
    pub description: Option<&'a str>,
    pub status: &'a str,
    pub status_reason: Option<&'a str>,
    /// (serial, instrument, calibrated at, certificate U in µm).
    pub masters: Vec<(String, String, String, f64)>,
    pub qualification: Option<&'a Qualification>,
}

fn opt(v: Option<f64>, decimals: usize) -> String {
    v.map_or("–".into(), |v| format!("{v:.decimals$}"))
}

/// Bars of each thread's bias before (grey) and after (blue) the correction, µm.
fn bias_plot(q: &Qualification) -> String {
    let threads = &q.gauge.threads;
    if threads.is_empty() {
        return String::new();
    }
    let (w, h, left, top) = (640.0, 220.0, 48.0, 12.0);
    let span = threads.iter().flat_map(|t| [t.bias_before_um.abs(), t.bias_after_um.abs()]).fold(5.0, f64::max) * 1.15;
    let y = |v: f64| top + (h - 2.0 * top) / 2.0 * (1.0 - v / span);
    let slot = (w - left - 8.0) / threads.len() as f64;
    let mut s = format!(
        r##"<svg class="plot" id="bias-plot" viewBox="0 0 {w} {h}" width="{w}" height="{h}" role="img" aria-label="bias per thread before and after the correction"><line x1="{left}" x2="{w}" y1="{0:.1}" y2="{0:.1}" stroke="#888"/>"##,
        y(0.0)
    );
    for tick in [-span / 1.15, 0.0, span / 1.15] {
        let _ = write!(
            s,
            r##"<text x="{:.1}" y="{:.1}" text-anchor="end" class="tick">{tick:+.0} µm</text>"##,
            left - 4.0,
            y(tick) + 3.5
        );
    }
    for (i, t) in threads.iter().enumerate() {
        let x = left + i as f64 * slot;
        for (k, (v, colour)) in [(t.bias_before_um, "#999"), (t.bias_after_um, "#08519c")].into_iter().enumerate() {
            let (y0, y1) = (y(0.0).min(y(v)), y(0.0).max(y(v)));
            let _ = write!(
                s,
                r##"<rect x="{:.1}" y="{y0:.1}" width="{:.1}" height="{:.1}" fill="{colour}"><title>thread {} {}: {v:+.1} µm</title></rect>"##,
                x + slot * (0.15 + 0.35 * k as f64),
                slot * 0.33,
                (y1 - y0).max(0.5),
                t.thread,
                if k == 0 { "before" } else { "after" }
            );
        }
        let _ = write!(
            s,
            r##"<text x="{:.1}" y="{:.1}" text-anchor="middle" class="tick">{}</text>"##,
            x + slot / 2.0,
            h - 2.0,
            t.thread
        );
    }
    s.push_str("</svg>\n");
    s
}

pub fn station_page(p: &StationPage) -> String {
    let mut page = String::with_capacity(32 * 1024);
    let title = format!("crestscan station: {}", p.name);
    let _ = write!(
        page,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n<title>{0}</title>\n<style>\n{STYLE}</style>\n</head>\n<body>\n<main>\n<header id=\"summary\"><h1>{0}</h1>\n",
        escape(&title)
    );
    let _ = writeln!(
        page,
        r#"<p class="badges"><span class="badge station-{0}">{0}</span></p>{1}{2}</header>"#,
        escape(p.status),
        p.description.map(|d| format!("<p>{}</p>", escape(d))).unwrap_or_default(),
        p.status_reason.map(|r| format!("<p class=\"reason\">{}</p>", escape(r))).unwrap_or_default()
    );
    page.push_str("<section id=\"masters\"><h2>Masters</h2><table><thead><tr><th>serial</th><th>certificate</th><th>calibrated</th><th>U (k = 2)</th></tr></thead><tbody>");
    for (serial, instrument, at, u_um) in &p.masters {
        let _ = write!(
            page,
            "<tr><td>{}</td><td>{}</td><td>{}</td><td>{u_um:.1} µm</td></tr>",
            escape(serial),
            escape(instrument),
            escape(at)
        );
    }
    page.push_str("</tbody></table></section>\n");
    let Some(q) = p.qualification else {
        page.push_str("<p id=\"no-study\">No study yet: inspections at this station are decided as at any station.</p>\n</main>\n</body>\n</html>\n");
        return page;
    };
    let f = &q.fingerprint;
    let _ = write!(
        page,
        "<section id=\"fingerprint\"><h2>Fingerprint</h2><dl class=\"facts\"><dt>study</dt><dd>{}</dd><dt>projection</dt><dd>{:?}</dd><dt>object pixel</dt><dd>{:.1} µm</dd><dt>depth of field</dt><dd>{:.3} mm</dd><dt>frame step</dt><dd>{:.3} mm</dd><dt>views</dt><dd>{} in {} row(s)</dd><dt>overlap</dt><dd>{}</dd><dt>valid until</dt><dd>{}</dd></dl></section>\n",
        escape(&q.study),
        f.projection,
        1e3 * f.object_pixel_mm,
        f.depth_of_field_mm,
        f.frame_step_mm,
        f.views,
        f.axial_rows,
        f.overlap_deg.map_or("–".into(), |o| format!("{o:.1}°")),
        q.valid_until.as_deref().map(escape).unwrap_or_else(|| "until requalified".into())
    );
    let u = &q.uncertainty;
    let _ = write!(
        page,
        "<section id=\"uncertainty\"><h2>Uncertainty (ISO 15530-3)</h2><table><tbody><tr><th>u_cal</th><td>{:.2} µm</td></tr><tr><th>u_p (repeatability)</th><td>{:.2} µm</td></tr><tr><th>u_b (correction)</th><td>{:.2} µm</td></tr><tr><th>u_w (master to master)</th><td>{}</td></tr><tr><th>U (k = {})</th><td>{:.1} µm</td></tr></tbody></table><p>Heights against the certificates: {:.1} µm RMS before the correction, {:.1} µm after it ({}, model {}).</p></section>\n",
        u.u_cal_um,
        u.u_p_um,
        u.u_b_um,
        if u.u_w_measured { format!("{:.2} µm", u.u_w_um) } else { "not measured (one master)".into() },
        u.coverage_factor,
        u.expanded_um,
        q.rms_before_um,
        q.rms_after_um,
        escape(&q.selection.method.replace('_', " ")),
        q.correction.model.as_str()
    );
    let g = &q.gauge;
    let _ = write!(
        page,
        "<section id=\"gauge\"><h2>Gauge study</h2><p>Against the height tolerance band T = {:.0} µm: Cg min {}, Cgk min {}; %GRR {} of T, {} of the total variation, ndc {} ({} parts × {} repeats).</p>\n",
        g.tolerance_um,
        opt(g.cg_min, 2),
        opt(g.cgk_min, 2),
        opt(g.grr_percent_tolerance, 1),
        opt(g.grr_percent_total, 1),
        opt(g.ndc, 1),
        g.parts,
        g.repeats
    );
    page.push_str(&bias_plot(q));
    page.push_str("<table id=\"thread-gauge\"><thead><tr><th>master</th><th>thread</th><th>correction</th><th>bias before</th><th>bias after</th><th>repeatability</th><th>Cg</th><th>Cgk</th></tr></thead><tbody>");
    for t in &g.threads {
        let correction = q.correction.threads.iter().find(|c| c.thread == t.thread).map(|c| c.bias_um);
        let _ = write!(
            page,
            "<tr><td>{}</td><td>{}</td><td>{} µm</td><td>{:+.1} µm</td><td>{:+.1} µm</td><td>{:.1} µm</td><td>{}</td><td>{}</td></tr>",
            escape(&t.master),
            t.thread,
            opt(correction, 1),
            t.bias_before_um,
            t.bias_after_um,
            t.repeatability_um,
            opt(t.cg, 2),
            opt(t.cgk, 2)
        );
    }
    page.push_str("</tbody></table></section>\n</main>\n</body>\n</html>\n");
    page
}
