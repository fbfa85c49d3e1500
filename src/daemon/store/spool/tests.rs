//! The spool's tests: picking up, the table, restarts, unreadable and missing job
//! directories, a full disk, and the history. Apart from `mod.rs` only for its length.

use super::*;
use std::io::Write;

/// A temporary folder holding a hot folder `hot` and a spool `spool`, opened.
fn open_with_hot_folder() -> (tempfile::TempDir, PathBuf, PathBuf, Spool) {
    let tmp = tempfile::tempdir().unwrap();
    let hot = tmp.path().join("hot");
    std::fs::create_dir(&hot).unwrap();
    let spool = tmp.path().join("spool");
    let store = Spool::open(&spool).unwrap();
    (tmp, hot, spool, store)
}

fn drop_file(dir: &Path, name: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, b"solid x\nendsolid x\n").unwrap();
    p
}

#[test]
fn admit_moves_file_and_persists_state() {
    let (_tmp, hot, spool, mut store) = open_with_hot_folder();
    let src = drop_file(&hot, "a b.stl");
    std::fs::write(hot.join("a b.stl.toml"), "enhance = false\n").unwrap();
    let job = store.admit(&src, &hot).unwrap();
    assert!(!src.exists());
    assert!(store.job_dir(&job.id).join("a b.stl").exists());
    assert!(store.job_dir(&job.id).join("a b.stl.toml").exists());
    assert!(!hot.join("a b.stl.toml").exists());
    assert_eq!(job.state, JobState::Queued);

    let err = Spool::open(&spool).err().unwrap();
    assert!(matches!(err, StoreError::Locked { .. }), "{err}");
    drop(store);
    let store2 = Spool::open(&spool).unwrap();
    let again = store2.get(&job.id).unwrap();
    assert_eq!(again.file, "a b.stl");
    assert_eq!(again.state, JobState::Queued);
}

/// A dropped `café.gcode` becomes a job named in the one spelling (composed), whichever
/// spelling it was dropped under; its sidecar goes with it in the other spelling too.
#[test]
fn a_job_is_named_in_the_one_spelling_and_finds_its_sidecar_in_any() {
    let (_tmp, hot, spool, mut store) = open_with_hot_folder();
    let composed = "caf\u{e9}.gcode";
    let src = drop_file(&hot, "cafe\u{301}.gcode");
    std::fs::write(hot.join(format!("{composed}.toml")), "hold = true\n").unwrap();
    let job = store.admit(&src, &hot).unwrap();
    assert_eq!(job.file, composed);
    let dir = store.job_dir(&job.id);
    assert!(dir.join(composed).is_file());
    assert!(dir.join(format!("{composed}.toml")).is_file());
    assert_eq!(std::fs::read_dir(&hot).unwrap().count(), 0, "both taken");
    // Composed model, decomposed sidecar.
    let src = drop_file(&hot, composed);
    std::fs::write(hot.join("cafe\u{301}.gcode.toml"), "copies = 2\n").unwrap();
    let second = store.admit(&src, &hot).unwrap();
    assert_eq!(second.file, composed);
    assert!(store
        .job_dir(&second.id)
        .join(format!("{composed}.toml"))
        .is_file());
    assert_eq!(std::fs::read_dir(&hot).unwrap().count(), 0, "both taken");
    drop(store);
    let store = Spool::open(&spool).unwrap();
    assert_eq!(store.get(&job.id).unwrap().file, composed);
}

#[test]
fn restart_rules_and_gates_survive_reopen() {
    let (_tmp, hot, spool, mut store) = open_with_hot_folder();
    let a = store.admit(&drop_file(&hot, "a.stl"), &hot).unwrap().id;
    let b = store.admit(&drop_file(&hot, "b.stl"), &hot).unwrap().id;
    let c = store.admit(&drop_file(&hot, "c.stl"), &hot).unwrap().id;
    store.transition(&a, JobState::Preparing, None).unwrap();
    for (id, path) in [
        (
            &b,
            &[JobState::Preparing, JobState::Ready, JobState::Printing][..],
        ),
        (&c, &[JobState::Preparing, JobState::Ready]),
    ] {
        for &state in path {
            store.transition(id, state, None).unwrap();
        }
    }
    store.update(&b, |j| j.printer = Some("p1".into())).unwrap();
    drop(store);

    let mut store = Spool::open(&spool).unwrap();
    let changed = store.recover().unwrap();
    assert_eq!(changed.len(), 2);
    assert_eq!(store.get(&a).unwrap().state, JobState::Queued);
    assert_eq!(store.get(&b).unwrap().state, JobState::Interrupted);
    assert!(store.get(&b).unwrap().reason.is_some());
    assert_eq!(store.get(&c).unwrap().state, JobState::Ready);
    assert!(store.gate("p1").bed_not_cleared());
    assert!(!store.gate("p2").bed_not_cleared());

    drop(store);
    let store = Spool::open(&spool).unwrap();
    assert!(store.gate("p1").bed_not_cleared());
    let order: Vec<&str> = store.jobs().map(|j| j.id.as_str()).collect();
    assert_eq!(order, vec![a.as_str(), b.as_str(), c.as_str()]);
}

#[test]
fn retry_only_from_finished_states() {
    let (_tmp, hot, _, mut store) = open_with_hot_folder();
    let a = store.admit(&drop_file(&hot, "a.stl"), &hot).unwrap().id;
    let err = store.retry(&a).unwrap_err().to_string();
    assert!(err.contains("is queued"), "{err}");
    store
        .transition(&a, JobState::Failed, Some("bad mesh".into()))
        .unwrap();
    let job = store.retry(&a).unwrap();
    assert_eq!(
        job.state,
        JobState::Queued,
        "nothing prepared: prepare again"
    );
    assert_eq!(job.reason, None);
    assert!(matches!(store.retry("nope"), Err(StoreError::NoSuchJob(_))));

    // Prepared, then cancelled in print: straight back to ready with its G-code.
    std::fs::write(store.job_dir(&a).join("a.stl.gcode"), b"G28\n").unwrap();
    store
        .update(&a, |j| j.slice_report = Some(Default::default()))
        .unwrap();
    store.transition(&a, JobState::Preparing, None).unwrap();
    store.transition(&a, JobState::Ready, None).unwrap();
    store.transition(&a, JobState::Printing, None).unwrap();
    store
        .transition(&a, JobState::Cancelled, Some("cancelled".into()))
        .unwrap();
    assert_eq!(store.retry(&a).unwrap().state, JobState::Ready);
}

#[test]
fn orphaned_pickup_is_adopted() {
    let tmp = tempfile::tempdir().unwrap();
    let spool = tmp.path().join("spool");
    let dir = spool.join("jobs").join("0007-x_stl");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("x.stl"), b"data").unwrap();
    std::fs::write(
        dir.join("origin.json"),
        serde_json::to_vec(
            &serde_json::json!({"id": "0007-x_stl", "file": "x.stl", "folder": "/hot"}),
        )
        .unwrap(),
    )
    .unwrap();
    let store = Spool::open(&spool).unwrap();
    let job = store.get("0007-x_stl").unwrap();
    assert_eq!(job.state, JobState::Queued);
    assert_eq!(job.file, "x.stl");
}

/// The store refuses every change the table refuses, leaves the job as it was (in
/// memory and on disk), and `update` can never change a state behind the table's back.
#[test]
fn store_enforces_the_table() {
    let (_tmp, hot, spool, mut store) = open_with_hot_folder();
    let a = store.admit(&drop_file(&hot, "a.stl"), &hot).unwrap().id;
    let err = store.transition(&a, JobState::Done, None).unwrap_err();
    assert!(
        matches!(
            err,
            StoreError::IllegalTransition {
                from: JobState::Queued,
                to: JobState::Done,
                ..
            }
        ),
        "{err}"
    );
    store.update(&a, |j| j.state = JobState::Done).unwrap();
    assert_eq!(store.get(&a).unwrap().state, JobState::Queued);
    drop(store);
    let reopened = Spool::open(&spool).unwrap();
    assert_eq!(reopened.get(&a).unwrap().state, JobState::Queued);
    assert_eq!(reopened.get(&a).unwrap().history.len(), 1);
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig::with_cases(48))]
    /// Random sequences of attempted changes (legal or not) and restarts on a real
    /// spool: a change succeeds exactly when the table allows it, the state on disk
    /// always equals the one in memory, every step of the recorded history is legal,
    /// and once done a job stays done.
    #[test]
    fn random_transitions_follow_the_table(
        steps in proptest::collection::vec((0usize..9, 0usize..8), 1..40)
    ) {
        let (_tmp, hot, spool, mut store) = open_with_hot_folder();
        let id = store.admit(&drop_file(&hot, "m.stl"), &hot).unwrap().id;
        let mut done = false;
        for (op, target) in steps {
            let before = store.get(&id).unwrap().state;
            if op == 8 {
                // A restart: reopen from disk and apply the restart rules.
                drop(store);
                store = Spool::open(&spool).unwrap();
                store.recover().unwrap();
                let after = store.get(&id).unwrap().state;
                proptest::prop_assert!(after == before || before.can_go_to(after));
            } else {
                let to = JobState::ALL[target];
                let result = store.transition(&id, to, None);
                proptest::prop_assert_eq!(result.is_ok(), before.can_go_to(to));
                let now = store.get(&id).unwrap().state;
                proptest::prop_assert_eq!(now, if result.is_ok() { to } else { before });
            }
            let now = store.get(&id).unwrap().state;
            proptest::prop_assert!(!done || now == JobState::Done, "done is final");
            done |= now == JobState::Done;
            let on_disk: Job = serde_json::from_slice(
                &std::fs::read(store.job_dir(&id).join("job.json")).unwrap(),
            )
            .unwrap();
            proptest::prop_assert_eq!(on_disk.state, now);
        }
        let history = &store.get(&id).unwrap().history;
        for pair in history.windows(2) {
            proptest::prop_assert!(pair[0].0.can_go_to(pair[1].0), "{:?}", pair);
        }
    }
}

/// A corrupt, oversized or lying job state fails that job only: the spool still
/// opens, the other jobs load, and the directory stays as it was.
#[test]
fn unreadable_job_state_fails_that_job_only() {
    let (_tmp, hot, spool, mut store) = open_with_hot_folder();
    let ids: Vec<String> = ["a.stl", "b.stl", "c.stl", "d.stl"]
        .iter()
        .map(|f| store.admit(&drop_file(&hot, f), &hot).unwrap().id)
        .collect();
    drop(store);
    let state = |id: &str| spool.join("jobs").join(id).join("job.json");
    std::fs::write(state(&ids[0]), b"{\"id\": \"0001-a_stl\", trunc").unwrap();
    let evil = std::fs::read_to_string(state(&ids[1]))
        .unwrap()
        .replace(&ids[1], "../../../etc");
    std::fs::write(state(&ids[1]), evil).unwrap();
    std::fs::write(state(&ids[2]), vec![b' '; 2 << 20]).unwrap();

    let store = Spool::open(&spool).unwrap();
    for id in &ids[..3] {
        let job = store.get(id).unwrap_or_else(|| panic!("{id} is listed"));
        assert_eq!(job.state, JobState::Failed, "{id}");
        let reason = job.reason.as_deref().unwrap();
        assert!(
            reason.contains("job.json") && reason.contains("kept"),
            "{reason}"
        );
        // Clients see the reason: the files relative to the spool, never its path.
        assert!(
            reason.contains(&format!("jobs/{id}/job.json"))
                && reason.contains(&format!("directory jobs/{id} is kept"))
                && !reason.contains(&*spool.to_string_lossy()),
            "{reason}"
        );
    }
    assert_eq!(
        store.get(&ids[0]).unwrap().file,
        "a.stl",
        "from origin.json"
    );
    assert_eq!(store.get(&ids[3]).unwrap().state, JobState::Queued);
    assert!(std::fs::read(state(&ids[0])).unwrap().ends_with(b"trunc"));
}

/// A job directory copied within the spool (under any name) is not a second job, with
/// its state written or not yet.
#[test]
fn a_copied_job_directory_is_not_a_new_job() {
    let (_tmp, hot, spool, mut store) = open_with_hot_folder();
    let a = store.admit(&drop_file(&hot, "a.stl"), &hot).unwrap().id;
    drop(store);
    let jobs = spool.join("jobs");
    let copy = |to: &str| {
        let status = std::process::Command::new("cp")
            .arg("-a")
            .arg(jobs.join(&a))
            .arg(jobs.join(to))
            .status()
            .unwrap();
        assert!(status.success());
    };
    copy("0042-a_stl");
    copy("0001-a_stl copy");
    copy("0043-a_stl");
    // A copy of a pick-up that never got its state (origin.json only).
    std::fs::remove_file(jobs.join("0043-a_stl/job.json")).unwrap();
    let store = Spool::open(&spool).unwrap();
    let listed: Vec<&str> = store.jobs().map(|j| j.id.as_str()).collect();
    assert_eq!(listed, vec![a.as_str()]);
}

/// A dropped model named like the job's own files is kept under another name: the
/// model and the job's state both survive.
#[test]
fn a_model_named_like_crispens_files_overwrites_nothing() {
    let (_tmp, hot, spool, mut store) = open_with_hot_folder();
    let mut ids = Vec::new();
    for name in ["job.json", "origin.json"] {
        let job = store.admit(&drop_file(&hot, name), &hot).unwrap();
        assert_eq!(job.file, format!("model-{name}"));
        let dir = store.job_dir(&job.id);
        assert_eq!(
            std::fs::read(dir.join(&job.file)).unwrap(),
            b"solid x\nendsolid x\n"
        );
        ids.push(job.id);
    }
    drop(store);
    let store = Spool::open(&spool).unwrap();
    for id in &ids {
        assert_eq!(store.get(id).unwrap().state, JobState::Queued);
    }
}

/// A link in a hot folder is not followed: neither the model nor its sidecar.
#[test]
fn symbolic_links_are_not_picked_up() {
    let (tmp, hot, _, mut store) = open_with_hot_folder();
    let secret = tmp.path().join("secret.stl");
    std::fs::write(&secret, b"private").unwrap();
    std::os::unix::fs::symlink(&secret, hot.join("link.stl")).unwrap();
    let err = store.admit(&hot.join("link.stl"), &hot).unwrap_err();
    assert!(matches!(err, StoreError::NotAFile { .. }), "{err}");
    assert_eq!(store.jobs().count(), 0);

    let sidecar_target = tmp.path().join("other.toml");
    std::fs::write(&sidecar_target, "enhance = false\n").unwrap();
    std::os::unix::fs::symlink(&sidecar_target, hot.join("m.stl.toml")).unwrap();
    let job = store.admit(&drop_file(&hot, "m.stl"), &hot).unwrap();
    assert!(!store.job_dir(&job.id).join("m.stl.toml").exists());
}

/// A job whose directory was removed by hand fails (in memory) at its next change,
/// so whoever waits for it moves on.
#[test]
fn a_removed_job_directory_fails_the_job() {
    let (_tmp, hot, _, mut store) = open_with_hot_folder();
    let a = store.admit(&drop_file(&hot, "a.stl"), &hot).unwrap().id;
    std::fs::remove_dir_all(store.job_dir(&a)).unwrap();
    let err = store.transition(&a, JobState::Preparing, None).unwrap_err();
    assert!(matches!(err, StoreError::DirectoryGone { .. }), "{err}");
    let job = store.get(&a).unwrap();
    assert_eq!(job.state, JobState::Failed);
    assert!(job.reason.as_deref().unwrap().contains("removed"));
}

/// Makes every later write of this job's state fail, as a full disk would: the
/// temporary file's name is taken by a directory.
fn block_writes(store: &Spool, id: &str) -> PathBuf {
    let blocker = crate::fsutil::temp_path(&store.job_dir(id).join("job.json"));
    std::fs::create_dir_all(&blocker).unwrap();
    blocker
}

/// A pick-up that cannot be completed leaves the model and its sidecar in the hot
/// folder and no half job in the spool, now or after a restart.
#[test]
fn a_pickup_that_cannot_be_written_is_undone() {
    let (_tmp, hot, spool, mut store) = open_with_hot_folder();
    block_writes(&store, "0001-a_stl");
    let src = drop_file(&hot, "a.stl");
    std::fs::write(hot.join("a.stl.toml"), "enhance = false\n").unwrap();
    store.admit(&src, &hot).unwrap_err();
    assert_eq!(std::fs::read(&src).unwrap(), b"solid x\nendsolid x\n");
    assert!(hot.join("a.stl.toml").is_file());
    assert!(!store.job_dir("0001-a_stl").exists(), "no half job left");
    assert_eq!(store.jobs().count(), 0);
    drop(store);
    assert_eq!(Spool::open(&spool).unwrap().jobs().count(), 0);
}

/// A pick-up that fails again and again (a full disk) keeps one job number: the one that
/// works is the next number, not one more for each failure (0011 became 0048 in 15 s).
#[test]
fn failed_pickups_keep_one_job_number() {
    let (_tmp, hot, spool, mut store) = open_with_hot_folder();
    let src = drop_file(&hot, "a.stl");
    for _ in 0..5 {
        // The failed pick-up removes the job's directory, the blocker with it.
        block_writes(&store, "0001-a_stl");
        store.admit(&src, &hot).unwrap_err();
    }
    assert_eq!(store.admit(&src, &hot).unwrap().id, "0001-a_stl");
    let next = store.admit(&drop_file(&hot, "b.stl"), &hot).unwrap();
    assert_eq!(next.id, "0002-b_stl");
    // A failure of another file in between takes no number either.
    block_writes(&store, "0003-c_stl");
    store.admit(&drop_file(&hot, "c.stl"), &hot).unwrap_err();
    let d = store.admit(&drop_file(&hot, "d.stl"), &hot).unwrap();
    assert_eq!(d.id, "0003-d_stl");
    drop(store);
    let reopened = Spool::open(&spool).unwrap();
    let ids: Vec<&str> = reopened.jobs().map(|j| j.id.as_str()).collect();
    assert_eq!(ids, ["0001-a_stl", "0002-b_stl", "0003-d_stl"]);
}

/// Makes every write of the bed gates fail, as a full disk would (see [`block_writes`]).
fn block_gate_writes(spool: &Path) -> PathBuf {
    let blocker = crate::fsutil::temp_path(&spool.join("printers.json"));
    std::fs::create_dir_all(&blocker).unwrap();
    blocker
}

/// The bed gates on disk.
fn gates_on_disk(spool: &Path) -> BTreeMap<String, PrinterGate> {
    serde_json::from_slice(&std::fs::read(spool.join("printers.json")).unwrap()).unwrap()
}

/// A bed gate that cannot be written: a closed one (a print ended) is kept and written
/// later, so the bed still waits after the outage; a clear is not done, here as on disk,
/// and stays undone when writing works again (it once took effect in memory, was
/// reported failed, and was written later: the operator was told it failed while the
/// printer took the next job).
#[test]
fn a_clear_that_cannot_be_written_is_not_done() {
    let (_tmp, _hot, spool, mut store) = open_with_hot_folder();
    use crate::daemon::bed::{Bed, ClearedBy};
    let closed = |job: &str| PrinterGate {
        bed: Bed::Waiting { why: None },
        last_job: Some(job.into()),
        last_check: None,
    };
    let cleared = |job: &str| PrinterGate {
        bed: Bed::Clear {
            by: ClearedBy::Person,
            at_s: 1.0,
        },
        last_job: Some(job.into()),
        last_check: None,
    };
    store.set_gate("p1", closed("0001-a")).unwrap();

    // Written before the disk filled: the clear is refused and nothing is kept for later.
    let blocker = block_gate_writes(&spool);
    store.set_gate("p1", cleared("0001-a")).unwrap_err();
    assert_eq!(store.gate("p1"), closed("0001-a"));
    assert_eq!(store.unwritten(), 0, "nothing to write later");
    // A print on another printer ends meanwhile: its closed gate stands, kept.
    store.set_gate("p2", closed("0002-b")).unwrap();
    assert_eq!(store.gate("p2"), closed("0002-b"));
    assert_eq!(store.unwritten(), 1);
    // Its clear while still full is refused, and the closed gate stays kept.
    store.set_gate("p2", cleared("0002-b")).unwrap_err();
    assert_eq!(store.gate("p2"), closed("0002-b"));
    assert_eq!(store.unwritten(), 1);
    // A printer never seen before: refused, and it has no gate.
    store.set_gate("p3", cleared("0003-c")).unwrap_err();
    assert_eq!(store.gate("p3"), PrinterGate::default());
    assert!(!store.gates.contains_key("p3"));

    // Room again: what is written is what was said, both beds still to clear.
    std::fs::remove_dir(&blocker).unwrap();
    assert_eq!(store.write_pending(), 0);
    let on_disk = gates_on_disk(&spool);
    assert_eq!(on_disk["p1"], closed("0001-a"));
    assert_eq!(on_disk["p2"], closed("0002-b"));
    assert!(!on_disk.contains_key("p3"));
    drop(store);
    let mut store = Spool::open(&spool).unwrap();
    assert_eq!(store.gate("p1"), closed("0001-a"));
    // Now the clear is done, and written.
    store.set_gate("p1", cleared("0001-a")).unwrap();
    assert_eq!(gates_on_disk(&spool)["p1"], cleared("0001-a"));
}

/// A print that finished while its state could not be written counts as done at
/// once (never retried, never offered again) and is written once writing works.
#[test]
fn an_outcome_that_cannot_be_written_is_kept_and_written_later() {
    let (_tmp, hot, _, mut store) = open_with_hot_folder();
    let a = store.admit(&drop_file(&hot, "a.stl"), &hot).unwrap().id;
    for state in [JobState::Preparing, JobState::Ready, JobState::Printing] {
        store.transition(&a, state, None).unwrap();
    }
    let blocker = block_writes(&store, &a);
    let job = store
        .record_outcome(&a, JobState::Done, None, |j| j.copies_done += 1)
        .unwrap();
    assert_eq!(job.state, JobState::Done);
    assert_eq!(store.get(&a).unwrap().state, JobState::Done);
    assert!(matches!(
        store.retry(&a),
        Err(StoreError::WrongState { .. })
    ));
    let on_disk = |store: &Spool| -> Job {
        serde_json::from_slice(&std::fs::read(store.job_dir(&a).join("job.json")).unwrap()).unwrap()
    };
    assert_eq!(on_disk(&store).state, JobState::Printing);
    assert_eq!(store.write_pending(), 1, "still not writable");
    std::fs::remove_dir(&blocker).unwrap();
    assert_eq!(store.write_pending(), 0);
    let written = on_disk(&store);
    assert_eq!((written.state, written.copies_done), (JobState::Done, 1));
}

/// A spool with `n` jobs that went to `state` one after another, `gap` seconds apart
/// ending `ago` seconds before `now`; returns their ids, oldest first.
fn finished_jobs(store: &mut Spool, hot: &Path, n: usize, state: JobState) -> Vec<String> {
    (0..n)
        .map(|i| {
            let id = store
                .admit(&drop_file(hot, &format!("m{i}.stl")), hot)
                .unwrap()
                .id;
            store.transition(&id, state, Some("over".into())).unwrap();
            id
        })
        .collect()
}

fn retention(days: u64, jobs: usize) -> Retention {
    Retention {
        live_for: std::time::Duration::from_secs(days * 86_400),
        live_jobs: jobs,
        keep_for: None,
    }
}

/// `[history] keep_days`: a month of the history wholly older than it goes, its jobs'
/// directories first, then its file; later months stay, and a reopened spool agrees.
#[test]
fn the_history_forgets_months_older_than_it_keeps() {
    let (_tmp, hot, spool, mut store) = open_with_hot_folder();
    let done = finished_jobs(&mut store, &hot, 2, JobState::Cancelled);
    let now = now_s();
    let old = now - 100.0 * 86_400.0;
    // The older job moves to the history a hundred days ago, the other now.
    assert_eq!(store.retire(&retention(7, 1), old).unwrap(), done[..1]);
    assert_eq!(store.retire(&retention(7, 0), now).unwrap(), done[1..]);
    let old_month = spool
        .join("history")
        .join(format!("{}.jsonl", crate::calendar::month_of(old)));
    assert!(old_month.is_file());

    let keep = std::time::Duration::from_secs(30 * 86_400);
    assert_eq!(store.prune(keep, now).unwrap(), 1);
    assert!(!old_month.exists());
    assert!(!store.job_dir(&done[0]).exists());
    assert!(store.job_dir(&done[1]).join("m1.stl").is_file());
    assert_eq!(store.prune(keep, now).unwrap(), 0);
    let listed = |store: &Spool| -> Vec<String> {
        store
            .history_page(None, 10, &Default::default())
            .unwrap()
            .jobs
            .into_iter()
            .map(|r| r.id)
            .collect()
    };
    assert_eq!(listed(&store), done[1..]);
    assert!(store.retired_job(&done[0]).unwrap().is_none());
    drop(store);
    let store = Spool::open(&spool).unwrap();
    assert_eq!(store.jobs().count(), 0);
    assert_eq!(listed(&store), done[1..]);
}

/// Finished jobs beyond the count, and all of them once old enough, leave the live
/// jobs for the history; their directories stay; after a restart they are still in
/// the history (once each) and not live; active jobs never move.
#[test]
fn finished_jobs_move_to_the_history_and_stay_there() {
    let (_tmp, hot, spool, mut store) = open_with_hot_folder();
    let done = finished_jobs(&mut store, &hot, 5, JobState::Cancelled);
    let active = store
        .admit(&drop_file(&hot, "active.stl"), &hot)
        .unwrap()
        .id;
    let now = now_s();
    let moved = store.retire(&retention(7, 3), now).unwrap();
    assert_eq!(moved, done[..2].to_vec(), "the oldest beyond three");
    assert!(store.get(&done[0]).is_none() && store.get(&done[2]).is_some());
    assert!(
        store.job_dir(&done[0]).join("m0.stl").is_file(),
        "files stay"
    );
    assert!(store.retire(&retention(7, 3), now).unwrap().is_empty());

    // A week later every finished job is old enough; the active one stays.
    let moved = store
        .retire(&retention(7, 3), now + 8.0 * 86_400.0)
        .unwrap();
    assert_eq!(moved, done[2..].to_vec());
    assert_eq!(
        store.jobs().map(|j| j.id.clone()).collect::<Vec<_>>(),
        std::slice::from_ref(&active)
    );

    drop(store);
    let store = Spool::open(&spool).unwrap();
    assert_eq!(store.jobs().count(), 1);
    let page = store.history_page(None, 100, &Default::default()).unwrap();
    let mut ids: Vec<String> = page.jobs.iter().map(|r| r.id.clone()).collect();
    ids.reverse();
    assert_eq!(ids, done);
    let retired = store
        .retired_job(&done[3])
        .unwrap()
        .expect("retired job found");
    assert_eq!(retired.record.state, JobState::Cancelled);
    assert_eq!(retired.record.dir, store.job_dir(&done[3]));
    assert_eq!(retired.job.unwrap().reason.as_deref(), Some("over"));
    assert!(store.retired_job(&active).unwrap().is_none());
    // The history is not the queue.
    let mut store = store;
    let err = store.retry(&done[3]).unwrap_err();
    assert!(matches!(err, StoreError::WrongState { .. }), "{err}");
    assert!(err.to_string().contains("history"), "{err}");
    // New jobs continue the numbering past the retired ones.
    let next = store.admit(&drop_file(&hot, "next.stl"), &hot).unwrap();
    assert_eq!(next.seq, 7);
}

/// A crash after the history was written but before the jobs left the live ones:
/// after the restart each job is in the history once and not live. A crash in the
/// middle of writing a line: that job was not retired, is live, and is retired again
/// (once).
#[test]
fn a_crash_while_retiring_loses_nothing_and_shows_nothing_twice() {
    let (_tmp, hot, spool, mut store) = open_with_hot_folder();
    let done = finished_jobs(&mut store, &hot, 3, JobState::Failed);
    let now = now_s();
    // Written, then "killed" before the jobs left the live ones.
    let records: Vec<Retired> = done[..2]
        .iter()
        .map(|id| Retired::of(store.get(id).unwrap(), store.job_dir(id), now))
        .collect();
    store.history.append(&records, now).unwrap();
    drop(store);
    // And a line cut short, for the third.
    let file = spool
        .join("history")
        .join(format!("{}.jsonl", crate::calendar::month_of(now)));
    let third = serde_json::to_string(&Retired::of(
        &Spool::open(&spool).unwrap().get(&done[2]).unwrap().clone(),
        PathBuf::new(),
        now,
    ))
    .unwrap();
    let mut f = std::fs::OpenOptions::new()
        .append(true)
        .open(&file)
        .unwrap();
    f.write_all(&third.as_bytes()[..third.len() / 2]).unwrap();
    drop(f);

    let mut store = Spool::open(&spool).unwrap();
    let live: Vec<String> = store.jobs().map(|j| j.id.clone()).collect();
    assert_eq!(live, [done[2].clone()], "the cut line's job is live");
    assert!(std::fs::read(&file).unwrap().ends_with(b"\n"), "mended");
    assert_eq!(
        store.retire(&retention(7, 0), now).unwrap(),
        [done[2].clone()]
    );
    drop(store);
    let store = Spool::open(&spool).unwrap();
    assert_eq!(store.jobs().count(), 0);
    let page = store.history_page(None, 100, &Default::default()).unwrap();
    let ids: Vec<&str> = page.jobs.iter().map(|r| r.id.as_str()).collect();
    assert_eq!(
        ids,
        [&done[2], &done[1], &done[0]],
        "each once, newest first"
    );
}

/// A job with `copies = 3` that becomes ready gets copies 2 and 3: ready jobs of their
/// own, with its G-code as hard links (not its pictures), made once, and kept across a
/// reopen; copies already made by a run that stopped before it marked the job are not
/// made again.
#[test]
fn a_ready_job_makes_its_copies_once() {
    use std::os::unix::fs::MetadataExt;
    let (_tmp, hot, spool, mut store) = open_with_hot_folder();
    let src = drop_file(&hot, "a.stl");
    std::fs::write(hot.join("a.stl.toml"), "copies = 3\n").unwrap();
    let id = store.admit(&src, &hot).unwrap().id;
    assert!(
        store.make_copies(&id).unwrap().is_empty(),
        "not prepared yet"
    );
    store.transition(&id, JobState::Preparing, None).unwrap();
    let dir = store.job_dir(&id);
    std::fs::write(dir.join("a.stl.ultimaker2.gcode"), "G28\n").unwrap();
    std::fs::write(dir.join("00001.jpg"), "picture").unwrap();
    store
        .transition_with(&id, JobState::Ready, None, |j| {
            j.sidecar = Some(crate::daemon::job::Sidecar {
                copies: Some(3),
                ..Default::default()
            });
            j.slice_report = Some(Default::default());
            j.machines.insert(
                "ultimaker2".into(),
                crate::daemon::job::ForMachine::Gcode("a.stl.ultimaker2.gcode".into()),
            );
        })
        .unwrap();
    let made = store.make_copies(&id).unwrap();
    assert_eq!(made.len(), 2);
    for (n, copy_id) in (2..).zip(&made) {
        let copy = store.get(copy_id).unwrap();
        assert_eq!(copy.state, JobState::Ready);
        assert_eq!(
            copy.copy.as_ref().map(|c| (c.job.as_str(), c.n)),
            Some((id.as_str(), n))
        );
        assert_eq!(
            copy.gcode_for("ultimaker2").as_deref(),
            Some("a.stl.ultimaker2.gcode")
        );
        let copy_dir = store.job_dir(copy_id);
        let gcode = copy_dir.join("a.stl.ultimaker2.gcode");
        assert_eq!(
            std::fs::metadata(&gcode).unwrap().ino(),
            std::fs::metadata(dir.join("a.stl.ultimaker2.gcode"))
                .unwrap()
                .ino(),
            "a hard link"
        );
        assert!(
            copy_dir.join("a.stl").is_file(),
            "the model, for a retry that prepares again"
        );
        assert!(
            !copy_dir.join("00001.jpg").exists(),
            "its pictures stay the job's"
        );
        assert!(copy.copies_due().is_empty(), "a copy makes none");
    }
    assert_eq!(store.get(&id).unwrap().copies_made, 3);
    assert!(store.make_copies(&id).unwrap().is_empty(), "made once");

    // A run that made copy 2 and stopped before it marked the job: copy 3 only.
    store.update(&id, |j| j.copies_made = 0).unwrap();
    let three = made[1].clone();
    std::fs::remove_dir_all(store.job_dir(&three)).unwrap();
    drop(store);
    let mut store = Spool::open(&spool).unwrap();
    assert!(store.get(&made[0]).is_some(), "copy 2 kept across a reopen");
    let again = store.make_copies(&id).unwrap();
    assert_eq!(again.len(), 1);
    assert_eq!(store.get(&again[0]).unwrap().copy.as_ref().unwrap().n, 3);
    let copies = store.jobs().filter(|j| j.copy.is_some()).count();
    assert_eq!(copies, 2);
}
