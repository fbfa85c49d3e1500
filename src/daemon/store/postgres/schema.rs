//! The farm database's schema, created and migrated by the binary itself. Each migration
//! is applied once, in order, inside one transaction that holds an advisory lock, so hosts
//! starting together never race; `crispen_schema` records the version. A database whose
//! version is newer than this binary knows was written by a newer crispen: refuse it
//! rather than guess at its meaning.

use super::error::PgError;
use tokio_postgres::Client;

/// Every migration, oldest first; the schema's version is the number applied.
/// Never edit a released entry: append a new one.
const MIGRATIONS: &[&str] = &[
    // 1: hosts with leases, jobs with their history and files, printers.
    r#"
    CREATE TABLE hosts (
        name        text PRIMARY KEY,
        -- The host is alive while now() < lease_until; it renews by heartbeat.
        lease_until timestamptz NOT NULL,
        started_at  timestamptz NOT NULL DEFAULT now(),
        last_seen   timestamptz NOT NULL DEFAULT now(),
        -- Set once another host has applied the expiry rules to this host's work.
        expired_at  timestamptz
    );

    CREATE TABLE jobs (
        id          text PRIMARY KEY,
        seq         bigint GENERATED ALWAYS AS IDENTITY UNIQUE,
        file        text NOT NULL,
        -- The host whose hot folder it was dropped into, and that folder there.
        origin_host text NOT NULL,
        folder      text NOT NULL,
        -- The printers that may take it (the folder's rule), by name.
        printers    text[] NOT NULL,
        state       text NOT NULL CHECK (state IN ('queued', 'preparing', 'ready',
                        'printing', 'done', 'failed', 'cancelled', 'interrupted')),
        -- The host preparing or printing it, while it is preparing or printing.
        claimed_by  text REFERENCES hosts (name),
        printer     text,
        reason      text,
        sidecar     jsonb,
        copies_done integer NOT NULL DEFAULT 0,
        slice_report jsonb,
        print_report jsonb,
        updated_at  timestamptz NOT NULL DEFAULT now()
    );
    CREATE INDEX jobs_waiting ON jobs (state, seq) WHERE state IN ('queued', 'ready');

    CREATE TABLE job_history (
        job_id  text NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
        state   text NOT NULL,
        at      timestamptz NOT NULL DEFAULT now(),
        host    text NOT NULL
    );
    CREATE INDEX job_history_job ON job_history (job_id, at);

    -- The job's files (model, sidecar, G-code, pictures), so hosts share nothing else.
    CREATE TABLE job_files (
        job_id  text NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
        name    text NOT NULL,
        bytes   bytea NOT NULL,
        PRIMARY KEY (job_id, name)
    );

    CREATE TABLE printers (
        name            text PRIMARY KEY,
        host            text NOT NULL REFERENCES hosts (name),
        bed_not_cleared boolean NOT NULL DEFAULT false,
        last_job        text,
        status          jsonb,
        last_seen       timestamptz NOT NULL DEFAULT now()
    );
    "#,
    // 2: the whole job record (what the daemon keeps of a job beyond its state), each
    // printer's machine, and commands for a printer on another host.
    r#"
    ALTER TABLE jobs ADD COLUMN record jsonb;
    UPDATE jobs SET record = jsonb_build_object('sidecar', sidecar,
        'copies_done', copies_done, 'slice_report', slice_report, 'print_report', print_report);
    ALTER TABLE jobs ALTER COLUMN record SET NOT NULL,
        DROP COLUMN sidecar, DROP COLUMN copies_done, DROP COLUMN slice_report,
        DROP COLUMN print_report;
    CREATE INDEX jobs_updated ON jobs (updated_at);

    ALTER TABLE printers ADD COLUMN machine jsonb;

    CREATE TABLE commands (
        id         bigint GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
        -- The host whose printer it is for; it takes and carries out its commands.
        host       text NOT NULL,
        printer    text NOT NULL,
        command    text NOT NULL CHECK (command IN ('pause', 'resume', 'cancel')),
        created_at timestamptz NOT NULL DEFAULT now()
    );
    CREATE INDEX commands_host ON commands (host);
    "#,
    // 3: the run of crispen that holds a host's name: a random token each run takes with
    // the host's lease (issue 20: two daemons under one name printed a job twice).
    r#"
    ALTER TABLE hosts ADD COLUMN token text;
    "#,
    // 4: finished jobs leave the live queue for the history (issue 22): the row stays,
    // marked with when it was retired; hosts keep only the live ones in memory.
    r#"
    ALTER TABLE jobs ADD COLUMN retired_at timestamptz;
    CREATE INDEX jobs_history ON jobs (seq) WHERE retired_at IS NOT NULL;
    "#,
    // 5: the farm's spools and which printer holds which (issue 34): one document, changed
    // under its row's lock.
    r#"
    CREATE TABLE filament (
        id  integer PRIMARY KEY CHECK (id = 1),
        doc jsonb NOT NULL
    );
    "#,
    // 6: a bed's state between prints (issue 43: ejected by the printer, checked by its
    // camera) and the camera's last check; `bed_not_cleared` stays what claims read.
    r#"
    ALTER TABLE printers ADD COLUMN bed jsonb, ADD COLUMN last_check jsonb;
    "#,
    // 7: a part of a plate cancelled on another host's printer (issue 45): the command and
    // the part's name beside it.
    r#"
    ALTER TABLE commands DROP CONSTRAINT commands_command_check;
    ALTER TABLE commands ADD CONSTRAINT commands_command_check
        CHECK (command IN ('pause', 'resume', 'cancel', 'cancel-part'));
    ALTER TABLE commands ADD COLUMN part text;
    "#,
    // 8: which dropped file a job was made of (its folder, name, inode, size and
    // modification time): two hosts watching one shared hot folder both see a file, and
    // the one that comes second is refused instead of making a second job of it.
    r#"
    ALTER TABLE jobs ADD COLUMN pickup text;
    CREATE UNIQUE INDEX jobs_pickup ON jobs (pickup);
    "#,
];

/// The newest schema version this binary knows.
pub const SCHEMA_VERSION: i32 = MIGRATIONS.len() as i32;

/// Any number fixed for the farm: the advisory lock's key while migrating.
const MIGRATION_LOCK: i64 = 0x6372_6973_7065_6e00; // "crispen\0"

/// Brings the database to [`SCHEMA_VERSION`]; returns the version found before.
pub(crate) async fn migrate(client: &mut Client) -> Result<i32, PgError> {
    let tx = client.transaction().await?;
    tx.execute("SELECT pg_advisory_xact_lock($1)", &[&MIGRATION_LOCK])
        .await?;
    tx.batch_execute("CREATE TABLE IF NOT EXISTS crispen_schema (version integer NOT NULL)")
        .await?;
    let found: i32 = match tx
        .query_opt("SELECT version FROM crispen_schema", &[])
        .await?
    {
        Some(row) => row.get(0),
        None => {
            tx.execute("INSERT INTO crispen_schema (version) VALUES (0)", &[])
                .await?;
            0
        }
    };
    if found > SCHEMA_VERSION {
        return Err(PgError::SchemaTooNew {
            found,
            known: SCHEMA_VERSION,
        });
    }
    for (done, migration) in MIGRATIONS.iter().enumerate().skip(found as usize) {
        tx.batch_execute(migration)
            .await
            .map_err(|source| PgError::Migration {
                version: done as i32 + 1,
                source,
            })?;
    }
    tx.execute("UPDATE crispen_schema SET version = $1", &[&SCHEMA_VERSION])
        .await?;
    tx.commit().await?;
    Ok(found)
}
