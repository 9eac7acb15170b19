//! Progress of long commands (`simulate`, `inspect`, `bench`) on stderr, through indicatif: drawn
//! only on a terminal (indicatif hides it when stderr is piped or redirected) and never with
//! `--quiet`, so logs and CI output stay clean.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::time::Duration;

fn target(quiet: bool) -> ProgressDrawTarget {
    if quiet { ProgressDrawTarget::hidden() } else { ProgressDrawTarget::stderr() }
}

/// A bar over `len` units of work, labelled `what`.
pub fn bar(len: u64, what: &str, quiet: bool) -> ProgressBar {
    let bar = ProgressBar::with_draw_target(Some(len), target(quiet));
    bar.set_style(
        ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} {msg} ({elapsed}, about {eta} left)")
            .expect("a valid template")
            .progress_chars("=> "),
    );
    bar.set_prefix(what.to_string());
    bar
}

/// A bar over a fraction (0–1) of a job in stages, the stage as its message.
pub fn stages(what: &str, quiet: bool) -> ProgressBar {
    let bar = ProgressBar::with_draw_target(Some(1000), target(quiet));
    bar.set_style(
        ProgressStyle::with_template("{prefix} {spinner} {msg:8} [{bar:30}] {elapsed}")
            .expect("a valid template")
            .progress_chars("=> "),
    );
    bar.set_prefix(what.to_string());
    bar.enable_steady_tick(Duration::from_millis(200));
    bar
}
