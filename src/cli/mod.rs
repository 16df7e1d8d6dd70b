//! Command-line interface: argument parsing and the commands, each a thin layer over the library.

#[macro_use]
mod output;
mod args;
mod commands;
pub mod hint;
mod logger;

pub use output::is_broken_pipe;

pub fn run() -> semlook::Result<()> {
    use clap::Parser;
    let cli = args::Cli::parse();
    logger::init(cli.quiet);
    semlook::progress::show(!cli.quiet);
    commands::dispatch(cli)
}
