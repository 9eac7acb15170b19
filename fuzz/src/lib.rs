//! What each fuzz target does with its bytes; shared with the corpus replay in the main test suite
//! (`tests/it/fuzz_corpus.rs` includes this file), so a crash the fuzzer saved stays a test.
//! Errors are the expected answer to most inputs; a panic, an abort or an allocation past the
//! fuzzer's memory limit is the finding.

use crestscan::bundle::{Bundle, FrameCheck, Limits, OpenOptions, parse_manifest};
use crestscan::domain::thread::ConnectionTable;
use crestscan::eval::cmm::CmmMeasurements;

/// manifest.json bytes through the parser.
pub fn manifest(data: &[u8]) {
    if let Ok(manifest) = parse_manifest(data) {
        // What parses must serialise and parse back to the same manifest.
        let bytes = serde_json::to_vec(&manifest).expect("a manifest serialises");
        let again = parse_manifest(&bytes).expect("a parsed manifest re-parses");
        assert_eq!(again, manifest);
    }
}

/// Caps small enough that the fuzzer's memory limit only trips on a real amplification.
fn fuzz_limits() -> Limits {
    Limits {
        max_total_bytes: 64 << 20,
        max_file_bytes: 16 << 20,
        max_manifest_bytes: 1 << 20,
        max_stack_samples: 1 << 22,
        max_view_pixels: 1 << 22,
        max_surface_pixels: 1 << 24,
        ..Limits::default()
    }
}

/// An archive (zip or tar) through the bundle reader: opened, every frame decoded.
pub fn bundle(data: &[u8]) {
    let mut file = tempfile::NamedTempFile::new().expect("a temporary file");
    std::io::Write::write_all(&mut file, data).expect("the temporary file takes the input");
    static TABLE: std::sync::OnceLock<ConnectionTable> = std::sync::OnceLock::new();
    let table = TABLE.get_or_init(ConnectionTable::api5b);
    let options = OpenOptions { limits: fuzz_limits(), frame_check: FrameCheck::Decode, name: Some("the input") };
    if let Ok(bundle) = Bundle::open(file.path(), table, options) {
        for view in 0..bundle.views.len() {
            for frame in 0..bundle.views[view].frames.len() {
                let _ = bundle.read_frame(view, frame);
            }
        }
    }
}

/// CMM upload bytes through both parsers.
pub fn cmm(data: &[u8]) {
    let _ = CmmMeasurements::from_json(data);
    let _ = CmmMeasurements::from_csv(data);
}
