//! The command line's progress reporter (`semlook::progress::Reporter`): on a terminal, an
//! indicatif bar with rate and ETA; elsewhere (a pipe, a log file, CI) plain lines such as
//! `references: 120/500 (24 %), 3.1/s, eta 2m03s`, at most one per tenth of the work or per
//! `LINE_EVERY`, whichever comes first, and one at the end. Installed unless `--quiet`; standard
//! output is never touched.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use semlook::progress::{Reporter, Task};
use std::io::{IsTerminal, Write};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Longest time between two plain lines while work advances.
pub const LINE_EVERY: Duration = Duration::from_secs(5);

/// Lets the library's progress (and the command line's own) draw on stderr.
pub fn show(yes: bool) {
    semlook::progress::set_reporter(yes.then(|| Arc::new(Bars) as Arc<dyn Reporter>));
}

/// Bars on a terminal, plain lines elsewhere.
struct Bars;

impl Reporter for Bars {
    fn start(&self, len: usize, message: &str) -> Box<dyn Task> {
        Box::new(bar(len, message))
    }
}

/// Progress of `len` steps (0: unknown) named `message`: a bar or plain lines.
struct Progress {
    bar: ProgressBar,
    lines: Option<Lines>,
}

/// The plain-line state; `inc` runs on many threads at once.
struct Lines {
    message: String,
    len: u64,
    start: Instant,
    done: AtomicU64,
    /// Steps done at the last line, and its time in ms since `start`.
    printed: AtomicU64,
    printed_ms: AtomicU64,
    writing: Mutex<()>,
}

fn bar(len: usize, message: &str) -> Progress {
    let terminal = std::io::stderr().is_terminal();
    let pb = ProgressBar::new(len as u64);
    if !terminal {
        pb.set_draw_target(ProgressDrawTarget::hidden());
    }
    // a fixed, valid template; should indicatif refuse it, the bar keeps its default style
    if let Ok(style) = ProgressStyle::with_template("{msg:>14} [{bar:30}] {pos}/{len} {rate} eta {eta} ({elapsed})") {
        let rate = |s: &indicatif::ProgressState, w: &mut dyn std::fmt::Write| {
            let _ = w.write_str(&rate(s.pos(), s.elapsed()));
        };
        pb.set_style(style.with_key("rate", rate).progress_chars("=> "));
    }
    pb.set_message(message.to_string());
    let lines = (!terminal).then(|| Lines {
        message: message.to_string(),
        len: len as u64,
        start: Instant::now(),
        done: AtomicU64::new(0),
        printed: AtomicU64::new(0),
        printed_ms: AtomicU64::new(0),
        writing: Mutex::new(()),
    });
    Progress { bar: pb, lines }
}

impl Task for Progress {
    fn inc(&self, n: u64) {
        self.bar.inc(n);
        if let Some(l) = &self.lines {
            let done = l.done.fetch_add(n, Ordering::Relaxed) + n;
            l.maybe_print(done, false);
        }
    }
    /// Ends the bar (a terminal's line is cleared); plain output gets its last line if due.
    fn finish(&self) {
        self.bar.finish_and_clear();
        if let Some(l) = &self.lines {
            l.maybe_print(l.done.load(Ordering::Relaxed), true);
        }
    }
    /// Runs `f` with the bar hidden (for messages printed while it shows).
    fn suspend(&self, f: &mut dyn FnMut()) {
        self.bar.suspend(f)
    }
}

impl Lines {
    fn maybe_print(&self, done: u64, finished: bool) {
        let elapsed = self.start.elapsed();
        let since = elapsed.saturating_sub(Duration::from_millis(self.printed_ms.load(Ordering::Relaxed)));
        if !due(self.len, self.printed.load(Ordering::Relaxed), done, since, finished) {
            return;
        }
        let Ok(_guard) = self.writing.lock() else { return };
        // another thread may have printed meanwhile
        let printed = self.printed.load(Ordering::Relaxed);
        let since = elapsed.saturating_sub(Duration::from_millis(self.printed_ms.load(Ordering::Relaxed)));
        if done <= printed || !due(self.len, printed, done, since, finished) {
            return;
        }
        self.printed.store(done, Ordering::Relaxed);
        self.printed_ms.store(elapsed.as_millis() as u64, Ordering::Relaxed);
        // a closed standard error loses the line, never the work
        let _ = writeln!(std::io::stderr(), "{}", line(&self.message, done, self.len, elapsed));
    }
}

/// Whether a plain line is due at `done` steps of `len` (0: unknown), the last one printed at
/// `printed` steps `since` ago: a new tenth of the work reached, `LINE_EVERY` passed, or the end.
pub fn due(len: u64, printed: u64, done: u64, since: Duration, finished: bool) -> bool {
    if done <= printed {
        return false;
    }
    let complete = len > 0 && done >= len;
    let tenth = len > 0 && done * 10 / len > printed * 10 / len;
    finished || complete || tenth || since >= LINE_EVERY
}

/// `message: done/len (pct %), rate/s, eta 2m03s` (`in 12s` once complete; without `len`, the
/// count and the rate).
pub fn line(message: &str, done: u64, len: u64, elapsed: Duration) -> String {
    let secs = elapsed.as_secs_f64();
    let rate = rate(done, elapsed);
    if len == 0 {
        return format!("{message}: {done}, {rate}");
    }
    let pct = (done as f64 * 100.0 / len as f64).min(100.0);
    let tail = if done >= len {
        format!("in {}", duration(secs))
    } else if done > 0 {
        format!("eta {}", duration(secs * (len - done) as f64 / done as f64))
    } else {
        "eta -".to_string()
    };
    format!("{message}: {done}/{len} ({pct:.0} %), {rate}, {tail}")
}

/// Steps per second, to two significant digits or the unit (`0.25/s`, `3.1/s`, `412/s`).
fn rate(done: u64, elapsed: Duration) -> String {
    let secs = elapsed.as_secs_f64();
    match if secs > 0.0 { done as f64 / secs } else { 0.0 } {
        r if r >= 10.0 => format!("{r:.0}/s"),
        r if r >= 1.0 => format!("{r:.1}/s"),
        r => format!("{r:.2}/s"),
    }
}

/// `45s`, `2m03s`, `1h02m`.
pub fn duration(secs: f64) -> String {
    let s = secs.max(0.0).round() as u64;
    match s {
        0..60 => format!("{s}s"),
        60..3600 => format!("{}m{:02}s", s / 60, s % 60),
        _ => format!("{}h{:02}m", s / 3600, s % 3600 / 60),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_come_every_tenth_or_every_five_seconds_and_at_the_end() {
        let quick = Duration::from_millis(10);
        // 1000 steps, each a moment after the last: one line per tenth
        let (mut printed, mut n) = (0, 0);
        for done in 1..=1000 {
            if due(1000, printed, done, quick, false) {
                printed = done;
                n += 1;
            }
        }
        assert_eq!(n, 10);
        assert!(due(1000, 100, 150, LINE_EVERY, false), "5 s passed");
        assert!(!due(1000, 100, 150, quick, false));
        assert!(due(1000, 100, 150, quick, true), "the end");
        assert!(!due(1000, 150, 150, LINE_EVERY, true), "nothing new");
        assert!(!due(0, 10, 11, quick, false) && due(0, 10, 11, LINE_EVERY, false), "unknown length: by time only");
    }

    #[test]
    fn a_line_says_count_share_rate_and_eta() {
        assert_eq!(line("references", 120, 500, Duration::from_secs(40)), "references: 120/500 (24 %), 3.0/s, eta 2m07s");
        assert_eq!(line("images", 12, 12, Duration::from_secs(4)), "images: 12/12 (100 %), 3.0/s, in 4s");
        assert_eq!(line("frames", 30, 0, Duration::from_secs(2)), "frames: 30, 15/s");
        assert_eq!(duration(3725.0), "1h02m");
    }
}
