//! `crispen prepare-job` (hidden): the daemon's preparation child. Reads one
//! [`PrepareTask`] as JSON on stdin, prepares it (or measures a job already prepared), and
//! answers in [`ChildMessage`] JSON lines on stdout. The daemon kills it when the job is
//! cancelled, the daemon stops, or the time limit passes (see `crispen::daemon::prepare`).

use crispen::daemon::prepare::{self, ChildMessage, PrepareTask};
use std::io::{Read, Write};
use std::process::ExitCode;

#[derive(Debug, clap::Args)]
pub(crate) struct Args {}

pub(crate) fn run(_args: Args) -> anyhow::Result<ExitCode> {
    let mut input = Vec::new();
    std::io::stdin().read_to_end(&mut input)?;
    let task: PrepareTask = serde_json::from_slice(&input)?;
    let span = tracing::info_span!("job", job = %task.job);
    let _entered = span.enter();
    let answer = prepare::answer(&task, &mut |step| say(&ChildMessage::Step(step)));
    let code = match answer {
        ChildMessage::Failed(_) => ExitCode::FAILURE,
        _ => ExitCode::SUCCESS,
    };
    say(&answer);
    Ok(code)
}

fn say(message: &ChildMessage) {
    let mut line = serde_json::to_string(message).expect("a message serialises");
    line.push('\n');
    let mut out = std::io::stdout().lock();
    // The daemon is gone if this fails; there is nobody left to tell.
    let _ = out.write_all(line.as_bytes()).and_then(|_| out.flush());
}
