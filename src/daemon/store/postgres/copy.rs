//! A job's files in the farm database: stored and read back with binary `COPY`, in
//! pieces as they stream, never whole in memory; the files a job directory lacks on either
//! side. Apart because the framing of the `COPY` format is its own matter, whichever
//! change carries the files. The files are read and written off the runtime's threads
//! (`tokio::fs`, or a blocking thread for the atomic write).

use super::error::PgError;
use super::lease::PgStore;
use super::rows::ids;
use crate::daemon::job::Job;
use crate::daemon::store::blocking;
use postgres_protocol::escape::escape_literal;
use std::path::Path;

/// A file a job may not have in the database: the column holds at most 1 GiB.
pub const MAX_FILE_BYTES: u64 = 1 << 30;

/// A file stored with a job: small ones given whole, others read from their path as they
/// are sent, never whole in memory.
#[derive(Debug, Clone, Copy)]
pub enum FileBody<'a> {
    Bytes(&'a [u8]),
    Path(&'a Path),
}

impl PgStore {
    /// Stores (or replaces) one of a job's files.
    pub(crate) async fn put_file(&self, id: &str, name: &str, bytes: &[u8]) -> Result<(), PgError> {
        let client = self.client().await?;
        client
            .execute(
                "INSERT INTO job_files (job_id, name, bytes) VALUES ($1, $2, $3) \
                 ON CONFLICT (job_id, name) DO UPDATE SET bytes = EXCLUDED.bytes",
                &[&id, &name, &bytes],
            )
            .await?;
        Ok(())
    }

    /// The names of a job's files: its own, and (a copy) those of its first job, which
    /// it shares.
    pub(crate) async fn file_names(&self, job: &Job) -> Result<Vec<String>, PgError> {
        let client = self.client().await?;
        Ok(ids(client
            .query(
                "SELECT DISTINCT name FROM job_files WHERE job_id = $1 OR job_id = $2",
                &[&job.id, &job.group()],
            )
            .await?))
    }
}

/// Stores the regular files of `dir` that the job does not have in the database yet.
pub(super) async fn upload_missing(
    tx: &tokio_postgres::Transaction<'_>,
    id: &str,
    dir: &Path,
) -> Result<(), PgError> {
    let have: Vec<String> = ids(tx
        .query("SELECT name FROM job_files WHERE job_id = $1", &[&id])
        .await?);
    let file_err = |name: &str| {
        let (id, name) = (id.to_string(), name.to_string());
        move |source| PgError::File { id, name, source }
    };
    let mut entries = tokio::fs::read_dir(dir).await.map_err(file_err("."))?;
    while let Some(entry) = entries.next_entry().await.map_err(file_err("."))? {
        let name = entry.file_name().to_string_lossy().into_owned();
        let meta = entry.metadata().await.map_err(file_err(&name))?;
        let temporary = name.ends_with(".tmp") || name.starts_with(crate::fsutil::TEMP_PREFIX);
        if !meta.is_file() || have.contains(&name) || temporary {
            continue;
        }
        if meta.len() > MAX_FILE_BYTES {
            return Err(file_err(&name)(std::io::Error::other(format!(
                "{} bytes, more than the farm database keeps ({MAX_FILE_BYTES})",
                meta.len()
            ))));
        }
        copy_file_in(tx, id, &name, &entry.path()).await?;
    }
    Ok(())
}

/// The header of PostgreSQL's binary COPY format: signature, flags, extension length.
const COPY_HEADER: &[u8] = b"PGCOPY\n\xff\r\n\0\0\0\0\0\0\0\0\0";

/// Stores the file at `path` as job `id`'s file `name` with `COPY … FROM STDIN` in the
/// binary format, sending it in pieces as it is read: a G-code file of hundreds of MB is
/// never whole in this process's memory.
pub(super) async fn copy_file_in(
    tx: &tokio_postgres::Transaction<'_>,
    id: &str,
    name: &str,
    path: &Path,
) -> Result<(), PgError> {
    use futures_util::SinkExt;
    use tokio::io::AsyncReadExt;
    let file_err = |source| PgError::File {
        id: id.to_string(),
        name: name.to_string(),
        source,
    };
    let file = tokio::fs::File::open(path).await.map_err(file_err)?;
    let len = file.metadata().await.map_err(file_err)?.len();
    if len > MAX_FILE_BYTES {
        return Err(file_err(std::io::Error::other(format!(
            "{len} bytes, more than the farm database keeps ({MAX_FILE_BYTES})"
        ))));
    }
    let sink = tx
        .copy_in::<_, bytes::Bytes>(
            "COPY job_files (job_id, name, bytes) FROM STDIN (FORMAT binary)",
        )
        .await?;
    futures_util::pin_mut!(sink);
    // One row of three fields, each its length then its bytes; then the trailer.
    let mut head = COPY_HEADER.to_vec();
    head.extend_from_slice(&3i16.to_be_bytes());
    for text in [id, name] {
        head.extend_from_slice(&(text.len() as i32).to_be_bytes());
        head.extend_from_slice(text.as_bytes());
    }
    head.extend_from_slice(&(len as i32).to_be_bytes());
    sink.send(bytes::Bytes::from(head)).await?;
    let mut reader = file.take(len);
    let mut sent = 0u64;
    loop {
        let mut piece = vec![0u8; 1 << 20];
        let n = reader.read(&mut piece).await.map_err(file_err)?;
        if n == 0 {
            break;
        }
        piece.truncate(n);
        sent += n as u64;
        sink.send(bytes::Bytes::from(piece)).await?;
    }
    if sent != len {
        // The file shrank while it was read: the row would not match its length.
        return Err(file_err(std::io::Error::other(format!(
            "changed while it was stored ({sent} of {len} bytes read)"
        ))));
    }
    sink.send(bytes::Bytes::copy_from_slice(&(-1i16).to_be_bytes()))
        .await?;
    sink.as_mut().finish().await?;
    Ok(())
}

/// Writes job `id`'s file `name` to `to` with `COPY … TO STDOUT` in the binary format,
/// piece by piece as it arrives, atomically (see [`crate::fsutil`]).
async fn copy_file_out(
    tx: &tokio_postgres::Transaction<'_>,
    id: &str,
    name: &str,
    to: &Path,
) -> Result<(), PgError> {
    use futures_util::StreamExt;
    use std::io::Write;
    /// Written a piece this large at a time, on a blocking thread.
    const WRITE_PIECE: usize = 1 << 20;
    let file_err = |source| PgError::File {
        id: id.to_string(),
        name: name.to_string(),
        source,
    };
    let corrupt = |message: &str| PgError::Corrupt {
        id: id.to_string(),
        what: "file",
        message: format!("{name}: {message}"),
    };
    // COPY takes no parameters: the literals are spelt by the client library's escaping,
    // which is right whatever the server's `standard_conforming_strings`.
    let query = format!(
        "COPY (SELECT bytes FROM job_files WHERE job_id = {} AND name = {}) TO STDOUT (FORMAT binary)",
        escape_literal(id),
        escape_literal(name)
    );
    let stream = tx.copy_out(&query).await?;
    futures_util::pin_mut!(stream);
    let to = to.to_path_buf();
    let mut out = blocking(move || crate::fsutil::AtomicFile::create(&to))
        .await
        .map_err(|e| file_err(std::io::Error::from(e)))?;
    let mut unwritten: Vec<u8> = Vec::new();
    // Header, field count and length first; then the bytes, up to the trailer.
    const START: usize = COPY_HEADER.len() + 2 + 4;
    let mut head: Vec<u8> = Vec::new();
    let mut left: Option<u64> = None;
    let mut rows = 0;
    while let Some(piece) = stream.next().await {
        let piece = piece?;
        let data: &[u8] = match left {
            Some(_) => &piece,
            None => {
                head.extend_from_slice(&piece);
                if head.len() < START {
                    continue;
                }
                if !head.starts_with(&COPY_HEADER[..11]) {
                    return Err(corrupt("not a binary COPY answer"));
                }
                let size = i32::from_be_bytes([head[21], head[22], head[23], head[24]]);
                if size < 0 || size as u64 > MAX_FILE_BYTES {
                    return Err(corrupt("bad length"));
                }
                rows += 1;
                left = Some(size as u64);
                &head[START..]
            }
        };
        let want = left.unwrap_or(0);
        let take = (data.len() as u64).min(want) as usize;
        unwritten.extend_from_slice(&data[..take]);
        left = Some(want - take as u64);
        if unwritten.len() >= WRITE_PIECE {
            let piece = std::mem::take(&mut unwritten);
            out = blocking(move || out.file().write_all(&piece).map(|()| out))
                .await
                .map_err(file_err)?;
        }
    }
    if rows != 1 || left != Some(0) {
        return Err(corrupt("missing or cut short"));
    }
    blocking(move || {
        out.file().write_all(&unwritten)?;
        out.commit().map_err(std::io::Error::from)
    })
    .await
    .map_err(file_err)?;
    Ok(())
}

/// Writes the job's files that `dir` lacks (only its G-code with `only_gcode`): its own,
/// and those of its first job that a copy shares (a copy's own file of a name wins: a
/// copy prepared again has G-code of its own).
pub(super) async fn download_missing(
    tx: &tokio_postgres::Transaction<'_>,
    job: &Job,
    dir: &Path,
    only_gcode: bool,
) -> Result<(), PgError> {
    let id = job.id.as_str();
    let rows = tx
        .query(
            "SELECT DISTINCT ON (name) name, job_id FROM job_files \
             WHERE job_id = $1 OR job_id = $2 ORDER BY name, job_id = $1 DESC",
            &[&id, &job.group()],
        )
        .await?;
    let names: Vec<(String, String)> = rows.iter().map(|r| (r.get(0), r.get(1))).collect();
    let file_err = |name: &str| {
        let (id, name) = (id.to_string(), name.to_string());
        move |source| PgError::File { id, name, source }
    };
    tokio::fs::create_dir_all(dir)
        .await
        .map_err(file_err("."))?;
    for (name, owner) in names {
        // Names come from hosts of the farm; still, nothing leaves the job's directory.
        let plain = !name.is_empty() && !name.contains('/') && name != "." && name != "..";
        if !plain || (only_gcode && !name.ends_with(".gcode")) {
            continue;
        }
        let to = dir.join(&name);
        if tokio::fs::try_exists(&to).await.unwrap_or(false) {
            continue;
        }
        copy_file_out(tx, &owner, &name, &to).await?;
    }
    Ok(())
}
