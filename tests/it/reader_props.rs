//! Property tests for the bundle reader: hostile input gives an error, never a panic, and accepted
//! paths never leave the bundle.

use crate::common::{Scratch, walk};
use crestscan::bundle::{Bundle, OpenOptions, check_relative_path, parse_manifest};
use crestscan::domain::thread::ConnectionTable;
use proptest::prelude::*;
use std::io::Write;
use std::sync::OnceLock;

fn valid_manifest() -> &'static serde_json::Value {
    static M: OnceLock<serde_json::Value> = OnceLock::new();
    M.get_or_init(|| Scratch::new().manifest())
}

/// A zip of the ci bundle, built once.
fn zipped_ci() -> &'static Vec<u8> {
    static Z: OnceLock<Vec<u8>> = OnceLock::new();
    Z.get_or_init(|| {
        let s = Scratch::new();
        let mut bytes = Vec::new();
        {
            let mut zip = zip::ZipWriter::new(std::io::Cursor::new(&mut bytes));
            let options = zip::write::SimpleFileOptions::default();
            for path in walk(s.path()) {
                let rel = path.strip_prefix(s.path()).unwrap().to_string_lossy().into_owned();
                zip.start_file(rel, options).unwrap();
                zip.write_all(&std::fs::read(&path).unwrap()).unwrap();
            }
            zip.finish().unwrap();
        }
        bytes
    })
}

fn json_leaf() -> impl Strategy<Value = serde_json::Value> {
    prop_oneof![
        Just(serde_json::Value::Null),
        any::<bool>().prop_map(serde_json::Value::from),
        any::<f64>()
            .prop_map(|f| serde_json::Number::from_f64(f).map_or(serde_json::Value::Null, serde_json::Value::Number)),
        any::<i64>().prop_map(serde_json::Value::from),
        ".{0,12}".prop_map(serde_json::Value::from),
        Just(serde_json::json!([])),
        Just(serde_json::json!({})),
    ]
}

/// Replaces the value at a pseudo-random path (chosen by `choices`) with `leaf`.
fn mutate(value: &mut serde_json::Value, choices: &[usize], leaf: serde_json::Value) {
    let Some((&c, rest)) = choices.split_first() else {
        *value = leaf;
        return;
    };
    match value {
        serde_json::Value::Object(map) if !map.is_empty() => {
            let key = map.keys().nth(c % map.len()).unwrap().clone();
            mutate(map.get_mut(&key).unwrap(), rest, leaf);
        }
        serde_json::Value::Array(items) if !items.is_empty() => {
            let i = c % items.len();
            mutate(&mut items[i], rest, leaf);
        }
        _ => *value = leaf,
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn manifest_parser_never_panics_on_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
        let _ = parse_manifest(&bytes);
    }

    #[test]
    fn mutated_manifests_are_refused_by_field_or_parsed(
        choices in proptest::collection::vec(any::<usize>(), 1..6),
        leaf in json_leaf(),
    ) {
        let mut m = valid_manifest().clone();
        mutate(&mut m, &choices, leaf);
        if let Err(e) = parse_manifest(&serde_json::to_vec(&m).unwrap()) {
            let message = e.to_string();
            prop_assert!(message.starts_with("manifest.json: "), "{}", message);
        }
    }

    #[test]
    fn accepted_paths_stay_inside(path in "[a-z./\\\\:]{0,16}") {
        if check_relative_path(&path).is_ok() {
            prop_assert!(!path.starts_with('/'));
            prop_assert!(path.split('/').all(|c| c != ".." && c != "." && !c.is_empty()));
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    #[test]
    fn damaged_archives_give_errors_not_panics(cut in 0usize..100_000, flips in proptest::collection::vec((any::<usize>(), any::<u8>()), 0..8)) {
        let mut bytes = zipped_ci().clone();
        for (at, value) in flips {
            let i = at % bytes.len();
            bytes[i] ^= value;
        }
        let keep = bytes.len().saturating_sub(cut);
        bytes.truncate(keep);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bundle.zip");
        std::fs::write(&path, &bytes).unwrap();
        let table = ConnectionTable::api5b();
        if let Ok(bundle) = Bundle::open(&path, &table, OpenOptions::default()) {
            // Whatever survived validation still decodes or fails by name.
            for v in 0..bundle.views.len() {
                for k in 0..bundle.views[v].frames.len() {
                    if let Err(e) = bundle.read_frame(v, k) {
                        prop_assert!(e.to_string().contains(&bundle.views[v].frames[k].file), "{}", e);
                    }
                }
            }
        }
    }
}
