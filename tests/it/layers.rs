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
    // The stages' graph, checked by the same circle finder as the whole crate's.
    let stage_graph: BTreeMap<Vec<String>, BTreeSet<Vec<String>>> = stage_edges
        .iter()
        .map(|(from, to)| (vec![from.clone()], to.iter().map(|t| vec![t.clone()]).collect()))
        .collect();
    if let Some(cycle) = find_cycle(&stage_graph) {
        panic!("the pipeline's stages import each other in a cycle: {cycle}");
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

/// One source file as the import graph sees it: its module path (`service::api::cmm`; a `mod.rs`
/// is its folder's module), the child modules it declares, and its code without comments and
/// without its inline test modules (a test's `use super::*` is no import of the file).
struct SourceFile {
    module: Vec<String>,
    children: BTreeSet<String>,
    /// `pub use` re-exports: a name this module shows, and the path (from the crate root) of
    /// what it is, so that `crate::pipeline::PipelineOptions` is an import of `pipeline::options`.
    reexports: BTreeMap<String, Vec<String>>,
    code: String,
}

impl SourceFile {
    fn new(relative: &Path, text: &str) -> Self {
        let mut module: Vec<String> =
            relative.iter().map(|p| p.to_string_lossy().trim_end_matches(".rs").to_string()).collect();
        if matches!(module.last().map(String::as_str), Some("mod" | "lib" | "main")) {
            module.pop();
        }
        let mut code = strip_comments(text);
        // The inline test module (`#[cfg(test)]`, then `mod tests {` or `pub(crate) mod tests {`).
        let test_module = code.match_indices("#[cfg(test)]\n").map(|(i, m)| i + m.len()).find(|&after| {
            let next = code[after..].lines().next().unwrap_or("").trim();
            next.contains("mod ") && next.ends_with('{')
        });
        if let Some(after) = test_module {
            code.truncate(after - "#[cfg(test)]\n".len());
        }
        let children = code
            .lines()
            .filter_map(|l| {
                let l = l.trim();
                let rest = l.strip_prefix("pub mod ").or_else(|| l.strip_prefix("mod "))?;
                rest.strip_suffix(';').map(str::to_string)
            })
            .collect();
        let mut reexports = BTreeMap::new();
        for line in code.lines() {
            let Some(rest) = line.trim().strip_prefix("pub use ") else { continue };
            let rest = rest.trim_end_matches(';');
            let (base, names): (&str, Vec<&str>) = match rest.split_once("::{") {
                Some((base, group)) => (base, group.trim_end_matches('}').split(',').map(str::trim).collect()),
                None => match rest.rsplit_once("::") {
                    Some((base, name)) => (base, vec![name]),
                    None => continue,
                },
            };
            let mut origin: Vec<String> = if let Some(from_root) = base.strip_prefix("crate::") {
                from_root.split("::").map(String::from).collect()
            } else {
                let mut path = module.clone();
                path.extend(base.split("::").map(String::from));
                path
            };
            origin.retain(|s| s != "self");
            for name in names.into_iter().filter(|n| !n.is_empty() && *n != "self") {
                let shown = name.rsplit(" as ").next().unwrap_or(name).trim().to_string();
                let mut target = origin.clone();
                target.extend(name.split(" as ").next().unwrap_or(name).split("::").map(|s| s.trim().to_string()));
                reexports.insert(shown, target);
            }
        }
        Self { module, children, reexports, code }
    }
}

/// The modules each file imports, by the modules' paths: `crate::a::b::X` and `super::…` /
/// `self::…` paths, and paths through a child module the file declares (`cmm::router()`),
/// resolved to the longest prefix that is a module of the crate. A parent's `pub use child::…`
/// re-export is the module's face, not an import.
fn import_graph(files: &[SourceFile]) -> BTreeMap<Vec<String>, BTreeSet<Vec<String>>> {
    let modules: BTreeSet<Vec<String>> = files.iter().map(|f| f.module.clone()).collect();
    let reexports: BTreeMap<&Vec<String>, &BTreeMap<String, Vec<String>>> =
        files.iter().map(|f| (&f.module, &f.reexports)).collect();
    // The module a path names: its longest prefix that is a module, followed through that
    // module's re-export of the next segment (a few times: re-exports may chain).
    let resolve = |path: Vec<String>| -> Option<Vec<String>> {
        let mut path = path;
        for _ in 0..4 {
            let n = (1..=path.len()).rev().find(|&n| modules.contains(&path[..n].to_vec()))?;
            let module = path[..n].to_vec();
            match path.get(n).and_then(|next| reexports.get(&module).and_then(|r| r.get(next))) {
                Some(origin) if origin.len() > 1 => path = origin.clone(),
                _ => return Some(module),
            }
        }
        (1..=path.len()).rev().map(|n| path[..n].to_vec()).find(|p| modules.contains(p))
    };
    let mut graph = BTreeMap::new();
    for file in files {
        let mut edges = BTreeSet::new();
        let parent: Vec<String> = file.module[..file.module.len().saturating_sub(1)].to_vec();
        for line in file.code.lines() {
            let trimmed = line.trim_start();
            let face = trimmed.starts_with("pub use ")
                && file.children.iter().any(|c| trimmed["pub use ".len()..].starts_with(&format!("{c}::")));
            if face {
                continue;
            }
            for path in crate_paths(line) {
                edges.extend(resolve(path));
            }
            for (prefix, base) in [("super::", parent.clone()), ("self::", file.module.clone())] {
                for (i, _) in line.match_indices(prefix) {
                    if i > 0 && line[..i].ends_with(|c: char| c.is_alphanumeric() || c == '_' || c == ':') {
                        continue;
                    }
                    let mut after = &line[i + prefix.len()..];
                    let mut path = base.clone();
                    // `super::super::…` climbs once a segment.
                    while let Some(rest) = after.strip_prefix("super::") {
                        path.pop();
                        after = rest;
                    }
                    let head: String =
                        after.chars().take_while(|c| c.is_alphanumeric() || *c == '_' || *c == ':').collect();
                    path.extend(head.split("::").filter(|s| !s.is_empty()).map(String::from));
                    edges.extend(resolve(path));
                }
            }
            for child in &file.children {
                let needle = format!("{child}::");
                for (i, _) in line.match_indices(&needle) {
                    if i > 0 && line[..i].ends_with(|c: char| c.is_alphanumeric() || c == '_' || c == ':') {
                        continue;
                    }
                    let mut path = file.module.clone();
                    path.push(child.clone());
                    edges.extend(resolve(path));
                }
            }
        }
        edges.remove(&file.module);
        // A folder's module and its own files are one unit: the children see the parent's items
        // (Rust's privacy is built so) and the parent composes the children. Circles between
        // them are the module's inside; every other circle is one.
        edges.retain(|to| !(is_parent(to, &file.module) || is_parent(&file.module, to)));
        graph.insert(file.module.clone(), edges);
    }
    graph
}

/// Whether `parent` is `child`'s module one level up.
fn is_parent(parent: &[String], child: &[String]) -> bool {
    child.len() == parent.len() + 1 && child.starts_with(parent)
}

/// A cycle of the graph, as `a → b → a`, if there is one.
fn find_cycle(graph: &BTreeMap<Vec<String>, BTreeSet<Vec<String>>>) -> Option<String> {
    fn visit<'a>(
        node: &'a Vec<String>,
        graph: &'a BTreeMap<Vec<String>, BTreeSet<Vec<String>>>,
        done: &mut BTreeMap<&'a Vec<String>, bool>,
        path: &mut Vec<&'a Vec<String>>,
    ) -> Option<String> {
        match done.get(node) {
            Some(true) => return None,
            Some(false) => {
                let start = path.iter().position(|p| *p == node).unwrap_or(0);
                let mut names: Vec<String> = path[start..].iter().map(|m| m.join("::")).collect();
                names.push(node.join("::"));
                return Some(names.join(" → "));
            }
            None => {}
        }
        done.insert(node, false);
        path.push(node);
        for next in graph.get(node).into_iter().flatten() {
            if let Some(cycle) = visit(next, graph, done, path) {
                return Some(cycle);
            }
        }
        path.pop();
        done.insert(node, true);
        None
    }
    let mut done = BTreeMap::new();
    graph.keys().find_map(|node| visit(node, graph, &mut done, &mut Vec::new()))
}

/// The library's and the binary's source files (each its own crate: `crate::` in `cli/` is the
/// binary's), read for [`import_graph`].
fn crate_files(src: &Path, binary: bool) -> Vec<SourceFile> {
    let mut paths = Vec::new();
    rust_files(src, &mut paths);
    paths.sort();
    paths
        .iter()
        .filter(|p| {
            let relative = p.strip_prefix(src).unwrap();
            let in_binary = relative.starts_with("cli") || relative == Path::new("main.rs");
            in_binary == binary
        })
        .map(|p| SourceFile::new(p.strip_prefix(src).unwrap(), &std::fs::read_to_string(p).unwrap()))
        .collect()
}

/// Issue 49: no file imports, through others, a file that imports it, anywhere in the crate (the
/// service had a circle of 12 files that nothing caught).
#[test]
fn no_file_of_the_crate_imports_itself_through_others() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    for binary in [false, true] {
        let files = crate_files(&src, binary);
        let graph = import_graph(&files);
        assert!(graph.len() > if binary { 10 } else { 100 }, "the files were read: {}", graph.len());
        let edges: usize = graph.values().map(BTreeSet::len).sum();
        // The binary's files import the library (`crestscan::…`) and their parent, rarely each other.
        assert!(edges > if binary { 0 } else { graph.len() }, "the imports were read: {edges} edges");
        if let Some(cycle) = find_cycle(&graph) {
            panic!("an import circle: {cycle}");
        }
    }
}

/// The circle check finds a planted circle, through `crate::`, `super::` and a child module, and
/// leaves a parent's re-export of its child alone.
#[test]
fn the_circle_check_finds_a_planted_circle() {
    let file = |path: &str, code: &str| SourceFile::new(Path::new(path), code);
    // config takes `router` from api, which re-exports it from cmm; cmm takes config's settings.
    let planted = [
        file("service/mod.rs", "pub mod api;\npub mod config;\n"),
        file("service/config.rs", "use crate::service::api::router;\n"),
        file("service/api/mod.rs", "pub mod cmm;\npub use cmm::router;\nfn f() { cmm::router(); }\n"),
        file("service/api/cmm.rs", "use super::super::config::Settings;\n"),
    ];
    let cycle = find_cycle(&import_graph(&planted)).expect("the planted circle");
    assert!(cycle.contains("service::config") && cycle.contains("service::api::cmm"), "{cycle}");
    let clean = [
        file("service/mod.rs", "pub mod api;\n"),
        file("service/api/mod.rs", "pub mod cmm;\npub use cmm::router;\n"),
        file("service/api/cmm.rs", "use super::AppState;\n#[cfg(test)]\nmod tests {\n use super::*;\n}\n"),
    ];
    assert_eq!(find_cycle(&import_graph(&clean)), None);
}
