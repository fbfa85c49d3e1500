//! The `crispen` binary: the command line ([`cli`]) over the `crispen` library.
//! clap, `anyhow` and indicatif live only here, at the edge; the library returns typed errors.

mod cli;

fn main() -> std::process::ExitCode {
    cli::main()
}
