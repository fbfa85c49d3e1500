//! The farm's queue in PostgreSQL, against a real server started for each test
//! (`tests/common/postgres.rs`): the schema and its versions, claims from many hosts at
//! once, lease expiry, one run per host name, an outage of the database, and the daemon's
//! job store over it
//! (two hosts' stores passing a job and its files between them, through an outage).

use crate::common;

use common::postgres::PgServer;
use crispen::daemon::config::PgSettings;
use crispen::daemon::job::{JobState, StoreError};
use crispen::daemon::store::postgres::{FileBody, PgError, PgStore};
use crispen::daemon::store::{JobChange, PreparedJob};
use std::collections::HashSet;
use std::time::Duration;

const LEASE: Duration = Duration::from_secs(30);

fn settings(pg: &PgServer) -> PgSettings {
    PgSettings {
        conninfo: pg.conninfo(),
        password_file: None,
    }
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(4)
        .enable_all()
        .build()
        .unwrap()
}

async fn admit_n(store: &PgStore, n: usize, printers: &[String]) -> Vec<String> {
    let mut ids = Vec::new();
    for i in 0..n {
        let job = store
            .admit(
                &format!("part{i}.stl"),
                "/srv/in",
                printers,
                &[("model", FileBody::Bytes(b"solid x"))],
                None,
            )
            .await
            .unwrap();
        ids.push(job.id);
    }
    ids
}

/// Two hosts watching one shared hot folder both see a dropped file: the second to admit
/// it is refused (the file is the first's), while the same name dropped again (another
/// file) is a job of its own.
#[test]
fn a_file_seen_by_two_hosts_is_one_job() {
    use crispen::daemon::job::StoreError;
    let pg = PgServer::start();
    runtime().block_on(async {
        let a = PgStore::connect(&settings(&pg), "rack-1", LEASE)
            .await
            .unwrap();
        let b = PgStore::connect(&settings(&pg), "rack-2", LEASE)
            .await
            .unwrap();
        let files = [("model", FileBody::Bytes(b"solid x"))];
        let first = a
            .admit(
                "part.stl",
                "/srv/in",
                &[],
                &files,
                Some("7:7:1.000000001:/srv/in/part.stl"),
            )
            .await
            .unwrap();
        match b
            .admit(
                "part.stl",
                "/srv/in",
                &[],
                &files,
                Some("7:7:1.000000001:/srv/in/part.stl"),
            )
            .await
        {
            Err(e) => match StoreError::from(e) {
                StoreError::TakenElsewhere { path } => {
                    assert_eq!(path, std::path::Path::new("/srv/in/part.stl"))
                }
                other => panic!("{other}"),
            },
            Ok(job) => panic!("a second job {} of one file", job.id),
        }
        let again = b
            .admit(
                "part.stl",
                "/srv/in",
                &[],
                &files,
                Some("8:7:2.000000001:/srv/in/part.stl"),
            )
            .await
            .unwrap();
        assert_ne!(first.id, again.id);
        assert_eq!(a.jobs().await.unwrap().len(), 2);
    });
}

#[test]
fn schema_is_created_once_and_a_newer_one_is_refused() {
    let pg = PgServer::start();
    runtime().block_on(async {
        let a = PgStore::connect(&settings(&pg), "rack-1", LEASE)
            .await
            .unwrap();
        // A second host finds the schema in place and changes nothing.
        PgStore::connect(&settings(&pg), "rack-2", LEASE)
            .await
            .unwrap();
        let (client, conn) = tokio_postgres::connect(&pg.conninfo(), tokio_postgres::NoTls)
            .await
            .unwrap();
        tokio::spawn(conn);
        let version: i32 = client
            .query_one("SELECT version FROM crispen_schema", &[])
            .await
            .unwrap()
            .get(0);
        assert_eq!(
            version,
            crispen::daemon::store::postgres::schema::SCHEMA_VERSION
        );
        let rows = client
            .query("SELECT * FROM crispen_schema", &[])
            .await
            .unwrap();
        assert_eq!(rows.len(), 1, "one version row");
        drop(a);

        client
            .execute("UPDATE crispen_schema SET version = version + 1", &[])
            .await
            .unwrap();
        match PgStore::connect(&settings(&pg), "rack-3", LEASE).await {
            Err(PgError::SchemaTooNew { found, known }) => assert_eq!(found, known + 1),
            Err(other) => panic!("expected a refusal of the newer schema, got {other}"),
            Ok(_) => panic!("a newer schema was accepted"),
        }
    });
}

#[test]
fn a_password_in_the_connection_string_is_refused() {
    let bad = PgSettings {
        conninfo: "host=/nonexistent dbname=crispen password=hunter2".into(),
        password_file: None,
    };
    let err = runtime()
        .block_on(PgStore::connect(&bad, "rack-1", LEASE))
        .err()
        .expect("refused");
    let message = err.to_string();
    assert!(
        matches!(err, PgError::PasswordInConnectionString(_)),
        "{message}"
    );
    assert!(
        !message.contains("hunter2"),
        "the password leaked: {message}"
    );
}

/// Three hosts with eight claimers each race for 300 queued jobs: every job is claimed
/// exactly once, and nothing is left over.
#[test]
fn concurrent_claims_from_three_hosts_take_each_job_once() {
    let pg = PgServer::start();
    runtime().block_on(async {
        let mut hosts = Vec::new();
        for name in ["rack-1", "rack-2", "rack-3"] {
            hosts.push(PgStore::connect(&settings(&pg), name, LEASE).await.unwrap());
        }
        let ids = admit_n(&hosts[0], 300, &["a".to_string()]).await;
        let mut tasks = Vec::new();
        for host in &hosts {
            for _ in 0..8 {
                let host = host.clone();
                tasks.push(tokio::spawn(async move {
                    let mut mine = Vec::new();
                    while let Some(job) = host.claim_preparation().await.unwrap() {
                        assert_eq!(job.state, JobState::Preparing);
                        mine.push(job.id);
                    }
                    mine
                }));
            }
        }
        let mut seen = HashSet::new();
        for task in tasks {
            for id in task.await.unwrap() {
                assert!(seen.insert(id.clone()), "{id} was claimed twice");
            }
        }
        assert_eq!(seen, ids.into_iter().collect::<HashSet<_>>());
    });
}

/// A host that stops renewing its lease loses its work: its preparing job goes back to
/// the queue, its printing job becomes interrupted (never reprinted on its own), its
/// printer is shown offline and held for its bed, and its late outcome is refused.
#[test]
fn an_expired_lease_requeues_preparation_and_interrupts_printing() {
    let pg = PgServer::start();
    runtime().block_on(async {
        // Long enough that the claims below fit in it on a loaded machine (a one-second
        // lease once ran out before "nothing expires" was asserted); its end is waited
        // for by polling below, so it costs only its length.
        let dying = PgStore::connect(&settings(&pg), "rack-1", Duration::from_secs(5))
            .await
            .unwrap();
        let alive = PgStore::connect(&settings(&pg), "rack-2", LEASE)
            .await
            .unwrap();
        dying.register_printer("a", None).await.unwrap();
        alive.register_printer("b", None).await.unwrap();
        admit_n(&alive, 2, &["a".to_string(), "b".to_string()]).await;

        let printed = dying.claim_preparation().await.unwrap().unwrap();
        dying
            .finish(&printed.id, &[JobState::Preparing], JobState::Ready, None)
            .await
            .unwrap();
        let printing = dying.claim_print("a").await.unwrap().unwrap();
        assert_eq!(printing.id, printed.id);
        let prepared = dying.claim_preparation().await.unwrap().unwrap();

        // Nothing expires while the lease holds.
        assert_eq!(
            alive.expire_hosts().await.unwrap().hosts,
            Vec::<String>::new()
        );
        // Once the lease has run out by the database's clock, the next sweep takes the
        // host's work back.
        let deadline = std::time::Instant::now() + Duration::from_secs(30);
        let expired = loop {
            let expired = alive.expire_hosts().await.unwrap();
            if !expired.hosts.is_empty() {
                break expired;
            }
            assert!(
                std::time::Instant::now() < deadline,
                "the lease never ran out"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        };
        assert_eq!(expired.hosts, vec!["rack-1".to_string()]);
        assert_eq!(expired.requeued, vec![prepared.id.clone()]);
        assert_eq!(expired.interrupted, vec![printing.id.clone()]);
        // Each dead host is handled once.
        assert_eq!(alive.expire_hosts().await.unwrap(), Default::default());

        let job = alive.job(&printing.id).await.unwrap();
        assert_eq!(job.state, JobState::Interrupted);
        assert!(job.reason.unwrap().contains("rack-1"));
        let states: Vec<JobState> = job.history.iter().map(|h| h.0).collect();
        assert_eq!(
            states,
            [
                JobState::Queued,
                JobState::Preparing,
                JobState::Ready,
                JobState::Printing,
                JobState::Interrupted
            ]
        );
        let printers = alive.printers().await.unwrap();
        let a = printers.iter().find(|p| p.name == "a").unwrap();
        assert!(a.offline && a.bed_not_cleared, "{a:?}");
        assert_eq!(a.last_job.as_deref(), Some(printing.id.as_str()));
        assert!(!printers.iter().find(|p| p.name == "b").unwrap().offline);

        // The dead host comes back: its outcomes are refused, it holds nothing.
        dying.heartbeat(LEASE).await.unwrap();
        match dying
            .finish(&printing.id, &[JobState::Printing], JobState::Done, None)
            .await
        {
            Err(PgError::Job(StoreError::StateChanged { state, .. })) => {
                assert_eq!(state, JobState::Interrupted)
            }
            other => panic!("expected a refusal, got {other:?}"),
        }
        assert!(matches!(
            dying
                .finish(&prepared.id, &[JobState::Preparing], JobState::Ready, None)
                .await,
            Err(PgError::Job(StoreError::StateChanged { .. }))
        ));
        // The requeued job is the living host's to take; the interrupted one waits for
        // an operator, and printer a's bed gate holds it.
        let again = alive.claim_preparation().await.unwrap().unwrap();
        assert_eq!(again.id, prepared.id);
        assert!(dying.claim_print("a").await.unwrap().is_none());
    });
}

/// One run per host name (issue 20): a second connection under a live host's name is
/// refused with the time left on its lease; once that lease has run out, a new run takes
/// the name over and hands back the first run's work; the first run, displaced, can
/// neither claim, renew nor record an outcome.
#[test]
fn a_host_name_is_held_by_one_run_at_a_time() {
    let pg = PgServer::start();
    runtime().block_on(async {
        let lease = Duration::from_secs(2);
        let first = PgStore::connect(&settings(&pg), "rack-1", lease)
            .await
            .unwrap();
        first.register_printer("a", None).await.unwrap();
        admit_n(&first, 2, &["a".to_string()]).await;
        let preparing = first.claim_preparation().await.unwrap().unwrap();
        match PgStore::connect(&settings(&pg), "rack-1", lease).await {
            Err(PgError::HostInUse { host, remaining_s }) => {
                assert_eq!(host, "rack-1");
                assert!((0.0..=2.0).contains(&remaining_s), "{remaining_s}");
            }
            other => panic!("a second run under a live name: {:?}", other.map(|_| ())),
        }
        // Nothing of the first run's was taken.
        let job = first.job(&preparing.id).await.unwrap();
        assert_eq!(job.state, JobState::Preparing);

        // The lease runs out (no heartbeat): the name can be taken over.
        let second = loop {
            match PgStore::connect(&settings(&pg), "rack-1", LEASE).await {
                Ok(store) => break store,
                Err(PgError::HostInUse { .. }) => {
                    tokio::time::sleep(Duration::from_millis(200)).await
                }
                Err(e) => panic!("{e}"),
            }
        };
        assert_eq!(
            second.recover_own().await.unwrap(),
            vec![preparing.id.clone()]
        );
        // Refused by the check inside the claim's transaction, before anything told the
        // first run (its heartbeat) that it was displaced.
        assert!(matches!(
            first.claim_preparation().await,
            Err(PgError::Displaced { .. })
        ));
        assert!(matches!(
            first.heartbeat(LEASE).await,
            Err(PgError::Displaced { .. })
        ));
        assert!(matches!(
            first
                .finish(&preparing.id, &[JobState::Preparing], JobState::Ready, None)
                .await,
            Err(PgError::Displaced { .. })
        ));
        // The second run works as the host.
        let again = second.claim_preparation().await.unwrap().unwrap();
        second
            .finish(&again.id, &[JobState::Preparing], JobState::Ready, None)
            .await
            .unwrap();
        second.heartbeat(LEASE).await.unwrap();
    });
}

/// The database stopped for a while: calls fail within seconds with an error that says
/// so, and the same store works again once it is back, with nothing lost.
#[test]
fn an_outage_fails_calls_quickly_and_the_store_recovers() {
    let mut pg = PgServer::start();
    let rt = runtime();
    let store = rt.block_on(async {
        let store = PgStore::connect(&settings(&pg), "rack-1", LEASE)
            .await
            .unwrap();
        admit_n(&store, 3, &["a".to_string()]).await;
        store
    });
    pg.stop();
    rt.block_on(async {
        let outcome = tokio::time::timeout(Duration::from_secs(30), store.jobs()).await;
        let err = outcome
            .expect("a call during an outage must fail, not hang")
            .unwrap_err();
        assert!(
            matches!(err, PgError::Pool(_) | PgError::Db(_)),
            "unexpected error: {err}"
        );
    });
    pg.restart();
    rt.block_on(async {
        // The pool drops its broken connections and opens new ones.
        let mut jobs = Err(PgError::Job(StoreError::Stopped));
        for _ in 0..50 {
            jobs = store.jobs().await;
            if jobs.is_ok() {
                break;
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
        let jobs = jobs.expect("the store works again after the outage");
        assert_eq!(jobs.len(), 3);
        assert!(jobs.iter().all(|j| j.state == JobState::Queued));
    });
}

/// The daemon's store over the database, as two hosts use it through the store's task: a
/// file picked up on one host is prepared on the other (the model is copied there), its
/// G-code goes to the database as it becomes ready and to the printing host as that claims
/// it; a host that comes second is refused; an outcome recorded while the database is down
/// is kept and written once it is back, and the other host sees it.
#[test]
fn two_hosts_stores_pass_a_job_and_its_files_through_an_outage() {
    use crispen::daemon::job::ForMachine;
    use crispen::daemon::store::postgres::store::PgJobStore;
    let mut pg = PgServer::start();
    let tmp = tempfile::tempdir().unwrap();
    let hot = tmp.path().join("hot");
    std::fs::create_dir_all(&hot).unwrap();
    let rt = runtime();
    let (a, b) = rt.block_on(async {
        let open = |host: &'static str| {
            let (settings, dir) = (settings(&pg), tmp.path().join(host));
            async move {
                let db = PgStore::connect(&settings, host, LEASE).await.unwrap();
                let store = PgJobStore::open(db, &dir).await.unwrap();
                crispen::daemon::store::spawn(store)
            }
        };
        (open("rack-1").await, open("rack-2").await)
    });
    // A quote and a backslash in the name: the COPY that fetches the files spells it as an
    // SQL literal, on a server whose `standard_conforming_strings` is off (common::postgres).
    let name = r"it's a \ part.stl";
    let model = hot.join(name);
    std::fs::write(&model, b"solid part\nendsolid part\n").unwrap();
    std::fs::write(hot.join(format!("{name}.toml")), b"copies = 1\n").unwrap();
    let printers = vec!["p1".to_string()];
    let job = rt.block_on(a.admit(&model, &hot, &printers)).unwrap();
    assert!(!model.exists(), "the model left the hot folder");
    let origin = job.origin.clone().expect("a farm job knows its origin");
    assert_eq!(
        (origin.host.as_str(), origin.printers),
        ("rack-1", printers)
    );

    // Host 2 sees it after a resync, prepares it (the model and sidecar are copied there),
    // and host 1 coming second is refused.
    assert!(rt.block_on(b.resync()).unwrap(), "the new job is a change");
    let queued: &[JobState] = &[JobState::Queued];
    rt.block_on(b.transition_from(
        &job.id,
        queued,
        JobState::Preparing,
        None,
        JobChange::Nothing,
    ))
    .unwrap();
    let dir_b = b.snapshot().job_dir(&job.id);
    assert_eq!(
        std::fs::read(dir_b.join(name)).unwrap(),
        b"solid part\nendsolid part\n"
    );
    assert!(dir_b.join(format!("{name}.toml")).is_file());
    match rt.block_on(a.transition_from(
        &job.id,
        queued,
        JobState::Preparing,
        None,
        JobChange::Nothing,
    )) {
        Err(StoreError::StateChanged { state, .. }) => assert_eq!(state, JobState::Preparing),
        other => panic!("host 1 took a job host 2 had: {other:?}"),
    }
    // Only the preparing host records the preparation's outcome.
    let preparing: &[JobState] = &[JobState::Preparing];
    assert!(matches!(
        rt.block_on(a.transition_from(
            &job.id,
            preparing,
            JobState::Ready,
            None,
            JobChange::Nothing
        )),
        Err(StoreError::LostClaim { .. })
    ));
    std::fs::write(dir_b.join(format!("{name}.m.gcode")), b"G28\nM84\n").unwrap();
    rt.block_on(b.transition_from(
        &job.id,
        preparing,
        JobState::Ready,
        None,
        JobChange::Prepared(Box::new(PreparedJob {
            machines: [("m".into(), ForMachine::Gcode(format!("{name}.m.gcode")))].into(),
            needs: Default::default(),
            sidecar: None,
            asks: Default::default(),
            report: None,
            comparison: None,
        })),
    ))
    .unwrap();

    // Host 1 claims it for its printer: the G-code arrives in its job directory.
    rt.block_on(a.resync()).unwrap();
    let claimed = rt
        .block_on(a.claim("p1", |j| j.gcode_for("m").is_some()))
        .unwrap()
        .expect("the ready job is claimed");
    assert_eq!(claimed.printer.as_deref(), Some("p1"));
    let dir_a = a.snapshot().job_dir(&job.id);
    assert_eq!(
        std::fs::read(dir_a.join(format!("{name}.m.gcode"))).unwrap(),
        b"G28\nM84\n"
    );
    rt.block_on(b.resync()).unwrap();
    assert!(
        rt.block_on(b.claim("p2", |_| true)).unwrap().is_none(),
        "claimed once"
    );

    // The print ends while the database is down: the outcome and the bed gate are kept.
    pg.stop();
    let done = rt
        .block_on(a.record_outcome(
            &job.id,
            JobState::Done,
            None,
            JobChange::Printed {
                report: Some(Default::default()),
                usage: None,
            },
        ))
        .expect("an outcome that happened is kept");
    assert_eq!(done.state, JobState::Done);
    rt.block_on(a.close_gate("p1", &job.id)).unwrap();
    let gate = a.snapshot().gate("p1");
    assert!(gate.bed_not_cleared());
    assert_eq!(gate.last_job.as_deref(), Some(job.id.as_str()));
    assert_eq!(a.snapshot().unwritten(), 2);
    assert!(matches!(
        rt.block_on(b.transition(&job.id, JobState::Cancelled, None)),
        Err(e) if e.is_outage()
    ));
    pg.restart();
    let mut left = usize::MAX;
    for _ in 0..100 {
        left = rt.block_on(a.write_pending()).unwrap();
        if left == 0 {
            break;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    assert_eq!(left, 0, "written once the database is back");
    assert!(rt.block_on(b.resync()).unwrap());
    let seen = b.snapshot();
    let job_b = seen.get(&job.id).unwrap();
    assert_eq!((job_b.state, job_b.copies_done), (JobState::Done, 1));
    let states: Vec<JobState> = job_b.history.iter().map(|h| h.0).collect();
    assert_eq!(
        states,
        [
            JobState::Queued,
            JobState::Preparing,
            JobState::Ready,
            JobState::Printing,
            JobState::Done
        ]
    );
    assert_eq!(seen.gate("p1"), gate);

    // Each host counts every change once, its own and the other's it took in by a
    // resync (before, only the changes a host made itself were counted, by a wrapper
    // around its requests): both see the whole farm.
    rt.block_on(a.resync()).unwrap();
    for (host, store) in [("rack-1", &a), ("rack-2", &b)] {
        let snapshot = store.snapshot();
        let counts = snapshot.counts();
        for state in states.iter().copied() {
            assert_eq!(counts.entered(state), 1, "{host}: into {state}");
        }
        assert_eq!(counts.finished(), 1, "{host}");
        let tally = snapshot.tally().read();
        let p1 = &tally["p1"];
        assert_eq!((p1.done, p1.prints), (1, 1), "{host}: the print on p1");
    }
}

/// Retention in the farm database, through two hosts' stores: finished jobs beyond the
/// live count leave both hosts' snapshots (rows marked retired, never deleted); the
/// history pages through them from any host, a third host opening later finds them there
/// and not live, and no host retries one. On the way: a job prepared before machines
/// existed (its G-code `<file>.gcode`) is retried straight to ready, as the spool does
/// (the database store sent it to be prepared again), and its files go to and from the
/// database streamed.
#[test]
fn retired_jobs_leave_every_hosts_memory_and_stay_in_the_history() {
    use crispen::daemon::store::postgres::store::PgJobStore;
    use crispen::daemon::store::Retention;
    let pg = PgServer::start();
    let tmp = tempfile::tempdir().unwrap();
    let hot = tmp.path().join("hot");
    std::fs::create_dir_all(&hot).unwrap();
    let rt = runtime();
    let retention = Retention {
        live_for: Duration::from_secs(86_400),
        live_jobs: 1,
        keep_for: None,
    };
    let open_with = |host: &'static str, retention: Retention| {
        let (settings, dir) = (settings(&pg), tmp.path().join(host));
        async move {
            let db = PgStore::connect(&settings, host, LEASE).await.unwrap();
            let store = PgJobStore::open(db, &dir).await.unwrap();
            crispen::daemon::store::spawn_with(store, retention)
        }
    };
    let open = |host: &'static str| open_with(host, retention);
    // Host 2 keeps more live: it retires nothing itself, and holds what host 1 retired
    // until it resyncs.
    let roomy = Retention {
        live_jobs: 100,
        ..retention
    };
    let (a, b) = rt.block_on(async { (open("rack-1").await, open_with("rack-2", roomy).await) });
    let printers = vec!["p1".to_string()];
    let mut ids = Vec::new();
    for i in 0..3 {
        let model = hot.join(format!("part{i}.stl"));
        std::fs::write(&model, format!("solid {i}\nendsolid {i}\n")).unwrap();
        ids.push(rt.block_on(a.admit(&model, &hot, &printers)).unwrap().id);
    }
    for id in &ids[1..] {
        rt.block_on(a.transition(id, JobState::Cancelled, None))
            .unwrap();
    }
    // Two finished, one kept live: the older leaves at the change that made one too many.
    let live: Vec<String> = a.snapshot().jobs().map(|j| j.id.clone()).collect();
    assert_eq!(live, [ids[0].clone(), ids[2].clone()]);

    // The first job is prepared the old way: one `<file>.gcode`, no machines.
    let queued: &[JobState] = &[JobState::Queued];
    let preparing: &[JobState] = &[JobState::Preparing];
    rt.block_on(a.transition_from(
        &ids[0],
        queued,
        JobState::Preparing,
        None,
        JobChange::Nothing,
    ))
    .unwrap();
    let gcode: Vec<u8> = (0..200_000)
        .flat_map(|i| format!("G1 X{} Y{}\n", i % 200, i % 7).into_bytes())
        .collect();
    let dir_a = a.snapshot().job_dir(&ids[0]);
    std::fs::write(dir_a.join("part0.stl.gcode"), &gcode).unwrap();
    rt.block_on(a.transition_from(
        &ids[0],
        preparing,
        JobState::Ready,
        None,
        JobChange::Prepared(Box::new(PreparedJob {
            machines: Default::default(),
            needs: Default::default(),
            sidecar: None,
            asks: Default::default(),
            report: Some(Default::default()),
            comparison: None,
        })),
    ))
    .unwrap();
    rt.block_on(b.resync()).unwrap();
    rt.block_on(b.claim("p1", |_| true))
        .unwrap()
        .expect("host 2 claims the ready job");
    let dir_b = b.snapshot().job_dir(&ids[0]);
    assert!(
        std::fs::read(dir_b.join("part0.stl.gcode")).unwrap() == gcode,
        "the G-code arrived whole"
    );
    rt.block_on(b.record_outcome(
        &ids[0],
        JobState::Cancelled,
        Some("stopped".into()),
        JobChange::Nothing,
    ))
    .unwrap();
    rt.block_on(a.resync()).unwrap();
    let retried = rt.block_on(a.retry(&ids[0])).unwrap();
    assert_eq!(
        retried.state,
        JobState::Ready,
        "its G-code is kept: printed again as it was"
    );
    // The newest finished job (the first, cancelled last) stays live; the other leaves
    // at once, and a round finds nothing more.
    rt.block_on(a.transition(&ids[0], JobState::Cancelled, None))
        .unwrap();
    let live: Vec<String> = a.snapshot().jobs().map(|j| j.id.clone()).collect();
    assert_eq!(live, [ids[0].clone()]);
    let now = crispen::daemon::job::now_s();
    assert!(rt.block_on(a.retire(now)).unwrap().is_empty());

    // Host 2 has not seen it yet: its change is refused by the database all the same.
    assert!(b.snapshot().get(&ids[2]).is_some());
    let err = rt.block_on(b.retry(&ids[2])).unwrap_err();
    assert!(matches!(err, StoreError::WrongState { .. }), "{err}");
    assert!(rt.block_on(b.resync()).unwrap());
    assert!(b.snapshot().get(&ids[1]).is_none() && b.snapshot().get(&ids[2]).is_none());
    let err = rt.block_on(b.retry(&ids[1])).unwrap_err();
    assert!(err.to_string().contains("history"), "{err}");

    let page = rt.block_on(b.history(None, 1)).unwrap();
    assert_eq!(page.jobs[0].id, ids[2]);
    let page = rt.block_on(b.history(page.next, 1)).unwrap();
    assert_eq!(page.jobs[0].id, ids[1]);
    assert_eq!(page.next, None);
    let retired = rt.block_on(a.retired(&ids[1])).unwrap().unwrap();
    assert_eq!(retired.record.state, JobState::Cancelled);
    assert_eq!(retired.record.file, "part1.stl");

    // A host started later loads the live jobs only, and finds the rest in the history.
    let c = rt.block_on(open("rack-3"));
    let live: Vec<String> = c.snapshot().jobs().map(|j| j.id.clone()).collect();
    assert_eq!(live, [ids[0].clone()]);
    assert_eq!(rt.block_on(c.history(None, 10)).unwrap().jobs.len(), 2);

    // The farm's history filtered, and its statistics, from a host that made none of it.
    use crispen::daemon::store::history::Filter;
    let cancelled = Filter {
        state: Some(JobState::Cancelled),
        folder: Some("hot".into()),
        ..Filter::default()
    };
    let page = rt
        .block_on(c.history_where(None, 1, cancelled.clone()))
        .unwrap();
    assert_eq!(page.jobs[0].id, ids[2]);
    let page = rt
        .block_on(c.history_where(page.next, 1, cancelled))
        .unwrap();
    assert_eq!(page.jobs[0].id, ids[1]);
    assert_eq!(page.next, None);
    let done = Filter {
        state: Some(JobState::Done),
        ..Filter::default()
    };
    assert!(rt
        .block_on(c.history_where(None, 10, done))
        .unwrap()
        .jobs
        .is_empty());
    let now = crispen::daemon::job::now_s();
    let period = crispen::daemon::store::stats::Period::new(now - 3600.0, now + 60.0).unwrap();
    let stats = rt
        .block_on(c.stats(period, vec!["p1".into()], vec!["hot".into()], now))
        .unwrap();
    // Two from the history, one live.
    assert_eq!(stats.farm.jobs.cancelled, 3, "{stats:?}");
    assert_eq!(stats.folders.len(), 1);
    assert_eq!(stats.folders[0].name, "hot");
    assert_eq!(stats.folders[0].jobs.cancelled, 3);
    assert_eq!(stats.printers[0].name, "p1");

    // `[history] keep_days`: retired jobs older than it leave the database, history and all.
    let db = rt
        .block_on(PgStore::connect(&settings(&pg), "rack-4", LEASE))
        .unwrap();
    let mut gone = rt.block_on(db.forget_retired(now + 1.0)).unwrap();
    gone.sort();
    assert_eq!(gone, ids[1..].to_vec());
    assert!(rt.block_on(c.history(None, 10)).unwrap().jobs.is_empty());
    assert!(c.snapshot().get(&ids[0]).is_some(), "a live job stays");
}
