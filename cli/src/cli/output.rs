//! Standard output that returns its errors: `out!`/`outln!` for the commands, and how `main`
//! tells a closed pipe (end quietly) from a real failure.

/// `print!` to standard output that returns the write's error (`?`), so a closed pipe or a full
/// disk ends the command with a typed error instead of a panic (`main` ends quietly on the first).
macro_rules! out {
    ($($t:tt)*) => { $crate::cli::output::write_out(format_args!($($t)*))? };
}
/// [`out!`] with a newline.
macro_rules! outln {
    ($($t:tt)*) => { $crate::cli::output::write_out(format_args!("{}\n", format_args!($($t)*)))? };
}

/// Writes to standard output, naming it in the error.
pub fn write_out(args: std::fmt::Arguments) -> semlook::Result<()> {
    use std::io::Write;
    let mut o = std::io::stdout().lock();
    o.write_fmt(args).and_then(|()| o.flush()).map_err(|e| semlook::Error::io("standard output", e))
}

/// Whether `e` is a write to a reader that went away (`semlook ... | head`): not worth a word.
pub fn is_broken_pipe(e: &semlook::Error) -> bool {
    matches!(e, semlook::Error::Io { source, .. } if source.kind() == std::io::ErrorKind::BrokenPipe)
}
