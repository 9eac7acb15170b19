//! The layer rule, read from the sources (docs/architecture.md): each layer of the library imports
//! only the layers above it, nothing below the service imports axum, sqlx or tokio, and the
//! pipeline's stages import one another without a cycle. Run alone: `cargo test --test it layers`.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The library's layers in order, each with the layers it may import.
const LAYERS: &[(&str, &[&str])] = &[
    ("problem", &[]),
    ("numeric", &["problem"]),
    ("domain", &["problem", "numeric"]),
    // The learned models' runtime and registry: below the pipeline, which runs them.
    ("learned", &["problem", "numeric", "domain"]),
    ("bundle", &["problem", "numeric", "domain"]),
    ("pipeline", &["problem", "numeric", "domain", "learned"]),
    // The simulator writes the contract's manifest.
    ("sim", &["problem", "numeric", "domain", "bundle"]),
    ("export", &["problem", "numeric", "domain", "learned", "pipeline"]),
    ("eval", &["problem", "numeric", "domain", "learned", "bundle", "pipeline", "sim", "export"]),
    ("service", &["problem", "numeric", "domain", "learned", "bundle", "pipeline", "sim", "export", "eval"]),
];

/// Crates only the service may use.
const SERVICE_CRATES: &[&str] = &["axum", "sqlx", "tokio", "tower", "tower_http", "hyper", "utoipa_axum"];

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The source without comments (doc comments name other modules in links, which is no import).
fn strip_comments(text: &str) -> String {
    text.lines()
        .map(|l| match l.find("//") {
            Some(i) if !l[..i].contains('"') => &l[..i],
            _ => l,
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// Every path `crate::a::b…` the code names, as its segments (grouped imports expanded one
/// level: `crate::a::{b, c::d}` names `a::b` and `a::c::d`).
fn crate_paths(code: &str) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let mut rest = code;
    while let Some(i) = rest.find("crate::") {
        let after = &rest[i + "crate::".len()..];
        let is_word_start = i == 0 || !rest[..i].ends_with(|c: char| c.is_alphanumeric() || c == '_');
        rest = after;
        if !is_word_start {
            continue;
        }
        let head: String = after.chars().take_while(|c| c.is_alphanumeric() || *c == '_' || *c == ':').collect();
        let segments: Vec<String> = head.split("::").filter(|s| !s.is_empty()).map(String::from).collect();
        if after[head.len()..].starts_with('{') {
            let group = &after[head.len() + 1..after.find('}').unwrap_or(after.len())];
            for item in group.split(',') {
                let mut path = segments.clone();
                path.extend(item.trim().split("::").filter(|s| !s.is_empty() && *s != "self").map(String::from));
                out.push(path);
            }
        } else {
            out.push(segments);
        }
    }
    out
}

/// The file's place: its layer, and for the pipeline the stage it belongs to.
fn place_of(src: &Path, file: &Path) -> (String, Option<String>) {
    let relative = file.strip_prefix(src).unwrap();
    let parts: Vec<String> = relative.iter().map(|p| p.to_string_lossy().trim_end_matches(".rs").to_string()).collect();
    let layer = parts[0].clone();
    let stage = (layer == "pipeline" && parts.len() > 1 && parts[1] != "mod").then(|| parts[1].clone());
    (layer, stage)
}

#[test]
fn layers_import_only_the_layers_above_them_and_stages_form_no_cycle() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    files.sort();
    let allowed: BTreeMap<&str, &[&str]> = LAYERS.iter().copied().collect();
    let mut violations = Vec::new();
    let mut stage_edges: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    let mut layers_seen = BTreeSet::new();
    let stages = stages_of(&src);
    for file in &files {
        let (layer, stage) = place_of(&src, file);
        let Some(may_import) = allowed.get(layer.as_str()) else { continue };
        layers_seen.insert(layer.clone());
        let code = strip_comments(&std::fs::read_to_string(file).unwrap());
        for path in crate_paths(&code) {
            let Some(target) = path.first() else { continue };
            if *target != layer && !may_import.contains(&target.as_str()) {
                violations.push(format!("{}: imports crate::{}", file.display(), path.join("::")));
            }
            if let (Some(from), true) = (&stage, target == "pipeline") {
                if let Some(to) = path.get(1).filter(|to| *to != from && stages.contains(*to)) {
                    stage_edges.entry(from.clone()).or_default().insert(to.clone());
                }
            }
        }
        if layer != "service" {
            for krate in SERVICE_CRATES {
                let uses = code.contains(&format!("{krate}::")) || code.contains(&format!("use {krate}"));
                if uses {
                    violations.push(format!("{}: uses {krate}, which only the service may", file.display()));
                }
            }
        }
    }
    assert!(violations.is_empty(), "the layer rule is broken:\n{}", violations.join("\n"));
    // Every layer holds code: a renamed folder would otherwise pass unseen.
    for (layer, _) in LAYERS {
        assert!(layers_seen.contains(*layer), "no sources found for the layer {layer}");
    }
    // The stages' import graph is acyclic: depth-first search for a back edge.
    fn visit<'a>(
        node: &'a str,
        edges: &'a BTreeMap<String, BTreeSet<String>>,
        state: &mut BTreeMap<&'a str, bool>,
        path: &mut Vec<&'a str>,
    ) -> Option<String> {
        match state.get(node) {
            Some(true) => return None,
            Some(false) => return Some(format!("{} → {node}", path.join(" → "))),
            None => {}
        }
        state.insert(node, false);
        path.push(node);
        for next in edges.get(node).into_iter().flatten() {
            if let Some(cycle) = visit(next, edges, state, path) {
                return Some(cycle);
            }
        }
        path.pop();
        state.insert(node, true);
        None
    }
    let mut state = BTreeMap::new();
    for node in stage_edges.keys() {
        if let Some(cycle) = visit(node, &stage_edges, &mut state, &mut Vec::new()) {
            panic!("the pipeline's stages import each other in a cycle: {cycle}");
        }
    }
    assert!(stage_edges.contains_key("cloud"), "the stage graph was read (cloud imports depth): {stage_edges:?}");
}

/// The pipeline's stages: its files and folders.
fn stages_of(src: &Path) -> BTreeSet<String> {
    std::fs::read_dir(src.join("pipeline"))
        .unwrap()
        .map(|e| e.unwrap().path().file_stem().unwrap().to_string_lossy().to_string())
        .filter(|s| s != "mod")
        .collect()
}

#[test]
fn the_import_reader_expands_groups_and_skips_comments() {
    let code = strip_comments(
        "use crate::pipeline::{depth::DepthMap, self};\n/// see [`crate::service`]\nlet x = crate::sim::x; // crate::eval",
    );
    let paths = crate_paths(&code);
    assert_eq!(paths, vec![vec!["pipeline", "depth", "DepthMap"], vec!["pipeline"], vec!["sim", "x"]]);
}
