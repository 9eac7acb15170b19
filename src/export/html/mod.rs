//! The inspection report as one self-contained HTML page (issue 30): the verdict and decision with
//! their reasons, the developed surface, each thread's heights with the tolerance and uncertainty
//! bands, the black-crest arcs against the limit, crestscan against the CMM where it measured the
//! part, the images and the mesh in 3D. Everything is inline (styles, SVG plots, PNGs as data URIs,
//! the scripts with their hashes in the page's Content-Security-Policy, three.js among them): a
//! factory network has no CDN, and the page loads nothing from anywhere but, in the service, the
//! inspection's own mesh.

pub mod station;
pub mod svg;

use crate::pipeline::report::Report;
use base64::Engine;
use std::fmt::Write;

/// The width the page's images are reduced to (`png::preview_png`): the ring's mosaic is about
/// 8800 pixels wide at the standard station, megabytes inlined.
pub const IMAGE_WIDTH_PX: u32 = 2400;

/// The most vertices of the mesh a self-contained page inlines for its 3D view (about 2 MB of
/// GLB; the files written beside it keep the full mesh).
pub const VIEWER_MAX_VERTICES: usize = 60_000;

/// What the page shows besides the report.
#[derive(Default)]
pub struct PageInputs<'a> {
    /// The service's inspection id (the CLI has none).
    pub inspection_id: Option<&'a str>,
    pub mosaic_png: Option<&'a [u8]>,
    pub height_map_png: Option<&'a [u8]>,
    pub cmm: Option<CmmPanel>,
    pub mesh: Option<MeshSource<'a>>,
    /// Why the images and the mesh are missing, where they are (the service's retention deleted
    /// them): said on the page instead of the sections.
    pub artifacts_missing: Option<String>,
    /// Where the full-resolution images are (mosaic, height map): the service's image endpoints,
    /// or the files written beside the page.
    pub full_images: Option<[String; 2]>,
}

/// Where the 3D viewer finds the mesh (GLB, with vertex colours).
pub enum MeshSource<'a> {
    /// A same-origin URL (the service's mesh endpoint).
    Url(String),
    /// The GLB itself, inlined in base64 (a self-contained file).
    Inline(&'a [u8]),
}

/// crestscan against the CMM, as the page draws it.
pub struct CmmPanel {
    pub instrument: Option<String>,
    /// (CMM height, crestscan height), mm, where both measured.
    pub points: Vec<(f64, f64)>,
    /// CMM points crestscan did not measure.
    pub unmatched: usize,
    pub bias_mm: Option<f64>,
    pub rms_mm: Option<f64>,
    pub limits_of_agreement_mm: Option<[f64; 2]>,
    pub tolerance_mm: f64,
    pub within_tolerance: bool,
}

/// Text for HTML element content and attribute values.
pub fn escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// A serde enum's wire name (`accept`, `does_not_conform`, …).
fn wire<T: serde::Serialize>(value: &T) -> String {
    serde_json::to_value(value).ok().and_then(|v| v.as_str().map(str::to_string)).unwrap_or_default()
}

const STYLE: &str = include_str!("report.css");
/// Click an image to see it at full size (and again to fit it to the page).
const SCRIPT: &str = "document.querySelectorAll('figure.zoom img').forEach(function (img) {\n  img.addEventListener('click', function () { img.classList.toggle('full'); });\n});\n";
/// The 3D viewer with three.js, one classic script (assets/viewer/build.sh).
const VIEWER: &str = include_str!("viewer.min.js");

/// An inline script's CSP source expression: `'sha256-…'` of its exact text.
pub fn script_hash(script: &str) -> String {
    use sha2::Digest;
    format!("'sha256-{}'", base64::engine::general_purpose::STANDARD.encode(sha2::Sha256::digest(script.as_bytes())))
}

/// The Content-Security-Policy the page needs: its own inline styles, images as data URIs, its two
/// scripts by hash, and fetching from its own origin (the service's mesh); nothing else. Hashed
/// once (the viewer is half a megabyte), not per page served.
pub fn content_security_policy() -> &'static str {
    static POLICY: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    POLICY.get_or_init(|| {
        format!(
            "default-src 'none'; style-src 'unsafe-inline'; img-src data:; script-src {} {}; connect-src 'self'; \
             frame-ancestors 'none'; base-uri 'none'; form-action 'none'",
            script_hash(SCRIPT),
            script_hash(VIEWER)
        )
    })
}

fn data_uri_png(bytes: &[u8]) -> String {
    format!("data:image/png;base64,{}", base64::engine::general_purpose::STANDARD.encode(bytes))
}

/// The whole page.
pub fn report_page(report: &Report, inputs: &PageInputs) -> String {
    let mut page = String::with_capacity(256 * 1024);
    let title = format!(
        "crestscan report{}{}",
        report.serial.as_deref().map(|s| format!(": {s}")).unwrap_or_default(),
        report.connection.as_deref().map(|c| format!(" ({c})")).unwrap_or_default()
    );
    let _ = write!(
        page,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n<title>{}</title>\n<style>\n{STYLE}</style>\n</head>\n<body>\n<main>\n",
        escape(&title)
    );
    header(&mut page, report, inputs, &title);
    surface(&mut page, report);
    heights(&mut page, report);
    table(&mut page, report);
    black_crests(&mut page, report);
    if let Some(cmm) = &inputs.cmm {
        cmm_section(&mut page, cmm);
    }
    images(&mut page, inputs);
    viewer(&mut page, inputs);
    provenance(&mut page, report, inputs);
    let _ = write!(page, "</main>\n<script>{SCRIPT}</script>\n");
    if inputs.mesh.is_some() {
        let _ = write!(page, "<script>{VIEWER}</script>\n");
    }
    page.push_str("</body>\n</html>\n");
    page
}

fn header(page: &mut String, r: &Report, inputs: &PageInputs, title: &str) {
    let verdict = wire(&r.verdict);
    let decision = wire(&r.decision);
    let _ = writeln!(page, r#"<header id="summary"><h1>{}</h1>"#, escape(title));
    let _ = writeln!(
        page,
        r#"<p class="badges"><span class="badge verdict-{verdict}">verdict: {verdict}</span> <span class="badge decision-{decision}">decision: {}</span> {}</p>"#,
        decision.replace('_', " "),
        if r.review_required {
            r#"<span class="badge review">review required</span>"#
        } else {
            r#"<span class="badge ok">no review needed</span>"#
        }
    );
    let mut facts = vec![
        ("connection", r.connection.clone().unwrap_or_else(|| "custom form".into())),
        ("family", wire(&r.family)),
        ("pipe OD", format!("{:.2} mm", r.pipe_od_mm)),
        ("Lc", format!("{:.2} mm", r.lc_mm)),
        ("nominal height", format!("{:.4} ± {:.4} mm", r.nominal_height_mm, r.height_tolerance_mm)),
        ("quality", wire(&r.quality.status)),
    ];
    if let Some(s) = &r.serial {
        facts.insert(0, ("serial", s.clone()));
    }
    if let Some(id) = inputs.inspection_id {
        facts.push(("inspection", id.to_string()));
    }
    page.push_str("<dl class=\"facts\">");
    for (k, v) in facts {
        let _ = write!(page, "<dt>{}</dt><dd>{}</dd>", escape(k), escape(&v));
    }
    page.push_str("</dl>\n");
    if let Some(q) = &r.qualification {
        // Served by the service, the station's name links to its page.
        let name = match inputs.inspection_id {
            Some(_) => format!(
                "<a href=\"/v1/stations/{}?format=html\">{}</a>",
                escape(&q.station.replace('%', "%25")),
                escape(&q.station)
            ),
            None => escape(&q.station),
        };
        let state = match (&q.study, &q.refused) {
            (Some(study), None) => format!(
                "qualified: study {}{}",
                escape(study),
                q.uncertainty.as_ref().map(|u| format!(", U = {:.1} µm (k = 2)", u.expanded_um)).unwrap_or_default()
            ),
            (_, Some(reason)) => format!("qualification not applied: {}", escape(reason)),
            _ => "unqualified".into(),
        };
        let _ = writeln!(page, r#"<p class="station-link" id="station">Station {name}, {state}</p>"#);
    }
    page.push_str("<h2>API 5B</h2><ul class=\"reasons\">");
    for reason in &r.assessment.reasons {
        let figures = match (reason.value, reason.limit) {
            (Some(v), Some(l)) => {
                format!(
                    " <span class=\"figures\">({v:.3} against {l:.3} {})</span>",
                    escape(reason.unit.as_deref().unwrap_or(""))
                )
            }
            _ => String::new(),
        };
        let _ = write!(page, "<li>{}{figures}</li>", escape(&reason.message));
    }
    page.push_str("</ul>\n");
    let mut review: Vec<String> =
        r.quality.reasons.iter().map(|q| format!("{} ({})", q.message, wire(&q.code))).collect();
    if let Some(f) = &r.decision_finding {
        review.extend(f.reasons.iter().cloned());
    }
    if !review.is_empty() {
        page.push_str("<h2>Why review</h2><ul class=\"review\">");
        for line in review {
            let _ = write!(page, "<li>{}</li>", escape(&line));
        }
        page.push_str("</ul>\n");
    }
    if let Some(st) = &r.station {
        let _ = writeln!(
            page,
            "<p class=\"station\">Station{}: {} projection, object pixel {:.1} µm, depth of field {:.3} mm, frames every {:.3} mm ({:.2} DOF), {} views in {} row(s){}{}.</p>",
            // Reports stored before classes were have none: their station is classed again.
            match st.class.or_else(|| st.clone().with_frame_noise(st.frame_noise_percent).class) {
                Some(class) => format!(" (class {})", class.as_str()),
                None => " (in no class of the declared envelope)".into(),
            },
            wire(&st.projection),
            1e3 * st.object_pixel_mm,
            st.depth_of_field_mm,
            st.frame_step_mm,
            st.frame_step_dof,
            st.views,
            st.axial_rows,
            st.overlap_deg.map(|o| format!(", overlaps {o:.1}°")).unwrap_or_default(),
            st.frame_noise_percent.map(|n| format!(", frame noise {n:.2}%")).unwrap_or_default()
        );
    }
    let total: f64 = r.timings.iter().filter(|t| !t.is_part()).map(|t| t.seconds).sum();
    let stages: Vec<String> = r.timings.iter().map(|t| format!("{} {:.2} s", t.stage, t.seconds)).collect();
    let _ = writeln!(
        page,
        "<p class=\"timing\">Timing: {total:.2} s in all ({}); registration measured {} of {} overlaps; the fused map covers {:.1}% of the surface.</p></header>",
        escape(&stages.join(", ")),
        r.registration.pairs_measured,
        r.registration.pairs_expected,
        100.0 * r.map_coverage
    );
}

fn surface(page: &mut String, r: &Report) {
    page.push_str("<section id=\"surface\"><h2>Developed surface</h2>\n<p class=\"note\">Each 1° bin's height against nominal, thread by thread around the circumference: white is nominal, the scale saturates at twice the tolerance. Black outlines: black-crest arcs; dashed purple: Lc; shaded rows: the chamfer zone (1.5 pitches from the end face); hatched: not measured.</p>\n");
    page.push_str(&svg::developed_surface(r));
    page.push_str("</section>\n");
}

fn heights(page: &mut String, r: &Report) {
    page.push_str("<section id=\"heights\"><h2>Heights along each thread</h2>\n<p class=\"note\">Green: nominal ± tolerance; blue band: each height ± its expanded uncertainty (k = 2); black ticks: black crests.</p>\n<div class=\"small-multiples\">\n");
    for t in &r.threads {
        let _ = write!(page, "<figure><figcaption>thread {}</figcaption>", t.index);
        page.push_str(&svg::thread_heights(r, t));
        page.push_str("</figure>\n");
    }
    page.push_str("</div></section>\n");
}

fn table(page: &mut String, r: &Report) {
    let limit = match r.assessment.arc_limit_mm {
        Some(mm) => format!("{mm:.1} mm (25%)"),
        None => "none: any black crest within Lc".to_string(),
    };
    page.push_str("<section id=\"threads-table\"><h2>Per thread</h2>\n<table><thead><tr><th>thread</th><th>crest z, mm</th><th>within Lc</th><th>bins</th><th>mean, mm</th><th>min, mm</th><th>max, mm</th><th>black crest, mm</th><th>limit</th><th>height finding</th></tr></thead><tbody>\n");
    let mm = |v: Option<f64>| v.map_or("–".to_string(), |v| format!("{v:.4}"));
    for t in &r.threads {
        let within = if t.crest_z_mm[1] <= r.lc_mm {
            "yes"
        } else if t.crest_z_mm[0] < r.lc_mm {
            "partly"
        } else {
            "no"
        };
        let finding = t.height_finding.as_ref().map_or("–".to_string(), |f| {
            format!(
                "{}{}",
                wire(&f.finding).replace('_', " "),
                match (f.mean_height_mm, f.uncertainty_mm) {
                    (Some(m), Some(u)) => format!(" ({m:.4} ± {u:.4})"),
                    _ => String::new(),
                }
            )
        });
        // Why the rest have none, in small print under the count.
        let why: Vec<String> =
            t.unmeasured_bins.iter().map(|c| format!("{} {}", c.reason.as_str().replace('_', " "), c.bins)).collect();
        let bins = if why.is_empty() {
            t.bins_measured.to_string()
        } else {
            format!("{}<br><small>without: {}</small>", t.bins_measured, escape(&why.join(", ")))
        };
        let _ = writeln!(
            page,
            "<tr><td>{}</td><td>{:.2}–{:.2}</td><td>{within}</td><td>{bins}</td><td>{}</td><td>{}</td><td>{}</td><td>{:.2}</td><td>{}</td><td>{}</td></tr>",
            t.index,
            t.crest_z_mm[0],
            t.crest_z_mm[1],
            mm(t.mean_height_mm),
            mm(t.min_height_mm),
            mm(t.max_height_mm),
            t.black_crest_length_mm,
            escape(&limit),
            escape(&finding)
        );
    }
    page.push_str("</tbody></table></section>\n");
}

fn black_crests(page: &mut String, r: &Report) {
    page.push_str("<section id=\"black-crests\"><h2>Black crests</h2>\n");
    let limit_fraction = r.assessment.arc_limit_mm.map(|mm| mm / r.circumference_mm.max(1e-9));
    let black: Vec<_> = r.threads.iter().filter(|t| !t.black_crest_arcs_deg.is_empty()).collect();
    if black.is_empty() {
        page.push_str("<p>No black crest was found on any measured thread.</p>\n");
    } else {
        let _ = writeln!(
            page,
            "<p class=\"note\">Each thread with a black crest, its arcs drawn on its circle (0° at the top, clockwise){}.</p><div class=\"small-multiples\">",
            if limit_fraction.is_some() {
                "; orange: the 25% of the circumference a buttress thread may show, for scale"
            } else {
                "; a round thread may show none within Lc"
            }
        );
        for t in black {
            page.push_str(&svg::black_arcs_polar(t.index, &t.black_crest_arcs_deg, limit_fraction));
        }
        page.push_str("</div>\n");
    }
    page.push_str("</section>\n");
}

fn cmm_section(page: &mut String, cmm: &CmmPanel) {
    let um = |v: Option<f64>| v.map_or("–".to_string(), |v| format!("{:+.1} µm", 1e3 * v));
    let _ = writeln!(
        page,
        "<section id=\"cmm\"><h2>Against the CMM{}</h2><p>{} points compared ({} the CMM measured and crestscan did not); bias {}, RMS {}, limits of agreement {}; {} the ±{:.1} µm agreement tolerance.</p><div class=\"small-multiples\">",
        cmm.instrument.as_deref().map(|i| format!(" ({})", escape(i))).unwrap_or_default(),
        cmm.points.len(),
        cmm.unmatched,
        um(cmm.bias_mm),
        cmm.rms_mm.map_or("–".to_string(), |v| format!("{:.1} µm", 1e3 * v)),
        cmm.limits_of_agreement_mm.map_or("–".to_string(), |[a, b]| format!("{:+.1} to {:+.1} µm", 1e3 * a, 1e3 * b)),
        if cmm.within_tolerance { "within" } else { "not within" },
        1e3 * cmm.tolerance_mm
    );
    page.push_str(&svg::cmm_plots(&cmm.points, cmm.bias_mm, cmm.limits_of_agreement_mm));
    page.push_str("</div></section>\n");
}

fn images(page: &mut String, inputs: &PageInputs) {
    if let Some(why) = &inputs.artifacts_missing {
        let _ = writeln!(
            page,
            "<section id=\"images\"><h2>Images and the surface in 3D</h2><p class=\"note\">{}</p></section>",
            escape(why)
        );
        return;
    }
    if inputs.mosaic_png.is_none() && inputs.height_map_png.is_none() {
        return;
    }
    let _ = writeln!(
        page,
        "<section id=\"images\"><h2>Images</h2><p class=\"note\">The unrolled surface, angle across and z down, \
         reduced to {IMAGE_WIDTH_PX} pixels wide: click an image to see it at that size.</p>"
    );
    let links = inputs.full_images.as_ref();
    for (i, (caption, png)) in
        [("All-in-focus mosaic", inputs.mosaic_png), ("Height map", inputs.height_map_png)].into_iter().enumerate()
    {
        if let Some(png) = png {
            let full =
                links.map(|l| format!(" (<a href=\"{}\">full resolution</a>)", escape(&l[i]))).unwrap_or_default();
            let _ = writeln!(
                page,
                "<figure class=\"zoom\"><figcaption>{caption}{full}</figcaption><img alt=\"{caption}\" src=\"{}\"></figure>",
                data_uri_png(png)
            );
        }
    }
    page.push_str("</section>\n");
}

fn viewer(page: &mut String, inputs: &PageInputs) {
    let Some(mesh) = &inputs.mesh else { return };
    page.push_str("<section id=\"viewer\"><h2>The surface in 3D</h2>\n");
    let source = match mesh {
        MeshSource::Url(url) => format!("data-glb-url=\"{}\"", escape(url)),
        MeshSource::Inline(glb) => {
            let _ = writeln!(
                page,
                "<script type=\"application/octet-stream\" id=\"mesh-glb\">{}</script>",
                base64::engine::general_purpose::STANDARD.encode(glb)
            );
            "data-glb-element=\"mesh-glb\"".to_string()
        }
    };
    let _ = writeln!(
        page,
        "<div class=\"viewer\" {source}><p class=\"viewer-status note\">The 3D view needs JavaScript and WebGL.</p><button type=\"button\" class=\"viewer-reset\">Reset view</button></div></section>"
    );
}

fn provenance(page: &mut String, r: &Report, inputs: &PageInputs) {
    page.push_str("<footer id=\"provenance\"><h2>Provenance</h2><dl class=\"facts\">");
    let mut rows: Vec<(&str, String)> = Vec::new();
    if let Some(p) = &r.provenance {
        rows.push(("software", format!("crestscan {}", p.software_version)));
        if let Some(sha) = &p.bundle_sha256 {
            rows.push(("bundle sha256", sha.clone()));
        }
        rows.push((
            "learned models",
            match p.models.as_slice() {
                [] => "none: the classical pipeline".to_string(),
                models => models
                    .iter()
                    .map(|m| format!("{} {} ({}, sha256 {})", m.role.as_str(), m.name, m.source.as_str(), m.sha256))
                    .collect::<Vec<_>>()
                    .join("; "),
            },
        ));
    }
    if let Some(id) = inputs.inspection_id {
        rows.push(("inspection", id.to_string()));
    }
    if let Some(u) = &r.uncertainty {
        rows.push((
            "uncertainty",
            format!(
                "k = {}; median U {}; method {:.1} µm, registration {:.1} µm{}",
                u.coverage_factor,
                u.expanded_median_um.map_or("–".to_string(), |v| format!("{v:.1} µm")),
                u.method_um,
                u.registration_um,
                if u.along_helix_um > 0.0 || u.from_nominal_um > 0.0 || !u.from_nominal_by_thread.is_empty() {
                    let widest = u.from_nominal_by_thread.iter().map(|t| t.um).fold(u.from_nominal_um, f64::max);
                    format!(
                        ", along the helix {:.1} µm, from nominal {:.1} µm (the part; up to {:.1} µm on a thread), {} \
                         height(s) on or beside black crests left out of these two",
                        u.along_helix_um, u.from_nominal_um, widest, u.black_crest_bins_left_out
                    )
                } else {
                    String::new()
                }
            ),
        ));
    }
    for (k, v) in rows {
        let _ = write!(page, "<dt>{}</dt><dd>{}</dd>", escape(k), escape(&v));
    }
    page.push_str("</dl></footer>\n");
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_is_escaped_for_content_and_attributes() {
        assert_eq!(escape(r#"<a href="x">Tom's & co</a>"#), "&lt;a href=&quot;x&quot;&gt;Tom&#39;s &amp; co&lt;/a&gt;");
    }

    #[test]
    fn the_policy_allows_the_page_scripts_by_their_hashes_and_nothing_from_elsewhere() {
        use sha2::Digest;
        let csp = content_security_policy();
        for script in [SCRIPT, VIEWER] {
            let hash = base64::engine::general_purpose::STANDARD.encode(sha2::Sha256::digest(script.as_bytes()));
            assert!(csp.contains(&format!("'sha256-{hash}'")), "{csp}");
        }
        assert!(csp.starts_with("default-src 'none'") && csp.contains("connect-src 'self'"));
        assert!(!csp.contains("http") && !csp.contains("unsafe-eval"));
    }
}
