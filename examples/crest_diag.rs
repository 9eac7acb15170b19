//! Each crest bin's brightness as the crest stage reads it, for a simulated bundle: one line per
//! bin (thread, angle, crest gray, height, crest z and radius), to set against the truth's black
//! arcs offline. A working tool for the notebook (docs/notebook/accuracy.md), not part of the
//! product.
//!
//! cargo run --release --example crest_diag -- BUNDLE_DIR [OPTIONS_JSON] > bins.tsv
mod common;

fn main() {
    let (_, bundle, options) = common::bundle_and_options();
    let inspection = crestscan::pipeline::inspect(&bundle, &options, &|_, _| {}, &Default::default())
        .unwrap()
        .expect("not cancelled");
    println!(
        "thread\tangle_deg\tcrest_gray\theight_mm\tcrest_z_mm\tcrest_radius_mm\tmachined_crest_gray={}",
        inspection.report.machined_crest_gray
    );
    for t in &inspection.threads {
        for b in &t.bins {
            let gray = b.crest_gray.map_or("nan".to_string(), |g| format!("{g:.4}"));
            let height = b.height_mm.map_or("nan".to_string(), |h| format!("{h:.4}"));
            let radius = b.crest_radius_mm.map_or("nan".to_string(), |r| format!("{r:.4}"));
            println!("{}\t{:.1}\t{gray}\t{height}\t{:.4}\t{radius}", t.index, b.angle_deg, b.crest_z_mm);
        }
    }
}
