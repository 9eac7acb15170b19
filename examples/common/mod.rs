//! What the diagnostic examples share: the bundle named by the first argument and the pipeline
//! options, the defaults overridden by the JSON file named by the second (when given).

use crestscan::bundle::{Bundle, OpenOptions};
use crestscan::domain::thread::ConnectionTable;
use crestscan::pipeline::PipelineOptions;
use std::path::PathBuf;

/// `BUNDLE_DIR [OPTIONS_JSON]` from the command line: the bundle's directory, the opened bundle
/// and the options.
pub fn bundle_and_options() -> (PathBuf, Bundle, PipelineOptions) {
    let args: Vec<String> = std::env::args().collect();
    let dir = PathBuf::from(&args[1]);
    let options: PipelineOptions = match args.get(2) {
        Some(f) => PipelineOptions::default()
            .overridden_by(serde_json::from_slice(&std::fs::read(f).unwrap()).unwrap())
            .unwrap(),
        None => PipelineOptions::default(),
    };
    let table = ConnectionTable::api5b();
    let bundle = Bundle::open(&dir, &table, OpenOptions::default()).unwrap();
    (dir, bundle, options)
}
