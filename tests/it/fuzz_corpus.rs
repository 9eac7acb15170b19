//! The fuzz corpus (fuzz/corpus/<target>/: the seeds and every input scripts/fuzz kept or saved
//! as a crash) through the same target functions, so a finding stays fixed.

use super::fuzz_targets;
use std::path::Path;

fn replay(target: &str, run: fn(&[u8])) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus").join(target);
    let mut inputs = 0;
    for entry in std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
        let path = entry.unwrap().path();
        let data = std::fs::read(&path).unwrap();
        let outcome = std::panic::catch_unwind(|| run(&data));
        assert!(outcome.is_ok(), "{} panicked", path.display());
        inputs += 1;
    }
    assert!(inputs >= 2, "{}: {inputs} inputs", dir.display());
}

#[test]
fn the_manifest_corpus_parses_or_is_refused_without_a_panic() {
    replay("manifest", fuzz_targets::manifest);
}

#[test]
fn the_bundle_corpus_opens_or_is_refused_without_a_panic() {
    replay("bundle", fuzz_targets::bundle);
}

#[test]
fn the_cmm_corpus_parses_or_is_refused_without_a_panic() {
    replay("cmm", fuzz_targets::cmm);
}

/// The seeds are valid inputs: a test that only saw refusals would not exercise the readers.
#[test]
fn the_seeds_are_accepted_by_the_readers() {
    let corpus = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus");
    let manifest = std::fs::read(corpus.join("manifest/seed-small")).unwrap();
    crestscan::bundle::parse_manifest(&manifest).unwrap();
    let csv = std::fs::read(corpus.join("cmm/seed-csv")).unwrap();
    crestscan::eval::cmm::CmmMeasurements::from_csv(&csv).unwrap();
    let json = std::fs::read(corpus.join("cmm/seed-json")).unwrap();
    crestscan::eval::cmm::CmmMeasurements::from_json(&json).unwrap();
    for archive in ["seed-tar", "seed-zip-deflated"] {
        let path = corpus.join("bundle").join(archive);
        let table = crestscan::domain::thread::ConnectionTable::api5b();
        let opened = crestscan::bundle::Bundle::open(&path, &table, Default::default());
        // The 16×8 frames are far too small a station to inspect; everything before that passes.
        let e = opened.expect_err("a 16×8 station is refused");
        assert!(
            matches!(
                e,
                crestscan::bundle::BundleError::StationOutOfRange { .. }
                    | crestscan::bundle::BundleError::InspectionTooLarge { .. }
            ),
            "{archive}: {e}"
        );
    }
}
