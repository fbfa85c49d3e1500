//! Logging setup shared by every subcommand: `tracing` to stderr, or to the journal when
//! running under systemd (JOURNAL_STREAM is set). `RUST_LOG` overrides the level.

use std::io::IsTerminal;
use tracing_subscriber::{fmt, prelude::*, EnvFilter};

pub(crate) fn init() {
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    let registry = tracing_subscriber::registry().with(filter);
    if std::env::var_os("JOURNAL_STREAM").is_some() {
        if let Ok(journald) = tracing_journald::layer() {
            let _ = registry.with(journald).try_init();
            return;
        }
    }
    let _ = registry
        .with(
            fmt::layer()
                .with_writer(std::io::stderr)
                .with_ansi(std::io::stderr().is_terminal())
                .with_target(false),
        )
        .try_init();
}
