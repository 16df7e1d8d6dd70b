//! The `semlook` command-line tool.

mod cli;

fn main() {
    // Mesa's Vulkan loader prints a spurious error when XDG_RUNTIME_DIR is unset (headless
    // machines); it is not used for compute. Set before any thread starts.
    if std::env::var_os("XDG_RUNTIME_DIR").is_none() {
        // SAFETY: single-threaded here, at the very start of main.
        unsafe { std::env::set_var("XDG_RUNTIME_DIR", std::env::temp_dir()) };
    }
    match cli::run() {
        Ok(()) => {}
        // the reader of our output went away: end quietly, as other Unix tools do
        Err(e) if cli::is_broken_pipe(&e) => {}
        Err(e) => {
            use std::io::Write;
            let _ = writeln!(std::io::stderr(), "error: {e}");
            if let Some(hint) = cli::hint::hint(&e) {
                let _ = writeln!(std::io::stderr(), "hint: {hint}");
            }
            std::process::exit(1);
        }
    }
}
