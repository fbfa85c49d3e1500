//! The farm's queue in PostgreSQL, against a real server started for each test
//! (`tests/common/postgres.rs`): the schema and its versions, claims from many hosts at
//! once, lease expiry, and an outage of the database.

mod common;

use common::postgres::PgServer;
use crispen::daemon::job::JobState;
use crispen::daemon::store::postgres::{PgError, PgSettings, PgStore};
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
        let id = format!("job-{i:04}");
        store
            .admit(
                &id,
                &format!("part{i}.stl"),
                "/srv/in",
                printers,
                &[("model", b"solid x")],
            )
            .await
            .unwrap();
        ids.push(id);
    }
    ids
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
        let dying = PgStore::connect(&settings(&pg), "rack-1", Duration::from_secs(1))
            .await
            .unwrap();
        let alive = PgStore::connect(&settings(&pg), "rack-2", LEASE)
            .await
            .unwrap();
        dying.register_printer("a").await.unwrap();
        alive.register_printer("b").await.unwrap();
        admit_n(&alive, 2, &["a".to_string(), "b".to_string()]).await;

        let printed = dying.claim_preparation().await.unwrap().unwrap();
        dying
            .finish(&printed.id, JobState::Preparing, JobState::Ready, None)
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
        tokio::time::sleep(Duration::from_millis(1500)).await;
        let expired = alive.expire_hosts().await.unwrap();
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
            .finish(&printing.id, JobState::Printing, JobState::Done, None)
            .await
        {
            Err(PgError::LostClaim { state, .. }) => assert_eq!(state, JobState::Interrupted),
            other => panic!("expected a lost claim, got {other:?}"),
        }
        assert!(matches!(
            dying
                .finish(&prepared.id, JobState::Preparing, JobState::Ready, None)
                .await,
            Err(PgError::LostClaim { .. })
        ));
        // The requeued job is the living host's to take; the interrupted one waits for
        // an operator, and printer a's bed gate holds it.
        let again = alive.claim_preparation().await.unwrap().unwrap();
        assert_eq!(again.id, prepared.id);
        assert!(dying.claim_print("a").await.unwrap().is_none());
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
        let mut jobs = Err(PgError::NoSuchJob(String::new()));
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
