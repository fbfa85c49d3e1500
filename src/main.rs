//! The `crispen` binary: parses the command line and hands off to [`crispen::cli`].
//! `anyhow` lives only here, at the edge; the library returns typed errors.

fn main() -> std::process::ExitCode {
    crispen::cli::main()
}
