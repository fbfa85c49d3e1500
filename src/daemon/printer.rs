//! Printer supervisors: one task per printer that connects (reconnecting with backoff),
//! waits for its bed to be cleared (reading what the printer says meanwhile: a reset is
//! noted and an unplugged printer reconnected before a job depends on it), takes the oldest ready job of one of its folders,
//! holds it until a heating permit is free, streams it, and records the outcome.
//!
//! Temperatures: while a printer prints they come with the job's progress; between jobs
//! (and while a job waits for its heating permit) the link reads them every few seconds
//! ([`PrinterLink::watch_idle`]). They are shown only while current: they are dropped when
//! the connection is lost or re-opened and when the printer stops reporting them.
//!
//! Staggered heat-ups, approximated: a print holds one of `[farm] max_heating` permits from
//! its start until the streamer has had the last heat-and-wait command (`M109`, `M190`,
//! `M116`: [`crate::marlin::gcode::HEAT_WAITS`]) of the program's opening acknowledged;
//! Marlin acknowledges those only once the temperature is reached, so the permit is held
//! exactly through the heat-up. A program without such a command releases the permit at
//! once.
//!
//! The supervisor reaches the printer through [`Connector`]/[`PrinterLink`], so the real
//! Marlin streamer is wired in in one place ([`MarlinConnector`]).

//! What the supervisor shows of its printer it publishes on the printer's own `watch`
//! ([`PrinterOwner`]); it follows the job store's snapshot (a job ready, its bed cleared),
//! the config and the shared farm's database state, never a global wake-up.

use super::bed::Bed;
use super::config::power::PowerConfig;
use super::farm::{
    Farm, FarmView, LiveProgress, PrintCommand, PrinterLive, PrinterOwner, PrinterState,
    PrinterTemperatures,
};
use super::farm::{PowerReply, PowerRequest, POWER_ANSWER};
use super::job::{JobState, PrintReport};
use super::store::{JobChange, Use};
use super::time_left::{Pace, PaceSample, TimeLeft};
use crate::marlin::gcode::{GcodeError, GcodeProgram};
use crate::marlin::stream::{
    Connection, Idle, PauseSettings, PrintError, PrintProgress, PrintState, StreamControl,
    StreamOptions, Temperatures,
};
use std::future::Future;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{mpsc, watch};
use tracing::Instrument;

mod eject;
mod run;

pub(crate) use run::PrintFailure;

pub(crate) type BoxFuture<'a, T> = Pin<Box<dyn Future<Output = T> + Send + 'a>>;

/// A printer cannot be connected to (it is retried with backoff).
#[derive(Debug, thiserror::Error)]
#[error(transparent)]
pub(crate) struct ConnectError(#[from] pub PrintError);

/// An open connection to a printer.
pub(crate) trait PrinterLink: Send {
    /// Streams the G-code file at `gcode` without the parts of its plate named in
    /// `cancelled` (dropped from its first line); `control` pauses, resumes, cancels it or
    /// a part of it, progress is published on `progress` (its time left at the printer's
    /// `pace`). Returns a JSON report.
    fn print<'a>(
        &'a mut self,
        gcode: &'a Path,
        cancelled: Vec<String>,
        pace: Pace,
        control: mpsc::Receiver<PrintCommand>,
        progress: watch::Sender<LiveProgress>,
    ) -> BoxFuture<'a, Result<PrintReport, PrintFailure>>;

    /// Reads and logs what the printer says between jobs (reports, `start`, host actions),
    /// asking for its temperatures every few seconds, until it says something to act on
    /// or report. Cancel-safe: the supervisor races it against a bed being cleared or a
    /// job arriving.
    fn watch_idle(&mut self) -> BoxFuture<'_, IdleNews>;
}

/// What a printer said between jobs that the supervisor must act on.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum IdleNews {
    /// It said `start`: reset or power-cycled (the next job greets it afresh).
    Rebooted,
    /// The link closed; the connection must be re-opened.
    Lost(String),
    /// Its temperatures as read now; None once it stopped reporting them.
    Temperatures(Option<PrinterTemperatures>),
    /// It said it halted (`Error:Printer halted. kill() called!`, a thermal error...).
    Halted(String),
}

/// Opens connections to one printer.
pub(crate) trait Connector: Send + Sync {
    fn connect(&self) -> BoxFuture<'_, Result<Box<dyn PrinterLink>, ConnectError>>;
}

/// Index (in the program's command list) of the last heat-and-wait command of the opening
/// part of a program (before the first extruding move), if any.
pub(crate) fn heat_up_end<S: AsRef<str>>(commands: impl IntoIterator<Item = S>) -> Option<usize> {
    let mut last = None;
    for (i, c) in commands.into_iter().enumerate() {
        let c = c.as_ref();
        let word = c.split_whitespace().next().unwrap_or("");
        match word {
            w if crate::marlin::gcode::is_heat_wait(w) => last = Some(i),
            "G1" | "G0" if c.contains(" E") && last.is_some() => break,
            _ => {}
        }
    }
    last
}

/// One printer's supervisor: the farm it serves, and what it owns of the printer.
struct Supervisor {
    farm: Arc<Farm>,
    name: String,
    owner: PrinterOwner,
}

impl Supervisor {
    /// Changes what is shown of the printer; followers wake only on a real change.
    fn show(&self, change: impl FnOnce(&mut PrinterLive)) {
        self.owner.live.send_if_modified(|live| {
            let before = live.clone();
            change(live);
            *live != before
        });
    }
}

/// Runs one printer's supervisor until shutdown, or until `retire` turns true (the printer
/// left the config or changed); either takes effect between prints, never during one.
pub(crate) async fn supervise(
    farm: Arc<Farm>,
    name: String,
    owner: PrinterOwner,
    connector: Box<dyn Connector>,
    retire: watch::Receiver<bool>,
) {
    let span = tracing::info_span!("printer", printer = %name);
    let sup = Supervisor { farm, name, owner };
    supervise_inner(&sup, connector, retire)
        .instrument(span)
        .await
}

async fn supervise_inner(
    sup: &Supervisor,
    connector: Box<dyn Connector>,
    mut retire: watch::Receiver<bool>,
) {
    let farm = &sup.farm;
    let mut backoff = Duration::from_millis(500);
    let done = |retire: &watch::Receiver<bool>| farm.stopping() || *retire.borrow();
    // A print the daemon was stopped during (a kill): its filament, before anything else.
    super::usage::recover(farm, &sup.name).await;
    // Its switch, as the config had it when the supervisor started (a change restarts it).
    let power = farm
        .config()
        .printers
        .iter()
        .find(|p| p.name == sup.name)
        .and_then(|p| p.power.clone());
    // Why the printer is switched off, while it is; and until when a printer just switched
    // on may take to answer.
    let mut off = match &power {
        Some(p) => off_at_start(p).await,
        None => None,
    };
    let mut booting: Option<tokio::time::Instant> = None;
    // Since when the printer has been idle on a clear bed with nothing to print.
    let mut idle_since: Option<tokio::time::Instant> = None;
    'connect: loop {
        if done(&retire) {
            break;
        }
        if let (Some(p), Some(why)) = (&power, off.clone()) {
            let reply = match while_off(sup, &why, &mut retire).await {
                OffEnd::Stop => break,
                OffEnd::Again => continue,
                OffEnd::On(reply) => reply,
            };
            sup.show(|l| {
                l.state = PrinterState::Connecting;
                l.detail = Some("switching on".into());
            });
            match p.switch.send(crate::power::Ask::On).await {
                Ok(_) => {
                    tracing::info!(switch = p.switch.kind(), "switched the printer on");
                    answer(reply, Ok(true));
                    off = None;
                    idle_since = None;
                    booting = Some(tokio::time::Instant::now() + p.boot);
                }
                Err(e) => {
                    tracing::warn!(error = %e, "cannot switch the printer on");
                    answer(reply, Err(format!("cannot switch it on: {e}")));
                    off = Some(format!("cannot switch it on: {e}; tried again in 30 s"));
                    tokio::select! {
                        _ = tokio::time::sleep(Duration::from_secs(30)) => {}
                        _ = farm.shutdown.cancelled() => {}
                        _ = retire.changed() => {}
                    }
                    continue;
                }
            }
        }
        sup.show(|p| {
            p.state = PrinterState::Connecting;
            p.temperatures = None;
        });
        let connected = tokio::select! {
            connected = connector.connect() => connected,
            _ = farm.shutdown.cancelled() => break,
            _ = retire.changed() => continue,
        };
        let mut link = match connected {
            Ok(link) => {
                backoff = Duration::from_millis(500);
                booting = None;
                tracing::info!("connected");
                link
            }
            // Just switched on: its port appears, and its firmware answers, when it has
            // booted; until then, tried again soon and shown as connecting.
            Err(e) if booting.is_some_and(|until| tokio::time::Instant::now() < until) => {
                sup.show(|p| {
                    p.state = PrinterState::Connecting;
                    p.detail = Some(format!("switched on; waiting for it to answer ({e})"));
                });
                tokio::select! {
                    _ = tokio::time::sleep(Duration::from_millis(500)) => {}
                    _ = farm.shutdown.cancelled() => {}
                    _ = retire.changed() => {}
                }
                continue;
            }
            Err(e) => {
                tracing::warn!(error = %e, retry_in_s = backoff.as_secs_f64(), "cannot connect");
                let waited = booting.take().and(power.as_ref()).map(|p| p.boot);
                sup.show(|p| {
                    p.state = PrinterState::Disconnected;
                    p.detail = Some(match waited {
                        Some(boot) => format!(
                            "switched on, but it did not answer within {} s: {e}",
                            boot.as_secs()
                        ),
                        None => e.to_string(),
                    });
                });
                tokio::select! {
                    _ = tokio::time::sleep(backoff) => {}
                    _ = farm.shutdown.cancelled() => {}
                    _ = retire.changed() => {}
                }
                backoff = (backoff * 2).min(Duration::from_secs(30));
                continue;
            }
        };
        sup.show(|p| p.detail = None);
        // The firmware's message while it is halted; a new connection has had its
        // handshake answered, which a halted firmware never does.
        let mut halted: Option<String> = None;
        // The printer reset itself while idle: shown beside its other news until the
        // next job starts (it begins with a fresh handshake).
        let mut reset_between = false;
        loop {
            // Followed from before the look at the gate and the queue: a change while
            // looking is not missed.
            let mut follow = Follow::new(farm);
            if done(&retire) {
                break 'connect;
            }
            if let Some(message) = &halted {
                sup.show(|p| {
                    p.state = PrinterState::Halted;
                    p.detail = Some(format!(
                        "the firmware halted: {message}; it takes no job until it was reset \
                         (press its reset button or power-cycle it)"
                    ));
                });
                match until_reset(sup, link.as_mut(), &mut follow, &mut retire).await {
                    Reset::Lost => continue 'connect,
                    Reset::Seen => {
                        tracing::info!("the halted printer was reset (it said `start`)");
                        halted = None;
                        sup.show(|p| p.detail = None);
                    }
                    Reset::NotYet => {}
                }
                continue;
            }
            // The store's version this look starts from: what it passes over below, it
            // passed over in this version or a later one.
            let version = farm.store().version();
            let gate = farm.store().gate(&sup.name);
            match &gate.bed {
                Bed::Clear { .. } if eject::check_first(farm, &sup.name, &gate.bed) => {
                    eject::check_before_job(farm, &sup.name).await;
                    continue;
                }
                Bed::Clear { .. } => {}
                Bed::EjectDue { check } => {
                    let end = eject::run(sup, link.as_mut(), *check, &mut follow).await;
                    if end.lost {
                        continue 'connect;
                    }
                    halted = end.halted;
                    continue;
                }
                bed => {
                    idle_since = None;
                    let (state, detail) = match bed {
                        Bed::CheckDue { .. } => (PrinterState::CheckingBed, bed.describe()),
                        // An eject a restart found under way is the store's to end (its
                        // restart rules); another host's change may show it a moment.
                        Bed::Ejecting { .. } => (PrinterState::Ejecting, bed.describe()),
                        _ => (PrinterState::BedNotCleared, bed.describe()),
                    };
                    let detail = with_reset_note(reset_between, detail);
                    sup.show(|p| {
                        p.state = state;
                        p.job = gate.last_job.clone();
                        p.progress = None;
                        p.detail = detail;
                    });
                    sup.owner.looked.send_replace(version);
                    let waited = between_jobs(
                        sup,
                        link.as_mut(),
                        &mut follow,
                        &mut retire,
                        power.as_ref(),
                        None,
                    )
                    .await;
                    if after_wait(waited, &mut halted, &mut reset_between, &mut off) {
                        continue 'connect;
                    }
                    continue;
                }
            }
            if let Some(kept) = kept_for_care(farm, &sup.name) {
                idle_since = None;
                sup.show(|p| {
                    eject::forget_bed_shown(p);
                    p.state = PrinterState::Maintenance;
                    p.job = None;
                    p.progress = None;
                    p.detail = with_reset_note(reset_between, Some(kept.describe()));
                });
                sup.owner.looked.send_replace(version);
                let waited = between_jobs(
                    sup,
                    link.as_mut(),
                    &mut follow,
                    &mut retire,
                    power.as_ref(),
                    None,
                )
                .await;
                if after_wait(waited, &mut halted, &mut reset_between, &mut off) {
                    continue 'connect;
                }
                continue;
            }
            let Some(job_id) = claim_job(farm, &sup.name).await else {
                sup.show(|p| {
                    eject::forget_bed_shown(p);
                    // Why it was kept for its care is past.
                    if reset_between || p.state == PrinterState::Maintenance {
                        p.detail = with_reset_note(reset_between, None);
                    }
                    p.state = PrinterState::Idle;
                    p.job = None;
                    p.progress = None;
                });
                sup.owner.looked.send_replace(version);
                // Idle since it last had a print or a bed to wait for, whatever changed since.
                let since = *idle_since.get_or_insert_with(tokio::time::Instant::now);
                let off_at = power
                    .as_ref()
                    .and_then(|p| p.off_after_idle)
                    .map(|a| since + a);
                let waited = between_jobs(
                    sup,
                    link.as_mut(),
                    &mut follow,
                    &mut retire,
                    power.as_ref(),
                    off_at,
                )
                .await;
                if after_wait(waited, &mut halted, &mut reset_between, &mut off) {
                    continue 'connect;
                }
                continue;
            };
            reset_between = false;
            idle_since = None;
            let span = tracing::info_span!("job", job = %job_id);
            let end = run_job(sup, &job_id, link.as_mut()).instrument(span).await;
            if end.lost {
                continue 'connect;
            }
            halted = end.halted;
        }
    }
    if *retire.borrow() && !farm.stopping() {
        // The fleet takes it out of the farm once this task has ended.
        tracing::info!("supervisor retired by a config reload");
    } else {
        sup.show(|p| {
            p.state = PrinterState::Stopped;
            p.temperatures = None;
        });
    }
}

/// What an idle supervisor follows: a change of the jobs or bed gates, of the config (a
/// reload may make a job eligible), or the farm database answering again (claims that
/// failed meanwhile are tried again).
struct Follow {
    jobs: watch::Receiver<Arc<super::store::Snapshot>>,
    config: watch::Receiver<Arc<super::config::Config>>,
    shared: watch::Receiver<Option<FarmView>>,
    shutdown: super::farm::Stop,
}

impl Follow {
    fn new(farm: &Farm) -> Follow {
        Follow {
            jobs: farm.watch_jobs(),
            config: farm.watch_config(),
            shared: farm.watch_shared(),
            shutdown: farm.shutdown.clone(),
        }
    }

    async fn changed(&mut self) {
        let Follow {
            jobs,
            config,
            shared,
            shutdown,
        } = self;
        let database = |v: &Option<FarmView>| v.as_ref().and_then(|v| v.database.clone());
        let mut was = database(&shared.borrow_and_update());
        let answers_again = async {
            loop {
                if shared.changed().await.is_err() {
                    return std::future::pending().await;
                }
                let now = database(&shared.borrow_and_update());
                if was.is_some() && now.is_none() {
                    return;
                }
                was = now;
            }
        };
        tokio::select! {
            Ok(()) = jobs.changed() => {}
            Ok(()) = config.changed() => {}
            () = answers_again => {}
            () = shutdown.cancelled() => {}
        }
    }
}

/// How a wait between jobs ended.
enum Between {
    /// Something the supervisor may act on changed (a bed cleared, a job ready, a reload).
    Changed,
    /// The connection was lost.
    Lost,
    /// The firmware said it halted.
    Halted(String),
    /// The printer reset itself (it said `start`).
    Rebooted,
    /// Its switch switched it off (why, as shown): idle and cool long enough, or by hand.
    Off(String),
}

/// What a wait between jobs leaves the supervisor to know: the firmware's halt, a reset,
/// the printer switched off (why). Whether the connection is to be made again (lost, or
/// switched off).
fn after_wait(
    waited: Between,
    halted: &mut Option<String>,
    reset_between: &mut bool,
    off: &mut Option<String>,
) -> bool {
    match waited {
        Between::Lost => return true,
        Between::Halted(message) => *halted = Some(message),
        Between::Rebooted => *reset_between = true,
        Between::Changed => {}
        Between::Off(why) => {
            *off = Some(why);
            return true;
        }
    }
    false
}

/// `detail` with the note of a reset between jobs in front, when there was one.
fn with_reset_note(reset: bool, detail: Option<String>) -> Option<String> {
    const NOTE: &str =
        "the printer reset between jobs (it said `start`); the next job starts with a fresh handshake";
    match (reset, detail) {
        (false, detail) => detail,
        (true, None) => Some(NOTE.into()),
        (true, Some(d)) => Some(format!("{NOTE}; {d}")),
    }
}

/// Waits for a change the printer may act on (a bed cleared, a job ready, a reload) while
/// reading what the printer says meanwhile and showing its temperatures; a reset ends the
/// wait, for the caller to note it until the next job starts.
async fn between_jobs(
    sup: &Supervisor,
    link: &mut dyn PrinterLink,
    follow: &mut Follow,
    retire: &mut watch::Receiver<bool>,
    power: Option<&PowerConfig>,
    off_at: Option<tokio::time::Instant>,
) -> Between {
    let mut requests = sup.owner.power.lock().await;
    // An idle printer with a switch is switched off at `off_at`, once cool.
    let after = power
        .and_then(|p| p.off_after_idle)
        .filter(|_| off_at.is_some());
    // Without one, a timer that never fires (a century away).
    let timer =
        tokio::time::sleep_until(off_at.unwrap_or_else(|| {
            tokio::time::Instant::now() + Duration::from_secs(100 * 365 * 86_400)
        }));
    tokio::pin!(timer);
    let mut due = false;
    loop {
        let news = tokio::select! {
            () = follow.changed() => return Between::Changed,
            _ = retire.changed() => return Between::Changed,
            () = &mut timer, if !due && after.is_some() => {
                due = true;
                None
            }
            Some(request) = requests.recv() => {
                if let (Some(p), Some(reply)) = (power, by_hand(sup, power, request)) {
                    if let Some(why) = switch_off(sup, p, Some(reply), "switched off by hand").await {
                        return Between::Off(why);
                    }
                }
                continue;
            }
            news = link.watch_idle() => Some(news),
        };
        match news {
            Some(IdleNews::Temperatures(t)) => sup.show(|p| p.temperatures = t),
            Some(IdleNews::Halted(message)) => {
                tracing::error!(message, "the printer halted between jobs");
                return Between::Halted(message);
            }
            Some(IdleNews::Rebooted) => {
                tracing::warn!("printer reset between jobs (it said `start`); the next job starts with a fresh handshake");
                return Between::Rebooted;
            }
            Some(IdleNews::Lost(why)) => {
                lost_between_jobs(sup, why);
                return Between::Lost;
            }
            None => {}
        }
        let (Some(p), Some(after), true) = (power, after, due) else {
            continue;
        };
        // Idle long enough: off once cool (never while its fan must cool the hotend).
        match hotend_too_hot(sup, p) {
            None => {
                let why = format!("switched off after {} idle", minutes(after));
                if let Some(why) = switch_off(sup, p, None, &why).await {
                    return Between::Off(why);
                }
                // Not switched: tried again after as long again.
                timer.as_mut().reset(tokio::time::Instant::now() + after);
                due = false;
            }
            Some(hot) => sup.show(|l| {
                l.detail = Some(format!(
                    "idle {}; stays on while its hotend is {hot} (switched off below {} °C)",
                    minutes(after),
                    p.safe_hotend_c
                ))
            }),
        }
    }
}

/// `12 min`, `30 s`.
fn minutes(d: Duration) -> String {
    let s = d.as_secs_f64();
    if s >= 60.0 {
        format!("{} min", crate::names::number((s / 6.0).round() / 10.0))
    } else {
        format!("{} s", crate::names::number(s.round()))
    }
}

/// Why the printer must not be switched off for its heat, if it must not: its hotend at or
/// above `safe_hotend_c`, or not known.
fn hotend_too_hot(sup: &Supervisor, p: &PowerConfig) -> Option<String> {
    let hotend = sup
        .owner
        .live
        .borrow()
        .temperatures
        .and_then(|t| t.hotend_c);
    match hotend {
        Some(c) if c < p.safe_hotend_c => None,
        Some(c) => Some(format!("{c:.0} °C")),
        None => Some("not known".into()),
    }
}

/// An operator's power request while the printer is on and between prints: its reply when
/// the printer is to be switched off now; else answered here (it has no switch, it is on
/// already, or it may not be switched off now).
fn by_hand(
    sup: &Supervisor,
    power: Option<&PowerConfig>,
    request: PowerRequest,
) -> Option<PowerReply> {
    let refused = match power {
        _ if request.asked.elapsed() > POWER_ANSWER => {
            Err("asked too long ago; ask again".to_string())
        }
        None => Err("it has no [printer.power] switch".to_string()),
        Some(_) if request.on => Ok(false),
        Some(_)
            if !request.force
                && !matches!(
                    sup.owner.live.borrow().state,
                    PrinterState::Idle | PrinterState::Maintenance
                ) =>
        {
            Err("a print is still on its bed: clear it first, or switch off with --force".into())
        }
        Some(p) => match hotend_too_hot(sup, p) {
            Some(hot) => Err(format!(
                "its hotend is {hot}: it is switched off only below safe_hotend_c = {} °C",
                p.safe_hotend_c
            )),
            None => return Some(request.reply),
        },
    };
    let _ = request.reply.send(refused);
    None
}

/// Switches the printer off: why it is off when it did (for [`Between::Off`]), else None
/// with the switch's error shown. `reply`: an operator's request to answer.
async fn switch_off(
    sup: &Supervisor,
    p: &PowerConfig,
    reply: Option<PowerReply>,
    why: &str,
) -> Option<String> {
    match p.switch.send(crate::power::Ask::Off).await {
        Ok(_) => {
            tracing::info!(switch = p.switch.kind(), why, "switched the printer off");
            answer(reply, Ok(true));
            Some(why.to_string())
        }
        Err(e) => {
            tracing::warn!(error = %e, "cannot switch the printer off");
            sup.show(|l| l.detail = Some(format!("cannot switch it off: {e}")));
            answer(reply, Err(format!("cannot switch it off: {e}")));
            None
        }
    }
}

/// Answers an operator's power request, if there is one.
fn answer(reply: Option<PowerReply>, result: Result<bool, String>) {
    if let Some(reply) = reply {
        let _ = reply.send(result);
    }
}

/// Whether a printer with a switch is off as the supervisor starts: why, if its switch
/// says so (a switch that cannot be asked, or does not answer, is taken as on).
async fn off_at_start(p: &PowerConfig) -> Option<String> {
    match p.switch.send(crate::power::Ask::State).await {
        Ok(false) => Some("its switch was off when the daemon started".into()),
        Ok(true) | Err(crate::power::PowerError::NoState) => None,
        Err(e) => {
            tracing::warn!(error = %e, "cannot ask the printer's switch whether it is on; taken as on");
            None
        }
    }
}

/// How waiting while switched off ended.
enum OffEnd {
    /// Switch it on: it has work, or an operator asked (their reply).
    On(Option<PowerReply>),
    /// The config changed: look again.
    Again,
    /// The farm stops.
    Stop,
}

/// Shows the printer off (`why`) and waits for work it can take, an operator's request to
/// switch it on, or the end.
async fn while_off(sup: &Supervisor, why: &str, retire: &mut watch::Receiver<bool>) -> OffEnd {
    let farm = &sup.farm;
    let mut requests = sup.owner.power.lock().await;
    loop {
        let mut follow = Follow::new(farm);
        sup.show(|p| {
            p.state = PrinterState::Off;
            p.detail = Some(why.to_string());
            p.temperatures = None;
            p.job = None;
            p.progress = None;
        });
        if job_waiting_for(farm, &sup.name) {
            return OffEnd::On(None);
        }
        tokio::select! {
            () = follow.changed() => {}
            _ = retire.changed() => return OffEnd::Again,
            _ = farm.shutdown.cancelled() => return OffEnd::Stop,
            Some(request) = requests.recv() => {
                if request.asked.elapsed() > POWER_ANSWER {
                    let _ = request.reply.send(Err("asked too long ago; ask again".into()));
                } else if request.on {
                    return OffEnd::On(Some(request.reply));
                } else {
                    let _ = request.reply.send(Ok(false));
                }
            }
        }
    }
}

/// What became of a halted printer while the supervisor waited.
enum Reset {
    /// It said `start`: reset, it may take jobs again.
    Seen,
    /// The link closed: reconnect (a connection that completes its handshake shows the
    /// firmware answers again).
    Lost,
    /// Something else changed (shutdown, a reload): look again.
    NotYet,
}

/// Waits for a halted printer to be reset, showing its temperatures meanwhile.
async fn until_reset(
    sup: &Supervisor,
    link: &mut dyn PrinterLink,
    follow: &mut Follow,
    retire: &mut watch::Receiver<bool>,
) -> Reset {
    loop {
        let news = tokio::select! {
            () = follow.changed() => return Reset::NotYet,
            _ = retire.changed() => return Reset::NotYet,
            news = link.watch_idle() => news,
        };
        match news {
            IdleNews::Temperatures(t) => sup.show(|p| p.temperatures = t),
            // Another halt message of the same halt.
            IdleNews::Halted(_) => {}
            IdleNews::Rebooted => return Reset::Seen,
            IdleNews::Lost(why) => {
                lost_between_jobs(sup, why);
                return Reset::Lost;
            }
        }
    }
}

fn lost_between_jobs(sup: &Supervisor, why: String) {
    tracing::warn!(reason = %why, "printer link lost between jobs; reconnecting");
    sup.show(|p| {
        p.state = PrinterState::Disconnected;
        p.detail = Some(why);
        p.temperatures = None;
    });
}

/// Why `printer` takes no job for its care now, if it takes none: held by hand, or a
/// blocking task due (by the counts and the clock as they are when it would claim one: a
/// task due by days needs no change to be seen, since only a change brings a job).
fn kept_for_care(farm: &Farm, printer: &str) -> Option<super::care::Kept> {
    let config = farm.config();
    let store = farm.store();
    super::care::kept(
        config.tasks_of(printer),
        store.inventory().care.get(printer),
        super::job::now_s(),
    )
}

/// Takes the oldest ready job this printer may print, marking it printing. The search and
/// the change are one request to the job store: supervisors run on several threads, and
/// two of them must never take the same job.
async fn claim_job(farm: &Farm, printer: &str) -> Option<String> {
    let eligible = eligible(farm, printer)?;
    match farm.jobs().claim(printer, eligible).await {
        Ok(job) => job.map(|j| j.id),
        Err(e) => {
            tracing::error!(error = %e, "cannot claim a job");
            None
        }
    }
}

/// Whether a job may go to `printer` now (a ready job is claimed if so); None when the
/// printer is not in the config.
fn eligible(
    farm: &Farm,
    printer: &str,
) -> Option<impl Fn(&super::job::Job) -> bool + Send + 'static> {
    let config = farm.config();
    // A printer only receives G-code made for its machine.
    let machine = config
        .printers
        .iter()
        .find(|p| p.name == printer)
        .map(|p| p.machine.name.clone())?;
    let name = printer.to_string();
    let snapshot = farm.store();
    Some(move |j: &super::job::Job| {
        let printer = name.as_str();
        let served =
            super::farm::folder_rule(&config, j).is_some_and(|r| r.iter().any(|p| p == printer));
        let wanted = j.wanted_printer().is_none_or(|p| p == printer);
        // What it asks of the printer, against what the printer holds as the store had
        // it just before the claim (the store's task serves the claim; a spool loaded
        // meanwhile is seen at the next claim). An idle printer has nothing reserved.
        let fits = || {
            config
                .printers
                .iter()
                .find(|p| p.name == printer)
                .is_some_and(|p| {
                    let offer = super::farm::offer(p, snapshot.inventory(), 0.0);
                    super::filament::routing::refusal(&j.asks, j.need_on(&machine), &offer)
                        .is_none()
                })
        };
        served && wanted && !j.held() && j.gcode_for(&machine).is_some() && fits()
    })
}

/// A ready job `printer` could take now, by the snapshot (no claim is made).
pub(crate) fn job_waiting_for(farm: &Farm, printer: &str) -> bool {
    eligible(farm, printer).is_some_and(|eligible| {
        farm.store()
            .jobs()
            .any(|j| j.state == JobState::Ready && eligible(j))
    })
}

/// How a job's run left its printer.
#[derive(Default)]
struct JobEnd {
    /// The connection was lost.
    lost: bool,
    /// The firmware halted (its message).
    halted: Option<String>,
}

/// Prints one job.
async fn run_job(sup: &Supervisor, job_id: &str, link: &mut dyn PrinterLink) -> JobEnd {
    let (farm, printer) = (&sup.farm, sup.name.as_str());
    let machine = farm
        .config()
        .printers
        .iter()
        .find(|p| p.name == printer)
        .map(|p| p.machine.name.clone());
    // The parts cancelled before this print began (dropped from its first line).
    let (gcode, print_number, cancelled, pace): (PathBuf, u32, Vec<String>, Pace) = {
        let store = farm.store();
        let Some(job) = store.get(job_id) else {
            return JobEnd::default();
        };
        // The printer's pace, from its finished prints the farm still holds.
        let mut paced: Vec<(f64, PaceSample)> = store
            .jobs()
            .filter(|j| j.printer.as_deref() == Some(printer))
            .filter_map(|j| {
                let sample = j.print_report.as_ref()?.pace?;
                Some((j.history.last().map_or(0.0, |h| h.1), sample))
            })
            .collect();
        paced.sort_by(|a, b| a.0.total_cmp(&b.0));
        let pace = Pace::of(paced.into_iter().map(|(_, s)| s));
        let print_number = job.print_number();
        let cancelled = job
            .parts_cancelled_in(print_number)
            .map(|c| c.part.clone())
            .collect();
        let gcode = match machine.and_then(|m| job.gcode_for(&m)) {
            Some(file) => store.job_dir(job_id).join(file),
            None => {
                // The printer's machine changed (a reload) since the claim: not for it.
                drop(store);
                if let Err(e) = farm.jobs().transition(job_id, JobState::Ready, None).await {
                    tracing::error!(error = %e, "cannot put the job back");
                }
                return JobEnd::default();
            }
        };
        (gcode, print_number, cancelled, pace)
    };

    sup.show(|p| {
        p.state = PrinterState::WaitingToHeat;
        p.job = Some(job_id.to_string());
        p.progress = None;
    });
    // Meanwhile the printer is still read (its temperatures, a reset, a lost link).
    let permit = loop {
        let news = tokio::select! {
            permit = farm.heating_permit() => break permit,
            _ = farm.shutdown.cancelled() => None,
            news = link.watch_idle() => Some(news),
        };
        let end = match news {
            Some(IdleNews::Temperatures(t)) => {
                sup.show(|p| p.temperatures = t);
                continue;
            }
            // The job's start greets it afresh.
            Some(IdleNews::Rebooted) => continue,
            Some(IdleNews::Lost(why)) => {
                lost_between_jobs(sup, why);
                JobEnd {
                    lost: true,
                    halted: None,
                }
            }
            Some(IdleNews::Halted(message)) => {
                tracing::error!(message, "the printer halted while its job waited to heat");
                JobEnd {
                    lost: false,
                    halted: Some(message),
                }
            }
            None => JobEnd::default(),
        };
        // Nothing was sent to the printer: the job waits for the next start, or for
        // the next printer.
        if let Err(e) = farm.jobs().transition(job_id, JobState::Ready, None).await {
            tracing::error!(error = %e, "cannot put the job back");
        }
        sup.show(|p| p.job = None);
        return end;
    };
    tracing::info!(gcode = %gcode.display(), "starting print");
    // The odometer: what the print pushed is measured from it, even after a kill.
    let odometer_path = super::usage::path(&farm.config().spool_dir, printer);
    let mut odometer = super::usage::Odometer::start(farm, printer, job_id, &gcode);
    odometer.write(&odometer_path).await;
    sup.show(|p| {
        p.state = PrinterState::Printing;
        p.detail = None;
    });

    let (control_tx, control_rx) = mpsc::channel(8);
    sup.owner.print.send_replace(Some(control_tx.clone()));
    let (progress_tx, mut progress_rx) = watch::channel(LiveProgress::default());

    let mut run = run::JobRun::new();
    let mut permit = Some(permit);
    let print = link.print(&gcode, cancelled, pace, control_rx, progress_tx);
    tokio::pin!(print);
    let mut progress_open = true;
    let outcome = loop {
        tokio::select! {
            outcome = &mut print => break outcome,
            changed = progress_rx.changed(), if progress_open => {
                if changed.is_err() { progress_open = false; continue; }
                let live = progress_rx.borrow_and_update().clone();
                let step = run.progress(&live);
                if let Some(write) = step.odometer {
                    odometer.lines_acked = write.lines_acked;
                    if let Some(cancels) = write.cancels {
                        odometer.cancels = cancels;
                    }
                    odometer.write(&odometer_path).await;
                }
                if !step.record_parts.is_empty() {
                    record_parts(farm, job_id, print_number, &step.record_parts).await;
                }
                if step.release_permit {
                    permit = None;
                    tracing::info!("heat-up done; heating permit released");
                }
                sup.show(|p| {
                    p.state = step.state;
                    p.detail = step.detail;
                    show_progress(p, live);
                });
            }
            // A stop requested by shutdown (`StopOwner::stop_prints`) is a cancel that
            // ends as interrupted rather than cancelled.
            _ = farm.stop_prints.cancelled(), if !run.stopped() => {
                if run.stop() {
                    let _ = control_tx.send(PrintCommand::Cancel).await;
                }
            }
        }
    };
    drop(permit);
    if progress_open {
        let live = progress_rx.borrow_and_update().clone();
        sup.show(|p| show_progress(p, live));
    }
    if matches!(outcome, Err(PrintFailure::Lost(_))) {
        // Whatever was read last is no longer current.
        sup.show(|p| p.temperatures = None);
    }
    sup.owner.print.send_replace(None);

    let ending = run.end(&outcome, progress_rx.borrow().lines_acked);
    // A job that failed to load sent nothing: the bed is as it was, and nobody needs to
    // clear it. A print that ended well may be ejected; any other waits for a person.
    if !ending.sent_nothing {
        eject::close_gate(farm, printer, job_id, ending.may_eject).await;
    }
    // What the print pushed: every line of a finished one, else what was acknowledged.
    odometer.lines_acked = ending.lines_acked;
    let mut usage = odometer.measure(super::job::now_s()).await;
    if let Some(u) = &mut usage {
        u.failed = ending.state == JobState::Failed;
    }
    // One print per job: its other copies are jobs of their own.
    let printed = outcome.ok();
    let recorded = farm
        .jobs()
        .record_outcome(
            job_id,
            ending.state,
            ending.reason,
            JobChange::Printed {
                report: printed,
                usage: usage.map(|usage| Use {
                    print: odometer.print,
                    usage,
                }),
            },
        )
        .await;
    // The odometer stays: the next start reads it, and records its use only if the job
    // has none for this print (removing it here would free space under a full disk that
    // the outcome waits for, and buys nothing).
    if let Err(e) = recorded {
        tracing::error!(error = %e, "cannot record the print's outcome");
    }
    sup.show(|p| {
        p.state = if ending.sent_nothing {
            PrinterState::Idle
        } else {
            PrinterState::BedNotCleared
        };
        p.detail = None;
        p.progress = None;
    });
    JobEnd {
        lost: ending.lost,
        halted: ending.halted,
    }
}

/// Records in the job the parts its print `print` dropped, with where: one the operator
/// cancelled before the print is completed with it, any other added.
async fn record_parts(farm: &Farm, job_id: &str, print: u32, dropped: &[super::job::PartCancel]) {
    let change = JobChange::PartsDropped {
        print,
        dropped: dropped.to_vec(),
    };
    let recorded = farm.jobs().update(job_id, change).await;
    if let Err(e) = recorded {
        tracing::error!(error = %e, "cannot record the parts of the plate dropped");
    }
}

/// A print's progress, and its temperatures once the printer has reported them (until
/// then the last ones read before the job stand).
fn show_progress(p: &mut PrinterLive, live: LiveProgress) {
    if live.hotend_c.is_some() || live.bed_c.is_some() {
        p.temperatures = Some(PrinterTemperatures {
            hotend_c: live.hotend_c,
            hotend_target_c: live.hotend_target_c,
            bed_c: live.bed_c,
            bed_target_c: live.bed_target_c,
        });
    }
    p.progress = Some(live);
}

fn live_progress(p: &PrintProgress, heated: bool, paused: bool, plate: &Plate) -> LiveProgress {
    // A file's pause is shown once the head is parked: an operator told to act while it
    // still moves would reach into a moving printer (and the park is still the print's).
    let pause = p
        .pause
        .clone()
        .filter(|_| p.state == PrintState::WaitingForOperator);
    let time_left = TimeLeft {
        planned_s: plate.estimate.left_after_acked(p.lines_acked, plate.ahead),
        pace: plate.pace,
        heating: !heated,
        settings: plate.settings,
    };
    LiveProgress {
        parts_cancelled: p.cancelled_parts.iter().map(|c| plate.dropped(c)).collect(),
        stop_wait: p.stop_wait.clone(),
        lines_acked: p.lines_acked,
        lines_total: p.lines_total,
        hotend_c: p.hotend.map(|t| t.current),
        hotend_target_c: p.hotend.and_then(|t| t.target),
        bed_c: p.bed.map(|t| t.current),
        bed_target_c: p.bed.and_then(|t| t.target),
        elapsed_s: p.elapsed_s,
        remaining_s: Some(time_left.seconds()),
        time_left: Some(time_left),
        heated,
        paused,
        pause,
    }
}

fn printer_temperatures(t: &Temperatures) -> PrinterTemperatures {
    PrinterTemperatures {
        hotend_c: t.hotend.map(|t| t.current),
        hotend_target_c: t.hotend.and_then(|t| t.target),
        bed_c: t.bed.map(|t| t.current),
        bed_target_c: t.bed.and_then(|t| t.target),
    }
}

/// What a print knows of its plate: its program's lines and layers, to say where a part
/// was dropped; the planner's estimate of its commands and its printer's pace, to say
/// how long it has left.
struct Plate {
    program: GcodeProgram,
    map: Option<crate::marlin::plate::PlateMap>,
    estimate: crate::marlin::estimate::Estimate,
    /// The moves its printer may hold acknowledged but not yet made.
    ahead: usize,
    pace: Pace,
    /// Whose planner settings the estimate was made with.
    settings: super::time_left::Settings,
}

impl Plate {
    fn dropped(&self, c: &crate::marlin::stream::CancelledPart) -> super::job::PartCancel {
        let layer = self.map.as_ref().and_then(|m| m.layer_at(c.from));
        super::job::PartCancel {
            part: c.name.clone(),
            print: 0,
            at_s: super::job::now_s(),
            dropped: Some(super::job::Dropped {
                command: c.from,
                line: self.program.source_line(c.from).unwrap_or(0),
                layer: layer.map(|l| l.number),
                z_mm: layer.map(|l| l.z_mm),
            }),
        }
    }
}

/// The real printer connection: `crispen::marlin::stream` on a serial port or pty.
pub(crate) struct MarlinConnector {
    pub port: PathBuf,
    pub firmware: crate::marlin::firmware::Firmware,
    pub baud: u32,
    pub heat_timeout: Duration,
    /// How the pauses files ask for are made on this printer.
    pub pause: PauseSettings,
}

impl Connector for MarlinConnector {
    fn connect(&self) -> BoxFuture<'_, Result<Box<dyn PrinterLink>, ConnectError>> {
        Box::pin(async move {
            let mut opts = StreamOptions::for_firmware(self.firmware);
            opts.baud = self.baud;
            opts.protocol.heat_timeout = self.heat_timeout;
            opts.pause = Some(self.pause.clone());
            let connection = Connection::open(&self.port, &opts).await?;
            Ok(Box::new(MarlinLink {
                connection,
                firmware: self.firmware,
            }) as Box<dyn PrinterLink>)
        })
    }
}

struct MarlinLink {
    connection: Connection,
    firmware: crate::marlin::firmware::Firmware,
}

impl PrinterLink for MarlinLink {
    fn print<'a>(
        &'a mut self,
        gcode: &'a Path,
        cancelled: Vec<String>,
        pace: Pace,
        mut control: mpsc::Receiver<PrintCommand>,
        progress: watch::Sender<LiveProgress>,
    ) -> BoxFuture<'a, Result<PrintReport, PrintFailure>> {
        Box::pin(async move {
            // Reading and checking a file of millions of lines is blocking work; so is
            // following its plate's layers and planning its moves.
            let (path, firmware) = (gcode.to_path_buf(), self.firmware);
            // The printer's own planner settings where it reported them (M503 at
            // connect), else the machine's stock ones.
            let (limits, settings) =
                super::time_left::Settings::limits(firmware, self.connection.settings());
            tracing::debug!(?settings, ?limits, "the time left's planner settings");
            let plate = tokio::task::spawn_blocking(move || {
                let program = GcodeProgram::load_for(&path, firmware)?;
                let map = program.marks().map(|marks| {
                    crate::marlin::plate::PlateMap::read(program.iter(), marks, firmware)
                });
                let estimate = crate::marlin::estimate::estimate_with(program.iter(), limits);
                Ok::<_, GcodeError>(Plate {
                    program,
                    map,
                    estimate,
                    ahead: crate::marlin::estimate::moves_ahead(firmware),
                    pace,
                    settings,
                })
            })
            .await
            .map_err(PrintFailure::LoaderCrashed)??;
            let program = &plate.program;
            let heat_end = heat_up_end(program.iter());
            let part_of = |name: &str| {
                let part = program.marks().and_then(|m| m.find(name));
                if part.is_none() {
                    tracing::warn!(
                        part = name,
                        "no such part in the plate's G-code; nothing dropped"
                    );
                }
                part
            };
            let dropped: Vec<u16> = cancelled.iter().filter_map(|n| part_of(n)).collect();
            let (stream_tx, stream_rx) = mpsc::channel(8);
            let (inner_tx, mut inner_rx) = watch::channel(PrintProgress::default());
            let print = self
                .connection
                .print_plate(program, &dropped, stream_rx, inner_tx);
            tokio::pin!(print);
            let mut control_open = true;
            let mut progress_open = true;
            let mut last_forward = std::time::Instant::now() - Duration::from_secs(1);
            let mut last_heated = false;
            let mut last_paused = false;
            let mut last_pause = None;
            let mut last_parts = 0;
            let mut last_stop_wait = None;
            // For the printer's pace: when the heat-up ended, and whether the print kept
            // to its plan (no pause, no part dropped).
            let mut heated_at = None;
            let mut as_planned = dropped.is_empty();
            let result = loop {
                tokio::select! {
                    result = &mut print => break result,
                    command = control.recv(), if control_open => match command {
                        None => control_open = false,
                        Some(c) => {
                            let c = match c {
                                PrintCommand::Pause => StreamControl::Pause,
                                PrintCommand::Resume => StreamControl::Resume,
                                PrintCommand::Cancel => StreamControl::Cancel,
                                PrintCommand::CancelPart(name) => match part_of(&name) {
                                    Some(part) => StreamControl::CancelPart(part),
                                    None => continue,
                                },
                            };
                            let _ = stream_tx.send(c).await;
                        }
                    },
                    changed = inner_rx.changed(), if progress_open => {
                        if changed.is_err() {
                            progress_open = false;
                            continue;
                        }
                        let p = inner_rx.borrow_and_update().clone();
                        // Past the heat-up in acknowledgements, and not heating by the
                        // printer's own reports (Ultimaker2Marlin acknowledges moves queued
                        // behind an M109 before it finishes).
                        let heated = heat_end.is_none_or(|i| p.lines_acked > i)
                            && p.state != PrintState::Heating;
                        // Paused once the printer has drained the lines in flight: until
                        // then it is still printing them.
                        let paused = p.state == PrintState::Paused;
                        // The streamer publishes on every acknowledgement; the farm only
                        // needs a few updates a second, or at once when heat-up or pause
                        // state changes (the heating permit waits on it).
                        let due = last_forward.elapsed() >= Duration::from_millis(250)
                            || heated != last_heated
                            || paused != last_paused
                            || p.pause != last_pause
                            || p.cancelled_parts.len() != last_parts
                            || p.stop_wait != last_stop_wait;
                        as_planned &= !paused && p.pause.is_none() && p.cancelled_parts.is_empty();
                        if !due {
                            continue;
                        }
                        if heated && !last_heated {
                            heated_at = Some(std::time::Instant::now());
                        }
                        last_forward = std::time::Instant::now();
                        last_heated = heated;
                        last_paused = paused;
                        last_pause = p.pause.clone();
                        last_stop_wait = p.stop_wait.clone();
                        last_parts = p.cancelled_parts.len();
                        progress.send_replace(live_progress(&p, heated, paused, &plate));
                    }
                }
            };
            // The last figures, which the throttle above may have held back: a finished
            // print shows all its lines acknowledged.
            progress.send_replace(live_progress(
                &inner_rx.borrow(),
                last_heated,
                last_paused,
                &plate,
            ));
            match result {
                Ok(report) => {
                    let mut report = PrintReport::from(report);
                    report.pace = heated_at.filter(|_| as_planned).map(|at| PaceSample {
                        planned_s: plate.estimate.left_after(heat_end.map_or(0, |i| i + 1)),
                        took_s: at.elapsed().as_secs_f64(),
                    });
                    Ok(report)
                }
                Err(e) => Err(PrintFailure::of(e)),
            }
        })
    }

    fn watch_idle(&mut self) -> BoxFuture<'_, IdleNews> {
        Box::pin(async move {
            loop {
                match self.connection.idle_for(Duration::from_secs(3600)).await {
                    Ok(Idle::Quiet) => {}
                    Ok(Idle::Rebooted) => return IdleNews::Rebooted,
                    Ok(Idle::Temperatures(t)) => {
                        return IdleNews::Temperatures(Some(printer_temperatures(&t)))
                    }
                    Ok(Idle::Silent) => return IdleNews::Temperatures(None),
                    Ok(Idle::Halted(message)) => return IdleNews::Halted(message),
                    Err(e) => return IdleNews::Lost(e.to_string()),
                }
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heat_up_ends_at_last_wait_before_extrusion() {
        let prog: Vec<String> = [
            "M140 S60",
            "M104 S200",
            "M190 S60",
            "M109 S200",
            "G28",
            "G1 X10 E5",
            "M109 S210",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        assert_eq!(heat_up_end(&prog), Some(3));
        assert_eq!(heat_up_end(&prog[..2]), None);
    }

    /// Eight printers' supervisors, on a multi-threaded runtime, claiming 200 ready jobs
    /// at once through the store's task: each job made for their machine is claimed
    /// exactly once, by the printer it is recorded for, and no other job is.
    #[tokio::test(flavor = "multi_thread", worker_threads = 4)]
    async fn concurrent_claims_take_each_job_once() {
        use crate::daemon::job::ForMachine;
        let tmp = tempfile::tempdir().unwrap();
        let hot = tmp.path().join("hot");
        std::fs::create_dir(&hot).unwrap();
        let printers: Vec<String> = (0..8).map(|i| format!("p{i}")).collect();
        let mut text = String::from("[spool]\ndir = \"spool\"\n");
        for p in &printers {
            text += &format!(
                "[[printer]]\nname = \"{p}\"\nfirmware = \"marlin2\"\n[printer.simulate]\n"
            );
        }
        text += &format!(
            "[[folder]]\npath = {:?}\nheight_mm = 30\nprinters = {:?}\n",
            hot.display().to_string(),
            printers
        );
        let config =
            crate::daemon::config::Config::parse(&text, &tmp.path().join("crispen.toml")).unwrap();
        let mut store =
            crate::daemon::store::spool::Spool::open(&tmp.path().join("spool")).unwrap();
        let mut ids = Vec::new();
        for i in 0..200 {
            let file = hot.join(format!("m{i}.stl"));
            std::fs::write(&file, b"solid x\nendsolid x\n").unwrap();
            let job = store.admit(&file, &hot).unwrap();
            store
                .transition(&job.id, JobState::Preparing, None)
                .unwrap();
            // Every tenth job was made only for another machine: no printer here takes it.
            let machine = if i % 10 == 9 {
                "ultimaker2"
            } else {
                "marlin-175"
            };
            store
                .transition_with(&job.id, JobState::Ready, None, |j| {
                    let gcode = ForMachine::Gcode(format!("m{i}.stl.{machine}.gcode"));
                    j.machines.insert(machine.to_string(), gcode);
                })
                .unwrap();
            if machine == "marlin-175" {
                ids.push(job.id);
            }
        }
        let store = crate::daemon::store::spool::SpoolStore::from(store);
        let (farm, _owners, task) = Farm::new(config, store);
        tokio::spawn(task);
        let start = Arc::new(tokio::sync::Barrier::new(printers.len()));
        let tasks: Vec<_> = printers
            .iter()
            .map(|p| {
                let (farm, start, p) = (Arc::clone(&farm), Arc::clone(&start), p.clone());
                tokio::spawn(async move {
                    start.wait().await;
                    let mut mine = Vec::new();
                    while let Some(id) = claim_job(&farm, &p).await {
                        mine.push(id);
                    }
                    mine
                })
            })
            .collect();
        let mut claimed = Vec::new();
        for task in tasks {
            claimed.push(task.await.unwrap());
        }
        let mut all: Vec<String> = claimed.concat();
        all.sort();
        assert_eq!(
            all, ids,
            "each ready job made for the printers' machine claimed exactly once, no other"
        );
        assert!(
            claimed.iter().filter(|c| !c.is_empty()).count() > 1,
            "the printers took turns"
        );
        let store = farm.store();
        for (p, jobs) in printers.iter().zip(&claimed) {
            for id in jobs {
                let job = store.get(id).unwrap();
                assert_eq!(job.state, JobState::Printing);
                assert_eq!(job.printer.as_deref(), Some(p.as_str()));
            }
        }
    }
}
