//! The CLI decides what the library's log records show: warnings and errors always, the rest
//! unless `--quiet` (the library itself never prints).

use log::{Level, LevelFilter, Log, Metadata, Record};

struct StderrLogger;

impl Log for StderrLogger {
    fn enabled(&self, m: &Metadata) -> bool {
        m.level() <= log::max_level() && m.target().starts_with("semlook")
    }
    fn log(&self, r: &Record) {
        if self.enabled(r.metadata()) {
            match r.level() {
                Level::Error => eprintln!("error: {}", r.args()),
                Level::Warn => eprintln!("warning: {}", r.args()),
                _ => eprintln!("{}", r.args()),
            }
        }
    }
    fn flush(&self) {}
}

static LOGGER: StderrLogger = StderrLogger;

pub fn init(quiet: bool) {
    // a second init (tests) keeps the first logger
    if log::set_logger(&LOGGER).is_ok() {
        log::set_max_level(if quiet { LevelFilter::Warn } else { LevelFilter::Info });
    }
}
