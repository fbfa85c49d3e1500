//! Running a slicer as a child process: its stdout and stderr are read while it runs (so a
//! chatty slicer never blocks on a full pipe) and the last lines kept for error messages;
//! a timeout and a cancel flag are enforced; and the child, in its own process group, is
//! killed with everything it started when the run ends early or the guard is dropped, and
//! by the kernel if this process dies.

use std::collections::VecDeque;
use std::ffi::OsString;
use std::io::{BufRead, BufReader, Read};
use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Lines of output kept for error messages.
pub(crate) const TAIL_LINES: usize = 30;
/// Longer lines are cut: CuraEngine logs all its settings on one enormous line.
pub(crate) const TAIL_LINE_CHARS: usize = 400;

/// How a run ended.
#[derive(Debug)]
pub(crate) enum End {
    Exited(ExitStatus),
    TimedOut,
    Cancelled,
}

/// The end of a run and the last lines the child wrote on each stream. The streams are
/// kept apart because their relative order is lost anyway (two reader threads), and so a
/// chatty stdout cannot push the error message out of stderr's tail.
#[derive(Debug)]
pub(crate) struct Outcome {
    pub end: End,
    pub stdout_tail: Vec<String>,
    pub stderr_tail: Vec<String>,
}

impl Outcome {
    /// The end of the output for an error message: the last few stdout lines, then
    /// stderr's tail (where slicers put their errors).
    pub(crate) fn tail_text(&self) -> String {
        let out = &self.stdout_tail[self.stdout_tail.len().saturating_sub(8)..];
        out.iter()
            .chain(self.stderr_tail.iter())
            .map(String::as_str)
            .collect::<Vec<_>>()
            .join("\n")
    }

    /// Every kept line, stdout's then stderr's.
    pub(crate) fn lines(&self) -> impl Iterator<Item = &str> {
        self.stdout_tail
            .iter()
            .chain(self.stderr_tail.iter())
            .map(String::as_str)
    }
}

#[derive(Debug)]
pub(crate) enum RunError {
    /// The program does not exist.
    NotFound,
    Spawn(std::io::Error),
}

/// Kills the child's whole process group unless it has been reaped: a job dropped early
/// (error, panic, cancelled caller) never leaves a slicer running.
struct ChildGuard {
    child: Child,
    reaped: bool,
}

impl ChildGuard {
    fn kill(&mut self) {
        if self.reaped {
            return;
        }
        // The child leads its own group (process_group(0)), so this also stops anything
        // it started, e.g. a wrapper script's `sleep`, which would keep the pipes open.
        if let Ok(pid) = i32::try_from(self.child.id()) {
            let _ = nix::sys::signal::killpg(
                nix::unistd::Pid::from_raw(pid),
                nix::sys::signal::Signal::SIGKILL,
            );
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
        self.reaped = true;
    }
}

impl Drop for ChildGuard {
    fn drop(&mut self) {
        self.kill();
    }
}

fn push_line(tail: &Mutex<VecDeque<String>>, line: &str) {
    let mut line = line.trim_end().to_string();
    if line.is_empty() {
        return;
    }
    if line.chars().count() > TAIL_LINE_CHARS {
        line = line.chars().take(TAIL_LINE_CHARS).collect::<String>() + " …";
    }
    let mut tail = tail.lock().unwrap_or_else(|e| e.into_inner());
    if tail.len() == TAIL_LINES {
        tail.pop_front();
    }
    tail.push_back(line);
}

/// Most bytes of one output line kept: enough for [`TAIL_LINE_CHARS`] characters of any
/// UTF-8. The rest of a longer line (a slicer printing a whole mesh on one line, or
/// output without a newline) is read and dropped, so memory stays bounded.
const LINE_BYTES_KEPT: usize = TAIL_LINE_CHARS * 4;

/// Reads one line into `buf` (cleared first), keeping at most `max` bytes of it and
/// reading past the rest. False at the end of the stream with nothing read.
fn read_line_bounded(
    reader: &mut impl BufRead,
    buf: &mut Vec<u8>,
    max: usize,
) -> std::io::Result<bool> {
    buf.clear();
    let mut read_any = false;
    loop {
        let available = match reader.fill_buf() {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        if available.is_empty() {
            return Ok(read_any);
        }
        read_any = true;
        let (taken, ends) = match available.iter().position(|&b| b == b'\n') {
            Some(at) => (at + 1, true),
            None => (available.len(), false),
        };
        let room = max.saturating_sub(buf.len());
        buf.extend_from_slice(&available[..taken.min(room)]);
        reader.consume(taken);
        if ends {
            return Ok(true);
        }
    }
}

fn spawn_reader(
    stream: impl Read + Send + 'static,
    tail: Arc<Mutex<VecDeque<String>>>,
) -> JoinHandle<()> {
    std::thread::spawn(move || {
        let mut reader = BufReader::new(stream);
        let mut buf = Vec::new();
        while let Ok(true) = read_line_bounded(&mut reader, &mut buf, LINE_BYTES_KEPT) {
            push_line(&tail, &String::from_utf8_lossy(&buf));
        }
    })
}

/// Makes the kernel kill the child `cmd` starts if this process dies without a chance to
/// clean up (kill -9, a crash), instead of leaving it to run on with no one waiting for it.
pub fn die_with_this_process(cmd: &mut Command) {
    let parent = nix::unistd::getpid();
    // SAFETY: between fork and exec only async-signal-safe calls (prctl and getppid) and no
    // allocation: an errno becomes an `io::Error` without a heap block, unlike a message.
    unsafe {
        cmd.pre_exec(move || {
            nix::sys::prctl::set_pdeathsig(nix::sys::signal::Signal::SIGKILL)?;
            if nix::unistd::getppid() != parent {
                // The parent died before the line above took effect: "no such process".
                return Err(std::io::Error::from_raw_os_error(nix::libc::ESRCH));
            }
            Ok(())
        });
    }
}

/// Runs `program args` with extra environment `env`, stdin closed, until it exits, the
/// timeout passes or `cancel` becomes true.
pub(crate) fn run(
    program: &Path,
    args: &[OsString],
    env: &[(OsString, OsString)],
    timeout: Duration,
    cancel: Option<&AtomicBool>,
) -> Result<Outcome, RunError> {
    let mut cmd = Command::new(program);
    cmd.args(args)
        .envs(env.iter().map(|(k, v)| (k, v)))
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .process_group(0);
    die_with_this_process(&mut cmd);
    let mut child = match cmd.spawn() {
        Ok(c) => c,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Err(RunError::NotFound),
        Err(e) => return Err(RunError::Spawn(e)),
    };
    let stdout_tail = Arc::new(Mutex::new(VecDeque::with_capacity(TAIL_LINES)));
    let stderr_tail = Arc::new(Mutex::new(VecDeque::with_capacity(TAIL_LINES)));
    let readers: Vec<JoinHandle<()>> = [
        child
            .stdout
            .take()
            .map(|s| spawn_reader(s, stdout_tail.clone())),
        child
            .stderr
            .take()
            .map(|s| spawn_reader(s, stderr_tail.clone())),
    ]
    .into_iter()
    .flatten()
    .collect();
    let mut guard = ChildGuard {
        child,
        reaped: false,
    };

    let deadline = Instant::now() + timeout;
    let end = loop {
        match guard.child.try_wait() {
            Ok(Some(status)) => {
                guard.reaped = true;
                break End::Exited(status);
            }
            Ok(None) => {}
            Err(e) => return Err(RunError::Spawn(e)),
        }
        if cancel.is_some_and(|c| c.load(Ordering::Relaxed)) {
            guard.kill();
            break End::Cancelled;
        }
        if Instant::now() >= deadline {
            guard.kill();
            break End::TimedOut;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    // The child is gone; a grandchild it left behind may still hold the pipes, so kill the
    // group before waiting for the readers.
    if let Ok(pid) = i32::try_from(guard.child.id()) {
        let _ = nix::sys::signal::killpg(
            nix::unistd::Pid::from_raw(pid),
            nix::sys::signal::Signal::SIGKILL,
        );
    }
    for r in readers {
        let _ = r.join();
    }
    let take = |t: &Mutex<VecDeque<String>>| -> Vec<String> {
        t.lock()
            .unwrap_or_else(|e| e.into_inner())
            .drain(..)
            .collect()
    };
    Ok(Outcome {
        end,
        stdout_tail: take(&stdout_tail),
        stderr_tail: take(&stderr_tail),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sh(script: &str, timeout: Duration) -> Outcome {
        run(
            Path::new("/bin/sh"),
            &["-c".into(), script.into()],
            &[],
            timeout,
            None,
        )
        .expect("sh runs")
    }

    #[test]
    fn keeps_the_tail_of_both_streams_and_the_exit_status() {
        let o = sh(
            "i=0; while [ $i -lt 100 ]; do echo out $i; i=$((i+1)); done; echo last-err >&2; exit 3",
            Duration::from_secs(20),
        );
        match o.end {
            End::Exited(s) => assert_eq!(s.code(), Some(3)),
            other => panic!("unexpected end {other:?}"),
        }
        assert_eq!(o.stdout_tail.len(), TAIL_LINES);
        assert_eq!(o.stdout_tail.last().map(String::as_str), Some("out 99"));
        assert!(!o.stdout_tail.iter().any(|l| l == "out 0"));
        assert_eq!(o.stderr_tail, vec!["last-err".to_string()]);
        let text = o.tail_text();
        assert!(
            text.starts_with("out 92\n") && text.ends_with("out 99\nlast-err"),
            "{text}"
        );
    }

    #[test]
    fn a_hanging_child_and_its_children_are_killed_at_the_timeout() {
        let started = Instant::now();
        let o = sh(
            "echo started; sleep 30; echo never",
            Duration::from_millis(300),
        );
        assert!(matches!(o.end, End::TimedOut), "{:?}", o.end);
        // Returning at all proves the orphaned `sleep` no longer holds the pipes open.
        assert!(started.elapsed() < Duration::from_secs(20));
        assert_eq!(o.stdout_tail, vec!["started".to_string()]);
    }

    #[test]
    fn setting_the_cancel_flag_stops_the_child() {
        let cancel = Arc::new(AtomicBool::new(false));
        let flag = cancel.clone();
        let setter = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(200));
            flag.store(true, Ordering::Relaxed);
        });
        let o = run(
            Path::new("/bin/sh"),
            &["-c".into(), "sleep 30".into()],
            &[],
            Duration::from_secs(60),
            Some(&cancel),
        )
        .expect("sh runs");
        setter.join().unwrap();
        assert!(matches!(o.end, End::Cancelled), "{:?}", o.end);
    }

    #[test]
    fn a_missing_program_is_reported_as_such() {
        let r = run(
            Path::new("/nonexistent/crispen-no-such-slicer"),
            &[],
            &[],
            Duration::from_secs(1),
            None,
        );
        assert!(matches!(r, Err(RunError::NotFound)), "{r:?}");
    }

    #[test]
    fn very_long_lines_are_cut() {
        let o = sh(
            "head -c 5000 /dev/zero | tr '\\0' x; echo",
            Duration::from_secs(20),
        );
        assert_eq!(o.stdout_tail.len(), 1);
        assert!(o.stdout_tail[0].chars().count() < TAIL_LINE_CHARS + 5);
    }

    /// A line far longer than what is kept costs no more memory than the bound: its
    /// start is kept, the rest read past, and the next line comes whole (`read_until`
    /// once held any line in full).
    #[test]
    fn an_endless_line_is_bounded_and_the_next_one_kept() {
        let mut text = vec![b'x'; 8 << 20];
        text.extend_from_slice(b"\nlast line\nno newline");
        let mut reader = BufReader::with_capacity(4096, &text[..]);
        let mut buf = Vec::new();
        let mut lines = Vec::new();
        while read_line_bounded(&mut reader, &mut buf, 100).unwrap() {
            assert!(
                buf.len() <= 100 && buf.capacity() < 4096 * 2,
                "{}",
                buf.len()
            );
            lines.push(String::from_utf8_lossy(&buf).into_owned());
        }
        assert_eq!(
            lines,
            ["x".repeat(100), "last line\n".into(), "no newline".into()]
        );
    }

    /// Through a real child: a slicer writing megabytes on one line leaves a short tail
    /// with its last lines.
    #[test]
    fn a_child_printing_a_huge_line_leaves_a_short_tail() {
        let out = run(
            Path::new("sh"),
            &[
                "-c".into(),
                "head -c 4000000 /dev/zero | tr '\\0' x; echo; echo done; echo oops >&2".into(),
            ],
            &[],
            Duration::from_secs(60),
            None,
        )
        .unwrap();
        assert_eq!(out.stdout_tail.len(), 2, "{:?}", out.stdout_tail.len());
        assert!(out.stdout_tail[0].chars().count() <= TAIL_LINE_CHARS + 2);
        assert_eq!(out.stdout_tail[1], "done");
        assert_eq!(out.stderr_tail, ["oops"]);
    }
}
