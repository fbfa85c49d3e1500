//! The store's task end to end, through its handle over the embedded spool: what a kept
//! reason says, which jobs the snapshot keeps live, and what it counts, also of changes
//! another host made. Apart from `task.rs` because they use every part of the store (the
//! spool among them), which the task itself does not depend on.

use super::change::{JobChange, Use};
use super::handle::StoreHandle;
use super::history::{self, Retention};
use super::job_store::{JobEdit, JobStore, RetiredJob};
use super::rules::StateFilter;
use super::spool;
use super::task::{spawn, spawn_with};
use crate::daemon::job::{Job, JobState, PrinterGate, StoreError};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;

/// A reason given to the store's task is kept (and so shown in the status and the
/// history) with the spool's paths made relative.
#[tokio::test]
async fn a_kept_reason_names_no_spool_path() {
    let tmp = tempfile::tempdir().unwrap();
    let hot = tmp.path().join("hot");
    std::fs::create_dir(&hot).unwrap();
    let root = tmp.path().join("spool");
    let store = spool::SpoolStore::open(&root).unwrap();
    let handle = spawn_with(store, Retention::default());
    std::fs::write(hot.join("a.gcode"), b"G28\n").unwrap();
    let job = handle.admit(&hot.join("a.gcode"), &hot, &[]).await.unwrap();
    let model = root.join("jobs").join(&job.id).join("a.gcode");
    let reason = format!("not G-code: {}: line 1", model.display());
    handle
        .transition(&job.id, JobState::Failed, Some(reason))
        .await
        .unwrap();
    let kept = handle
        .snapshot()
        .get(&job.id)
        .unwrap()
        .reason
        .clone()
        .unwrap();
    assert_eq!(kept, format!("not G-code: jobs/{}/a.gcode: line 1", job.id));
}

/// Through the store's task: retired jobs leave the published snapshot (beyond
/// `live_jobs` at the change that made one too many, older than `live_for` at a
/// round), the history pages through them, and one is found by id; what pictures a
/// job has is in the snapshot, looked at when the job changed.
#[tokio::test]
async fn the_snapshot_keeps_live_jobs_and_the_history_the_rest() {
    let tmp = tempfile::tempdir().unwrap();
    let hot = tmp.path().join("hot");
    std::fs::create_dir(&hot).unwrap();
    let store = spool::SpoolStore::open(&tmp.path().join("spool")).unwrap();
    let retention = Retention {
        live_for: std::time::Duration::from_secs(86_400),
        live_jobs: 2,
        keep_for: None,
    };
    let handle = spawn_with(store, retention);
    let mut ids = Vec::new();
    for i in 0..4 {
        let model = hot.join(format!("m{i}.stl"));
        std::fs::write(&model, b"solid x\nendsolid x\n").unwrap();
        let job = handle.admit(&model, &hot, &[]).await.unwrap();
        ids.push(job.id);
    }
    let snapshot = handle.snapshot();
    assert!(snapshot.pictures(&ids[0]).is_empty());
    std::fs::write(
        snapshot.job_dir(&ids[0]).join(crate::preview::AFTER_PNG),
        b"png",
    )
    .unwrap();
    let cancel = |id: String| {
        let handle = handle.clone();
        async move {
            handle
                .transition(&id, JobState::Cancelled, None)
                .await
                .unwrap()
        }
    };
    cancel(ids[0].clone()).await;
    assert_eq!(
        handle.snapshot().pictures(&ids[0]),
        [crate::preview::AFTER_PNG]
    );
    cancel(ids[1].clone()).await;
    assert!(handle.snapshot().get(&ids[0]).is_some(), "two finished");
    cancel(ids[2].clone()).await;
    let snapshot = handle.snapshot();
    let live: Vec<&str> = snapshot.jobs().map(|j| j.id.as_str()).collect();
    assert_eq!(
        live,
        &ids[1..],
        "the oldest of three finished retired at once"
    );

    let two_days_on = crate::daemon::job::now_s() + 2.0 * 86_400.0;
    let moved = handle.retire(two_days_on).await.unwrap();
    assert_eq!(moved, ids[1..3].to_vec());
    let snapshot = handle.snapshot();
    let live: Vec<&str> = snapshot.jobs().map(|j| j.id.as_str()).collect();
    assert_eq!(live, [ids[3].as_str()]);

    let mut paged = Vec::new();
    let mut next = None;
    loop {
        let page = handle.history(next, 1).await.unwrap();
        paged.extend(page.jobs.iter().map(|j| j.id.clone()));
        next = page.next;
        if next.is_none() {
            break;
        }
    }
    assert_eq!(paged, [&*ids[2], &ids[1], &ids[0]], "newest first");
    let retired = handle.retired(&ids[0]).await.unwrap().unwrap();
    assert_eq!(retired.record.state, JobState::Cancelled);
    assert!(handle.retired(&ids[3]).await.unwrap().is_none());
}

/// 3,000 jobs finishing within a minute (three bursts of 1,000, each finished as fast
/// as the store takes them) never leave more than `live_jobs` finished jobs live, as
/// every reply (sent after its snapshot) and the snapshot after each burst show. They
/// once all stayed live until the next round, up to ten minutes later, and every
/// status paid for them. The counts have every change.
#[tokio::test]
async fn a_burst_of_finished_jobs_never_exceeds_the_live_count() {
    use futures_util::future::join_all;
    const LIVE: usize = 50;
    const BURST: usize = 1_000;
    // 6,000 synced writes: in memory where there is a tmpfs (seconds, not minutes on
    // a busy disk); what is tested is the live count, not the disk.
    let tmp = tempfile::tempdir_in("/dev/shm")
        .or_else(|_| tempfile::tempdir())
        .unwrap();
    let hot = tmp.path().join("hot");
    std::fs::create_dir(&hot).unwrap();
    let store = spool::SpoolStore::open(&tmp.path().join("spool")).unwrap();
    let retention = Retention {
        live_for: std::time::Duration::from_secs(86_400),
        live_jobs: LIVE,
        keep_for: None,
    };
    let handle = spawn_with(store, retention);
    let mut last = String::new();
    for burst in 1..=3 {
        let admitted = join_all((0..BURST).map(|i| {
            let (handle, hot) = (handle.clone(), hot.clone());
            async move {
                let model = hot.join(format!("b{burst}-{i}.gcode"));
                std::fs::write(&model, b"G28\n").unwrap();
                handle.admit(&model, &hot, &[]).await.unwrap().id
            }
        }))
        .await;
        let finished = join_all(admitted.iter().enumerate().map(|(i, id)| {
            let handle = handle.clone();
            // Every way a job ends for good.
            let to = [JobState::Cancelled, JobState::Failed][i % 2];
            async move {
                handle.transition(id, to, None).await.unwrap();
                handle.snapshot().finished_live()
            }
        }))
        .await;
        let most = finished.into_iter().max().unwrap();
        assert!(most <= LIVE, "burst {burst}: {most} finished jobs live");
        let snapshot = handle.snapshot();
        assert_eq!(snapshot.finished_live(), LIVE, "burst {burst}");
        assert_eq!(snapshot.jobs().count(), LIVE, "burst {burst}: only those");
        let counts = snapshot.counts();
        assert_eq!(counts.entered(JobState::Queued), (burst * BURST) as u64);
        assert_eq!(counts.finished(), (burst * BURST) as u64);
        last = admitted.last().unwrap().clone();
    }
    // The newest stay live; the rest are in the history.
    assert!(handle.snapshot().get(&last).is_some());
    let page = handle.history(None, 1).await.unwrap();
    assert!(page.jobs[0].seq < handle.snapshot().get(&last).unwrap().seq);
}

/// The embedded store with a second writer, as a shared farm has: changes queued in
/// `elsewhere` are made behind the task's back, and taken in by the next resync.
/// `kept` stands for outcomes kept while the database was unreachable: written at the
/// first try once `reachable` is set.
struct TwoHosts {
    spool: spool::SpoolStore,
    elsewhere: Arc<std::sync::Mutex<Vec<(String, JobState)>>>,
    kept: Arc<AtomicUsize>,
    reachable: Arc<AtomicBool>,
}

#[async_trait::async_trait]
impl JobStore for TwoHosts {
    fn jobs_dir(&self) -> PathBuf {
        self.spool.jobs_dir()
    }
    fn jobs(&self) -> Vec<Job> {
        self.spool.jobs()
    }
    fn job(&self, id: &str) -> Option<Job> {
        self.spool.job(id)
    }
    fn gates(&self) -> BTreeMap<String, PrinterGate> {
        self.spool.gates()
    }
    fn inventory(&self) -> crate::daemon::filament::Inventory {
        self.spool.inventory()
    }
    async fn edit_inventory(
        &mut self,
        edit: &mut crate::daemon::store::InventoryEdit<'_>,
    ) -> Result<crate::daemon::filament::Inventory, StoreError> {
        self.spool.edit_inventory(edit).await
    }
    async fn recover(&mut self) -> Result<Vec<String>, StoreError> {
        self.spool.recover().await
    }
    async fn admit(
        &mut self,
        source: &Path,
        folder: &Path,
        p: &[String],
    ) -> Result<Job, StoreError> {
        self.spool.admit(source, folder, p).await
    }
    async fn make_copies(&mut self, id: &str) -> Result<Vec<String>, StoreError> {
        self.spool.make_copies(id).await
    }
    async fn late_sidecar(
        &mut self,
        id: &str,
        s: &Path,
        applies: bool,
    ) -> Result<bool, StoreError> {
        self.spool.late_sidecar(id, s, applies).await
    }
    async fn transition_with(
        &mut self,
        id: &str,
        from: Option<StateFilter>,
        state: JobState,
        reason: Option<String>,
        also: JobEdit,
    ) -> Result<Job, StoreError> {
        self.spool
            .transition_with(id, from, state, reason, also)
            .await
    }
    async fn record_outcome(
        &mut self,
        id: &str,
        state: JobState,
        reason: Option<String>,
        also: JobEdit,
    ) -> Result<Job, StoreError> {
        self.spool.record_outcome(id, state, reason, also).await
    }
    async fn update(&mut self, id: &str, change: JobEdit) -> Result<Job, StoreError> {
        self.spool.update(id, change).await
    }
    async fn retry(&mut self, id: &str) -> Result<Job, StoreError> {
        self.spool.retry(id).await
    }
    async fn set_gate(&mut self, printer: &str, gate: PrinterGate) -> Result<(), StoreError> {
        self.spool.set_gate(printer, gate).await
    }
    async fn write_pending(&mut self) -> usize {
        if self.reachable.load(Ordering::SeqCst) {
            self.kept.store(0, Ordering::SeqCst);
        }
        self.kept.load(Ordering::SeqCst)
    }
    fn unwritten(&self) -> usize {
        self.kept.load(Ordering::SeqCst)
    }
    async fn resync(&mut self) -> bool {
        let changes: Vec<_> = std::mem::take(&mut *self.elsewhere.lock().unwrap());
        for (id, state) in &changes {
            let on_p1: JobEdit = Box::new(|j| j.printer = Some("p1".into()));
            self.spool
                .transition_with(id, None, *state, None, on_p1)
                .await
                .unwrap();
        }
        // Always a rebuild of the snapshot: one with nothing new must count nothing.
        true
    }
    async fn retire(&mut self, r: &Retention, now: f64) -> Result<Vec<String>, StoreError> {
        self.spool.retire(r, now).await
    }
    async fn retired(&mut self, id: &str) -> Result<Option<RetiredJob>, StoreError> {
        self.spool.retired(id).await
    }
    async fn history(
        &mut self,
        before: Option<u64>,
        limit: usize,
        filter: &history::Filter,
    ) -> Result<history::Page, StoreError> {
        self.spool.history(before, limit, filter).await
    }
    async fn prune(&mut self, keep: std::time::Duration, now: f64) -> Result<usize, StoreError> {
        self.spool.prune(keep, now).await
    }
    async fn each_retired(
        &mut self,
        since: f64,
        visit: &mut (dyn FnMut(history::Retired) + Send),
    ) -> Result<(), StoreError> {
        self.spool.each_retired(since, visit).await
    }
}

/// Changes another host made are counted by the task from what a resync takes in,
/// each once (a rebuild that brings nothing new counts nothing): the counts and the
/// tally are the farm's, not only this host's requests (a wrapper around this host's
/// requests once counted, and missed them).
#[tokio::test]
async fn changes_from_elsewhere_are_counted_once() {
    let tmp = tempfile::tempdir().unwrap();
    let hot = tmp.path().join("hot");
    std::fs::create_dir(&hot).unwrap();
    let elsewhere = Arc::new(std::sync::Mutex::new(Vec::new()));
    let store = TwoHosts {
        spool: spool::SpoolStore::open(&tmp.path().join("spool")).unwrap(),
        elsewhere: Arc::clone(&elsewhere),
        kept: Arc::default(),
        reachable: Arc::new(AtomicBool::new(true)),
    };
    let handle = spawn(store);
    std::fs::write(hot.join("a.gcode"), b"G28\n").unwrap();
    let job = handle.admit(&hot.join("a.gcode"), &hot, &[]).await.unwrap();
    let counts = |state| handle.snapshot().counts().entered(state);
    assert_eq!(counts(JobState::Queued), 1, "this host's own change");
    elsewhere.lock().unwrap().extend(
        [
            JobState::Preparing,
            JobState::Ready,
            JobState::Printing,
            JobState::Done,
        ]
        .map(|s| (job.id.clone(), s)),
    );
    assert!(handle.resync().await.unwrap());
    // Rebuilt again from the same jobs: nothing is counted twice.
    assert!(handle.resync().await.unwrap());
    for state in [JobState::Queued, JobState::Preparing, JobState::Ready] {
        assert_eq!(counts(state), 1, "{state}");
    }
    assert_eq!((counts(JobState::Printing), counts(JobState::Done)), (1, 1));
    let snapshot = handle.snapshot();
    assert_eq!(snapshot.counts().finished(), 1);
    let p1 = &snapshot.tally().read()["p1"];
    assert_eq!((p1.done, p1.prints), (1, 1), "the print on p1");
}

/// Outcomes kept while the database was unreachable are written by the task on its own,
/// tried again while it stays out of reach, with no request asking (before, the service
/// sent one every tick, a new one even while the last still waited).
#[tokio::test(start_paused = true)]
async fn kept_outcomes_are_written_once_the_database_is_back() {
    let tmp = tempfile::tempdir().unwrap();
    let kept = Arc::new(AtomicUsize::new(2));
    let reachable = Arc::new(AtomicBool::new(false));
    let handle = spawn(TwoHosts {
        spool: spool::SpoolStore::open(&tmp.path().join("spool")).unwrap(),
        elsewhere: Arc::default(),
        kept: Arc::clone(&kept),
        reachable: Arc::clone(&reachable),
    });
    let mut follower = handle.subscribe();
    assert_eq!(handle.snapshot().unwritten(), 2);
    // Several tries while the database is away (the clock runs ahead while all wait).
    tokio::time::sleep(super::task::WRITE_PENDING_EVERY * 3).await;
    assert_eq!(handle.snapshot().unwritten(), 2);
    reachable.store(true, Ordering::SeqCst);
    let written = follower.wait_for(|s| s.unwritten() == 0);
    tokio::time::timeout(super::task::WRITE_PENDING_EVERY * 2, written)
        .await
        .expect("written at the next try")
        .unwrap();
    assert_eq!(kept.load(Ordering::SeqCst), 0);
}

/// A print's use reaches its spool even when its job leaves the live view in the same
/// change (`live_jobs = 0`): the ledgers are brought up to date before anything retires.
#[tokio::test]
async fn a_use_is_booked_before_its_job_retires() {
    let tmp = tempfile::tempdir().unwrap();
    let hot = tmp.path().join("hot");
    std::fs::create_dir(&hot).unwrap();
    let store = spool::SpoolStore::open(&tmp.path().join("spool")).unwrap();
    let retention = Retention {
        live_for: std::time::Duration::from_secs(86_400),
        live_jobs: 0,
        keep_for: None,
    };
    let handle = spawn_with(store, retention);
    let inventory = handle
        .edit_inventory(crate::daemon::store::InventoryChange::AddAndLoad {
            printer: "p".into(),
            filament: crate::daemon::filament::tests::petg_black(),
            grams: 100.0,
        })
        .await
        .unwrap();
    let spool = inventory.spool_on("p").unwrap().id.clone();
    // The job ends with its use recorded, and leaves the live view in the same change.
    let id = {
        let model = hot.join("b.gcode");
        std::fs::write(&model, b"G28\n").unwrap();
        handle.admit(&model, &hot, &[]).await.unwrap().id
    };
    let key = format!("{id}#0");
    let usage = crate::daemon::job::JobUse {
        key: key.clone(),
        spool: Some(spool.clone()),
        printer: "p".into(),
        material: "PETG".into(),
        colour: "black".into(),
        grams: 12.5,
        mm: 0.0,
        cost: None,
        at_s: 0.0,
        print_s: 0.0,
        failed: false,
    };
    handle
        .transition_from(
            &id,
            &[JobState::Queued],
            JobState::Cancelled,
            None,
            JobChange::Used(Use { print: 0, usage }),
        )
        .await
        .unwrap();
    let snapshot = handle.snapshot();
    assert!(snapshot.get(&id).is_none(), "retired at once");
    let s = &snapshot.inventory().spools[&spool];
    assert!(s.uses.contains_key(&key), "{:?}", s.uses);
    assert_eq!(s.remaining_g(), Some(87.5));
    // The printer's care counted it in the same write.
    let care = &snapshot.inventory().care["p"];
    assert_eq!((care.counts.prints, care.counts.filament_g), (1, 12.5));
    assert_eq!(care.counts.materials["PETG"].g, 12.5);
}

/// A print is counted on its printer once, whoever sees its use and however often: a
/// restart of the store reads the counts and the uses counted back, and counts nothing
/// again; a failed print counts as one; the key of a use whose job just left the live view
/// is kept, though its print ended long ago (`care::refresh` forgets it a day later).
#[tokio::test]
async fn a_print_is_counted_once_across_restarts() {
    let tmp = tempfile::tempdir().unwrap();
    let hot = tmp.path().join("hot");
    std::fs::create_dir(&hot).unwrap();
    let root = tmp.path().join("spool");
    let print = |id: &str, n: usize, at_s: f64, failed: bool| {
        JobChange::Used(Use {
            print: n,
            usage: crate::daemon::job::JobUse {
                key: format!("{id}#{n}"),
                spool: None,
                printer: "p".into(),
                material: "PLA".into(),
                colour: "black".into(),
                grams: 2.0,
                mm: 660.0,
                cost: None,
                at_s,
                print_s: 600.0,
                failed,
            },
        })
    };
    let admit = |handle: &StoreHandle, name: &str| {
        let model = hot.join(name);
        std::fs::write(&model, b"G28\n").unwrap();
        let handle = handle.clone();
        let hot = hot.clone();
        async move { handle.admit(&model, &hot, &[]).await.unwrap().id }
    };
    // The store's task is awaited once its last handle is gone, so the spool is free.
    let (handle, task) = super::task::start(
        spool::SpoolStore::open(&root).unwrap(),
        Retention::default(),
    );
    let task = tokio::spawn(task);
    let old = admit(&handle, "old.gcode").await;
    handle
        .update(&old, print(&old, 0, 1.0, false))
        .await
        .unwrap();
    let id = admit(&handle, "a.gcode").await;
    handle
        .update(&id, print(&id, 0, 1e12, false))
        .await
        .unwrap();
    handle.update(&id, print(&id, 1, 1e12, true)).await.unwrap();
    let care = handle.snapshot().inventory().care["p"].clone();
    assert_eq!((care.counts.prints, care.counts.failed), (3, 1));
    assert_eq!(care.counts.print_s, 1800.0);
    assert_eq!(care.counted.len(), 3);
    drop(handle);
    task.await.unwrap();

    let handle = spawn(spool::SpoolStore::open(&root).unwrap());
    // The first job leaves the live view; its key stays (a day from when it was last seen
    // live, though its print ended long before), and nothing is counted twice.
    handle
        .transition_from(
            &old,
            &[JobState::Queued],
            JobState::Cancelled,
            None,
            JobChange::Nothing,
        )
        .await
        .unwrap();
    assert_eq!(
        handle.retire(1e12).await.unwrap(),
        std::slice::from_ref(&old)
    );
    let other = admit(&handle, "b.gcode").await;
    handle
        .update(&other, print(&other, 0, 1e12, false))
        .await
        .unwrap();
    let care = handle.snapshot().inventory().care["p"].clone();
    assert_eq!((care.counts.prints, care.counts.failed), (4, 1));
    assert!(
        care.counted.contains_key(&format!("{old}#0")),
        "{:?}",
        care.counted
    );
    assert!(care.counted.contains_key(&format!("{id}#1")));
}

/// Through the store's task, a clear that cannot be written is refused and the published
/// snapshot agrees: the bed still waits, now and once writing works again (the task
/// publishes before it replies, so a reader never sees a clear the reply denies).
#[tokio::test]
async fn a_refused_clear_is_not_published() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("spool");
    let handle = spawn(spool::SpoolStore::open(&root).unwrap());
    handle.close_gate("p1", "0001-a").await.unwrap();
    let blocker = crate::fsutil::temp_path(&root.join("printers.json"));
    std::fs::create_dir_all(&blocker).unwrap();
    let follower = handle.subscribe();
    let refused = handle.clear_gate("p1").await.unwrap_err();
    assert!(matches!(refused, StoreError::Io { .. }), "{refused}");
    assert!(handle.snapshot().gate("p1").bed_not_cleared());
    assert_eq!(handle.snapshot().unwritten(), 0);
    std::fs::remove_dir(&blocker).unwrap();
    assert_eq!(handle.write_pending().await.unwrap(), 0);
    assert!(handle.snapshot().gate("p1").bed_not_cleared());
    assert!(
        !follower.has_changed().unwrap(),
        "nothing changed, nothing published"
    );
    assert!(handle.clear_gate("p1").await.unwrap());
    assert!(!handle.snapshot().gate("p1").bed_not_cleared());
}

/// Through the store's task: a job that asks for three copies and becomes ready has them
/// in the snapshot published with its change (ready jobs of their own); the wall
/// comparison measured for it is given to its copies, which never measure their own.
#[tokio::test]
async fn a_ready_job_publishes_its_copies_and_shares_its_comparison() {
    use super::change::PreparedJob;
    use crate::daemon::job::{Comparison, ForMachine, Sidecar};
    let tmp = tempfile::tempdir().unwrap();
    let hot = tmp.path().join("hot");
    std::fs::create_dir(&hot).unwrap();
    let handle = spawn(spool::SpoolStore::open(&tmp.path().join("spool")).unwrap());
    std::fs::write(hot.join("a.gcode"), b"G28\n").unwrap();
    let id = handle
        .admit(&hot.join("a.gcode"), &hot, &[])
        .await
        .unwrap()
        .id;
    handle
        .transition(&id, JobState::Preparing, None)
        .await
        .unwrap();
    let prepared = PreparedJob {
        machines: [("m".to_string(), ForMachine::Gcode("a.gcode".into()))].into(),
        needs: Default::default(),
        sidecar: Some(Sidecar {
            copies: Some(3),
            ..Default::default()
        }),
        asks: Default::default(),
        report: Some(Default::default()),
        comparison: Some(Comparison::Pending { tries: 0 }),
    };
    handle
        .transition_with(
            &id,
            JobState::Ready,
            None,
            JobChange::Prepared(Box::new(prepared)),
        )
        .await
        .unwrap();
    let snapshot = handle.snapshot();
    let copies: Vec<&Job> = snapshot.jobs().filter(|j| j.copy.is_some()).collect();
    assert_eq!(copies.len(), 2, "published with the change");
    assert!(copies
        .iter()
        .all(|c| c.state == JobState::Ready && c.group() == id));
    assert!(copies
        .iter()
        .all(|c| c.comparison == Some(Comparison::Pending { tries: 0 })));

    handle
        .update(
            &id,
            JobChange::ComparisonEnded {
                tries: 0,
                walls: Err("no slicer here".into()),
                started_s: 1.0,
                took_s: 2.0,
            },
        )
        .await
        .unwrap();
    let snapshot = handle.snapshot();
    let first = snapshot.get(&id).unwrap();
    for copy in snapshot.jobs().filter(|j| j.copy.is_some()) {
        assert_eq!(copy.comparison, first.comparison, "{}", copy.id);
        assert_eq!(
            copy.slice_report.as_ref().map(|r| r.moved()),
            first.slice_report.as_ref().map(|r| r.moved())
        );
    }
}
