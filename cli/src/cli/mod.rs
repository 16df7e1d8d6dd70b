//! Command-line interface: argument parsing and the commands, each a thin layer over the library.

#[macro_use]
mod output;
mod args;
mod commands;
pub mod hint;
mod logger;
mod progress;

pub use output::is_broken_pipe;

pub fn run() -> semlook::Result<()> {
    use clap::{CommandFactory, FromArgMatches};
    let matches = args::Cli::command().get_matches();
    let cli = args::Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
    hint::set_command_flags(command_flags(&matches));
    logger::init(cli.quiet);
    progress::show(!cli.quiet);
    commands::dispatch(cli)
}

/// The long flags of the (sub)command `m` runs, its parents' included (the global ones), as
/// [`hint::flags_of`] lists them.
fn command_flags(m: &clap::ArgMatches) -> Vec<String> {
    use clap::CommandFactory;
    let longs = hint::flags_of;
    let mut cmd = args::Cli::command();
    let mut flags = longs(&cmd);
    let mut m = m;
    while let Some((name, sub)) = m.subcommand() {
        let Some(c) = cmd.find_subcommand(name).cloned() else { break };
        flags.extend(longs(&c));
        cmd = c;
        m = sub;
    }
    flags
}
