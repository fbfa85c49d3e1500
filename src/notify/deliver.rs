//! The notification tasks of a running daemon. One observes the farm (every change of
//! its published state, [`crate::daemon::farm::FarmWatch`]), turns what changed into
//! events ([`super::observe`]) and writes each into the queue of every receiver that
//! wants it; then it wakes their tasks. Each receiver's task sends its queue oldest
//! first, one event at a time: a 2xx answer removes it; a failure keeps it and waits
//! (doubling from 1 s up to `backoff_max_s`) before the same event, with the same id, is
//! tried again. An event is dropped, and logged, once it is older than `retry_for_s`, once
//! `max_attempts` failed in this run, or when the receiver refuses it for good (a 4xx
//! answer other than 408 and 429).

use super::counts::{Counts, Outcome, Tally};
use super::event::Event;
use super::observe::{Look, Observer};
use super::outbox::Outbox;
use super::wire;
use crate::daemon::config::notify::Receiver;
use crate::daemon::farm::Farm;
use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};
use tokio::sync::{watch, Notify};
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;

/// After the stop, how long receivers may still take what was queued before the daemon
/// exits (what is left waits on disk for the next run).
pub(crate) const GRACE: Duration = Duration::from_secs(3);
/// The first wait after a failed attempt; it doubles up to the receiver's `backoff_max_s`.
const FIRST_BACKOFF: Duration = Duration::from_secs(1);

fn now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// A receiver's queue, the wake-up of its task, and whether its task is idle (nothing
/// pending that it could send now).
struct Queue {
    receiver: Receiver,
    outbox: Outbox,
    wake: Arc<Notify>,
    idle: watch::Receiver<bool>,
    tally: watch::Sender<Tally>,
}

/// Runs the notifications until `stop`: the observer and one task per receiver. Opens
/// the queues first: a spool where they cannot be made is an error at once. Returns the
/// receivers' counts with the task.
pub fn run(
    farm: Arc<Farm>,
    stop: CancellationToken,
) -> std::io::Result<(
    Counts,
    impl std::future::Future<Output = ()> + Send + 'static,
)> {
    let config = farm.config();
    let mut senders = JoinSet::new();
    let stop_senders = CancellationToken::new();
    let mut queues = Vec::new();
    let mut tallies = Vec::new();
    for receiver in &config.notify.receivers {
        let outbox = Outbox::open(&config.spool_dir, &receiver.name)?;
        let (tally, tally_rx) = watch::channel(Tally::default());
        tallies.push((receiver.name.clone(), tally_rx));
        let wake = Arc::new(Notify::new());
        let (idle_tx, idle) = watch::channel(false);
        senders.spawn(send_loop(
            receiver.clone(),
            outbox.clone(),
            Arc::clone(&wake),
            idle_tx,
            tally.clone(),
            stop_senders.clone(),
        ));
        queues.push(Queue {
            receiver: receiver.clone(),
            outbox,
            wake,
            idle,
            tally,
        });
    }
    let task = async move {
        if queues.is_empty() {
            // Nothing to send; the task still runs until the stop, as every task of
            // the service does (one that ends is taken for a failure).
            stop.cancelled().await;
        } else {
            tracing::info!(receivers = queues.len(), "notifications: sending");
            observe_loop(&farm, &queues, &stop).await;
            // What the stop itself caused (an interrupted print) is queued; give the
            // receivers a moment to take it.
            let all_idle = async {
                for q in &queues {
                    let mut idle = q.idle.clone();
                    let _ = idle.wait_for(|i| *i).await;
                }
            };
            let _ = tokio::time::timeout(GRACE, all_idle).await;
        }
        stop_senders.cancel();
        while let Some(ended) = senders.join_next().await {
            if let Err(e) = ended {
                if e.is_panic() {
                    std::panic::resume_unwind(e.into_panic());
                }
            }
        }
    };
    Ok((Counts::new(tallies), task))
}

/// Observes the farm until `stop`, then looks once more (the stop's own changes).
async fn observe_loop(farm: &Farm, queues: &[Queue], stop: &CancellationToken) {
    let config = farm.config();
    let mut observer = Observer::new(
        &config.farm.host,
        config.store.is_some(),
        config.notify.dashboard.clone(),
    )
    .with_cameras(
        config
            .printers
            .iter()
            .filter(|p| p.camera.is_some())
            .map(|p| p.name.clone())
            .collect(),
    );
    let mut watch = farm.watch();
    loop {
        let events = {
            let snapshot = farm.store();
            let printers = farm.local_printers();
            let hosts = farm.shared().map(|v| v.hosts).unwrap_or_default();
            observer.observe(Look {
                jobs: snapshot.jobs(),
                printers: &printers,
                hosts: &hosts,
                inventory: snapshot.inventory(),
                spool_low_g: farm.config().farm.spool_low_g,
                now: now(),
            })
        };
        if !events.is_empty() {
            queue(queues, events).await;
        }
        if stop.is_cancelled() {
            return;
        }
        tokio::select! {
            () = watch.changed() => {}
            () = stop.cancelled() => {}
        }
    }
}

/// Writes each event into the queues that want it, then wakes their tasks.
async fn queue(queues: &[Queue], events: Vec<Event>) {
    for event in events {
        tracing::info!(
            event = event.event.name(),
            id = %event.id,
            printer = event.printer.as_deref().unwrap_or(""),
            job = event.job.as_ref().map_or("", |j| j.id.as_str()),
            "notification"
        );
        let wanted: Vec<(usize, Outbox)> = queues
            .iter()
            .enumerate()
            .filter(|(_, q)| q.receiver.wants(event.event.name()))
            .map(|(i, q)| (i, q.outbox.clone()))
            .collect();
        let written = tokio::task::spawn_blocking(move || {
            wanted
                .into_iter()
                .map(|(i, outbox)| (i, outbox.put(&event)))
                .collect::<Vec<_>>()
        })
        .await
        .unwrap_or_default();
        for (i, result) in written {
            if let Err(e) = result {
                // The spool is what the farm runs on; when it cannot take a small file
                // the operator hears of it from the store's own errors too.
                let q = &queues[i];
                tracing::error!(receiver = %q.receiver.name, error = %e, "notification not queued: lost");
                Tally::count(&q.tally, Outcome::Dropped);
            }
        }
    }
    for q in queues {
        q.wake.notify_one();
    }
}

/// Sends `receiver`'s queue until `stop`.
async fn send_loop(
    receiver: Receiver,
    outbox: Outbox,
    wake: Arc<Notify>,
    idle: watch::Sender<bool>,
    tally: watch::Sender<Tally>,
    stop: CancellationToken,
) {
    let name = receiver.name.clone();
    let mut attempts: HashMap<String, u32> = HashMap::new();
    let mut backoff = FIRST_BACKOFF.min(receiver.backoff_max);
    loop {
        let listed = {
            let outbox = outbox.clone();
            tokio::task::spawn_blocking(move || outbox.pending()).await
        };
        let ids = match listed {
            Ok(Ok((ids, dropped))) => {
                for id in dropped {
                    tracing::error!(receiver = %name, id = %id, "notification dropped: the queue is full (the receiver has been down long)");
                    Tally::count(&tally, Outcome::Dropped);
                }
                ids
            }
            Ok(Err(e)) => {
                tracing::error!(receiver = %name, error = %e, dir = %outbox.dir().display(), "cannot read the notification queue");
                Vec::new()
            }
            Err(_) => Vec::new(),
        };
        let Some(id) = ids.first().cloned() else {
            idle.send_replace(true);
            tokio::select! {
                () = wake.notified() => {}
                () = stop.cancelled() => return,
            }
            idle.send_replace(false);
            continue;
        };
        idle.send_replace(false);
        let read = {
            let (outbox, id) = (outbox.clone(), id.clone());
            tokio::task::spawn_blocking(move || outbox.read(&id)).await
        };
        let event = match read {
            Ok(Ok(e)) => e,
            Ok(Err(e)) => {
                tracing::error!(receiver = %name, "{e}");
                Tally::count(&tally, Outcome::Dropped);
                // It was set aside; should that have failed too, it is not read again
                // at once.
                tokio::select! {
                    () = tokio::time::sleep(backoff) => {}
                    () = stop.cancelled() => return,
                }
                continue;
            }
            Err(_) => return,
        };
        let tried = attempts.get(&id).copied().unwrap_or(0);
        let age = now() - event.time;
        let give_up = if age > receiver.retry_for.as_secs_f64() {
            Some(format!("not delivered within {:?}", receiver.retry_for))
        } else if tried >= receiver.max_attempts {
            Some(format!("{tried} attempts failed"))
        } else {
            None
        };
        if let Some(why) = give_up {
            drop_event(&outbox, &name, &tally, &event, &why).await;
            attempts.remove(&id);
            continue;
        }
        let sent = tokio::select! {
            sent = wire::send(&receiver, &event) => sent,
            () = stop.cancelled() => return,
        };
        match sent {
            Ok(answer) if answer.ok() => {
                let removed = {
                    let (outbox, id) = (outbox.clone(), id.clone());
                    tokio::task::spawn_blocking(move || outbox.remove(&id)).await
                };
                if let Ok(Err(e)) = removed {
                    // It would be sent again and again: stop rather than spam.
                    tracing::error!(receiver = %name, error = %e, "cannot remove a delivered notification from the queue; notifications to this receiver stop");
                    return;
                }
                tracing::info!(receiver = %name, id = %id, event = event.event.name(), status = answer.status, "notification delivered");
                Tally::count(&tally, Outcome::Delivered);
                attempts.remove(&id);
                backoff = FIRST_BACKOFF.min(receiver.backoff_max);
                continue;
            }
            Ok(answer) if answer.permanent() => {
                let why = format!("refused with HTTP {}: {}", answer.status, answer.body);
                drop_event(&outbox, &name, &tally, &event, &why).await;
                attempts.remove(&id);
                continue;
            }
            Ok(answer) => {
                tracing::warn!(receiver = %name, id = %id, status = answer.status, body = %answer.body, retry_in_s = backoff.as_secs_f64(), "notification not taken; retrying");
            }
            Err(e) => {
                tracing::warn!(receiver = %name, id = %id, error = %e, retry_in_s = backoff.as_secs_f64(), "notification not sent; retrying");
            }
        }
        Tally::count(&tally, Outcome::Error);
        *attempts.entry(id).or_insert(0) += 1;
        tokio::select! {
            () = tokio::time::sleep(backoff) => {}
            () = stop.cancelled() => return,
        }
        backoff = (backoff * 2).min(receiver.backoff_max);
    }
}

async fn drop_event(
    outbox: &Outbox,
    name: &str,
    tally: &watch::Sender<Tally>,
    event: &Event,
    why: &str,
) {
    tracing::error!(receiver = %name, id = %event.id, event = event.event.name(), "notification dropped: {why}");
    Tally::count(tally, Outcome::Dropped);
    let (outbox, id) = (outbox.clone(), event.id.clone());
    let _ = tokio::task::spawn_blocking(move || outbox.remove(&id)).await;
}
