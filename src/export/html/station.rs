//! A station's page: its status, the fingerprint its study bound it to, the uncertainty
//! components, the correction per thread, and the gauge figures (bias before and after the
//! correction, repeatability, Cg/Cgk, %GRR, ndc), for the quality engineer who releases it.

use super::{STYLE, escape};
use crate::domain::control::{ChartPoint, ControlLimits, Violation};
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
    /// The check runs charted under the study in force, oldest first.
    pub checks: Vec<CheckLine<'a>>,
}

/// One check run on the page's control chart.
pub struct CheckLine<'a> {
    pub seq: i64,
    pub master: &'a str,
    pub inspection: &'a str,
    pub points: &'a [ChartPoint],
    pub violation: Option<&'a Violation>,
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

/// One chart (a master's statistic): its checks' z against the centre line and the 1σ, 2σ and 3σ
/// lines; a check that broke a rule drawn red. z beyond ±4.5 is drawn at the edge.
fn control_plot(limits: &ControlLimits, checks: &[CheckLine]) -> String {
    let (w, h, left, right, top) = (640.0, 180.0, 48.0, 12.0, 10.0);
    let zmax = 4.5;
    let y = |z: f64| top + (h - 2.0 * top) / 2.0 * (1.0 - z.clamp(-zmax, zmax) / zmax);
    let mine: Vec<(&CheckLine, &ChartPoint)> = checks
        .iter()
        .filter(|c| c.master == limits.master)
        .filter_map(|c| Some((c, c.points.iter().find(|p| p.statistic == limits.statistic)?)))
        .collect();
    let slot = (w - left - right) / (mine.len().max(10) as f64);
    let x = |i: usize| left + slot * (i as f64 + 0.5);
    let mut s = format!(
        r##"<svg class="plot control-plot" data-master="{}" data-statistic="{}" viewBox="0 0 {w} {h}" width="{w}" height="{h}" role="img" aria-label="control chart of master {}'s {}">"##,
        escape(&limits.master),
        limits.statistic.describe(),
        escape(&limits.master),
        limits.statistic.describe()
    );
    for (z, colour, dash) in [
        (0.0, "#555", ""),
        (1.0, "#bbb", " stroke-dasharray=\"2 3\""),
        (-1.0, "#bbb", " stroke-dasharray=\"2 3\""),
        (2.0, "#999", " stroke-dasharray=\"5 3\""),
        (-2.0, "#999", " stroke-dasharray=\"5 3\""),
        (3.0, "#b2182b", ""),
        (-3.0, "#b2182b", ""),
    ] {
        let _ = write!(
            s,
            r##"<line x1="{left}" x2="{x2:.1}" y1="{yz:.1}" y2="{yz:.1}" stroke="{colour}"{dash}/><text x="{tx:.1}" y="{ty:.1}" text-anchor="end" class="tick">{z:+.0}σ</text>"##,
            x2 = w - right,
            yz = y(z),
            tx = left - 4.0,
            ty = y(z) + 3.5
        );
    }
    let path: Vec<String> = mine.iter().enumerate().map(|(i, (_, p))| format!("{:.1},{:.1}", x(i), y(p.z))).collect();
    if path.len() >= 2 {
        let _ = write!(s, r##"<polyline fill="none" stroke="#08519c" points="{}"/>"##, path.join(" "));
    }
    for (i, (c, p)) in mine.iter().enumerate() {
        let broke = c.violation.is_some_and(|v| v.statistic == limits.statistic);
        let _ = write!(
            s,
            r##"<circle class="check{}" cx="{:.1}" cy="{:.1}" r="4" fill="{}"><title>check {}: {:.1} µm, {:+.2}σ{}</title></circle>"##,
            if broke { " violation" } else { "" },
            x(i),
            y(p.z),
            if broke { "#b2182b" } else { "#08519c" },
            c.seq,
            p.value_um,
            p.z,
            if broke { " (broke a rule)" } else { "" }
        );
    }
    s.push_str("</svg>\n");
    s
}

/// Which rules a chart is judged by, or why it is not.
fn judged_by(l: &ControlLimits) -> String {
    if !l.charted {
        return format!("shown only: {}", escape(l.not_charted_because.as_deref().unwrap_or("not charted")));
    }
    match l.rules.as_slice() {
        [1] => format!(
            "Western Electric rule 1 (limits from {} runs; rules 2–4 from {})",
            l.runs,
            crate::domain::control::SENSITIZING_MIN_RUNS
        ),
        rules => format!("Western Electric rules {}", rules.iter().map(u8::to_string).collect::<Vec<_>>().join(", ")),
    }
}

/// The control charts and the checks' table.
fn control_section(q: &Qualification, checks: &[CheckLine], station: &str) -> String {
    let mut s = String::from("<section id=\"control-chart\"><h2>Drift control</h2>\n");
    if q.control.is_empty() {
        s.push_str("<p>This study set no control limits (it was made before checks were charted): requalify to chart checks.</p></section>\n");
        return s;
    }
    s.push_str("<table id=\"control-limits\"><thead><tr><th>master</th><th>statistic</th><th>centre line</th><th>σ</th><th>runs</th><th>judged by</th></tr></thead><tbody>");
    for l in &q.control {
        let _ = write!(
            s,
            "<tr><td>{}</td><td>{}</td><td>{:.1} µm</td><td>{:.2} µm</td><td>{}</td><td>{}</td></tr>",
            escape(&l.master),
            l.statistic.describe(),
            l.center_um,
            l.sigma_um,
            l.runs,
            judged_by(l)
        );
    }
    s.push_str("</tbody></table>\n");
    if checks.is_empty() {
        let _ = writeln!(
            s,
            "<p id=\"no-checks\">No check runs yet: <code>POST /v1/stations/{}/checks</code> charts an inspection of a master.</p></section>",
            escape(station)
        );
        return s;
    }
    for l in &q.control {
        let _ = write!(s, "<h3>{} · {}</h3>\n", escape(&l.master), l.statistic.describe());
        s.push_str(&control_plot(l, checks));
    }
    s.push_str("<table id=\"checks\"><thead><tr><th>check</th><th>master</th><th>inspection</th><th>readings</th><th>rule broken</th></tr></thead><tbody>");
    for c in checks {
        let readings: Vec<String> = c
            .points
            .iter()
            .map(|p| format!("{} {:.1} µm ({:+.2}σ)", p.statistic.describe(), p.value_um, p.z))
            .collect();
        let _ = write!(
            s,
            "<tr{class}><td>{seq}</td><td>{master}</td><td><a href=\"/v1/inspections/{id}/report?format=html\">{id}</a></td><td>{readings}</td><td>{rule}</td></tr>",
            class = if c.violation.is_some() { " class=\"violation\"" } else { "" },
            seq = c.seq,
            master = escape(c.master),
            id = escape(c.inspection),
            readings = escape(&readings.join("; ")),
            rule = c.violation.map_or("–".into(), |v| escape(&v.description))
        );
    }
    s.push_str("</tbody></table></section>\n");
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
    page.push_str("</tbody></table></section>\n");
    page.push_str(&control_section(q, &p.checks, p.name));
    page.push_str("</main>\n</body>\n</html>\n");
    page
}
