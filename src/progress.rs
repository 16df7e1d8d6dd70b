//! Progress of long work (encoding frames, training a codebook, building a map, evaluating): the
//! library reports it to the [`Reporter`] the application installs with [`set_reporter`] (the
//! command line draws bars or plain lines on stderr); without one, nothing is drawn and nothing
//! is written: a library stays quiet.

use std::sync::{Arc, RwLock};

/// Where progress goes: the application's drawing (bars, lines, a log, a GUI).
pub trait Reporter: Send + Sync {
    /// A task of `len` steps (0: unknown) named `message` starts.
    fn start(&self, len: usize, message: &str) -> Box<dyn Task>;
}

/// One task's progress, advanced from any thread.
pub trait Task: Send + Sync {
    /// `n` more steps are done.
    fn inc(&self, n: u64);
    /// The task ended (done or abandoned).
    fn finish(&self);
    /// Runs `f` with the task's drawing out of the way (for a message printed meanwhile).
    fn suspend(&self, f: &mut dyn FnMut()) {
        f()
    }
}

static REPORTER: RwLock<Option<Arc<dyn Reporter>>> = RwLock::new(None);

/// Installs `reporter` for every task that starts from now on (`None`: report nothing).
pub fn set_reporter(reporter: Option<Arc<dyn Reporter>>) {
    if let Ok(mut r) = REPORTER.write() {
        *r = reporter;
    }
}

/// A task's handle: its progress goes to the installed reporter, or nowhere.
pub struct Progress(Option<Box<dyn Task>>);

/// Starts a task of `len` steps (0: unknown) named `message`; `quiet`: reports nothing (a call's
/// own switch, beside the application's reporter).
pub fn bar(len: usize, message: &str, quiet: bool) -> Progress {
    let reporter = if quiet { None } else { REPORTER.read().ok().and_then(|r| r.clone()) };
    Progress(reporter.map(|r| r.start(len, message)))
}

impl Progress {
    /// `n` more steps are done.
    pub fn inc(&self, n: u64) {
        if let Some(t) = &self.0 {
            t.inc(n);
        }
    }
    /// Ends the task.
    pub fn finish_and_clear(&self) {
        if let Some(t) = &self.0 {
            t.finish();
        }
    }
    /// Runs `f` with the task's drawing out of the way (for messages printed while it shows).
    pub fn suspend<R>(&self, f: impl FnOnce() -> R) -> R {
        match &self.0 {
            Some(t) => {
                let (mut f, mut out) = (Some(f), None);
                t.suspend(&mut || out = f.take().map(|f| f()));
                // a reporter that never ran `f` still gets it run
                out.unwrap_or_else(|| (f.take().expect("f runs at most once"))())
            }
            None => f(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    /// Records what it is told, as `message: event`.
    #[derive(Default)]
    struct Log(Arc<Mutex<Vec<String>>>);
    struct Logged(Arc<Mutex<Vec<String>>>, String);

    impl Reporter for Log {
        fn start(&self, len: usize, message: &str) -> Box<dyn Task> {
            self.0.lock().unwrap().push(format!("{message}: start {len}"));
            Box::new(Logged(self.0.clone(), message.to_string()))
        }
    }
    impl Task for Logged {
        fn inc(&self, n: u64) {
            self.0.lock().unwrap().push(format!("{}: +{n}", self.1));
        }
        fn finish(&self) {
            self.0.lock().unwrap().push(format!("{}: end", self.1));
        }
    }

    /// One test for the process-wide reporter (tests run on threads of one process).
    #[test]
    fn tasks_report_to_the_installed_reporter_unless_quiet_and_nowhere_without_one() {
        let log = Log::default();
        let seen = log.0.clone();
        set_reporter(Some(Arc::new(log)));
        let t = bar(3, "images", false);
        t.inc(2);
        assert_eq!(t.suspend(|| 7), 7, "suspend runs its closure and returns its value");
        t.finish_and_clear();
        let q = bar(3, "quiet", true);
        q.inc(1);
        q.finish_and_clear();
        set_reporter(None);
        let n = bar(1, "none", false);
        n.inc(1);
        assert_eq!(n.suspend(|| "ran"), "ran");
        assert_eq!(*seen.lock().unwrap(), ["images: start 3", "images: +2", "images: end"]);
    }
}
