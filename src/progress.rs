//! Progress bars for long work (indicatif on stderr). The library draws none unless the
//! application asks with [`show`] (the CLI does, unless `--quiet`); hidden when not a terminal.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::sync::atomic::{AtomicBool, Ordering};

static VISIBLE: AtomicBool = AtomicBool::new(false);

/// Lets the library's progress bars draw on stderr (off by default: a library stays quiet).
pub fn show(yes: bool) {
    VISIBLE.store(yes, Ordering::Relaxed);
}

pub fn bar(len: usize, message: &str, quiet: bool) -> ProgressBar {
    let pb = ProgressBar::new(len as u64);
    if quiet || !VISIBLE.load(Ordering::Relaxed) {
        pb.set_draw_target(ProgressDrawTarget::hidden());
    }
    // a fixed, valid template; should indicatif refuse it, the bar keeps its default style
    if let Ok(style) = ProgressStyle::with_template("{msg:>14} [{bar:30}] {pos}/{len} {elapsed_precise} eta {eta}") {
        pb.set_style(style.progress_chars("=> "));
    }
    pb.set_message(message.to_string());
    pb
}
