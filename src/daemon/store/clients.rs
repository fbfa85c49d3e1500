//! What clients are told of the spool: a reason names the files inside it relative to
//! it, never by the server's path. Apart because the spool (its own reasons) and the
//! store's task (every reason it keeps) both use it.

use super::job_store::JobStore;
use std::path::Path;

/// A job's reason as it is kept: the API, the dashboard, the history and notifications show
/// it to clients, which are never told the server's paths (the log has them). Whoever
/// built the reason (a preparation, a printer, a policy) may have named a file by its
/// path; every path inside the spool is named relative to it here (`jobs/<id>/part.gcode`).
pub(super) fn for_clients(reason: &str, store: &dyn JobStore) -> String {
    let jobs = store.jobs_dir();
    spool_relative(reason, jobs.parent().unwrap_or(&jobs))
}

/// `text` with every path inside `spool` named relative to it (`jobs/<id>/job.json`), and
/// `spool` itself as "the spool". The spool's path is matched as it is written and as it
/// resolves (a spool under a symbolic link), only where it is a whole path, not a piece of
/// a longer name (`/srv/spool` in `/srv/spool2/x` is left alone).
pub(crate) fn spool_relative(text: &str, spool: &Path) -> String {
    let mut spellings: Vec<String> = vec![spool.to_string_lossy().into_owned()];
    if let Ok(real) = spool.canonicalize() {
        spellings.push(real.to_string_lossy().into_owned());
    }
    let mut spellings: Vec<String> = spellings
        .into_iter()
        .map(|s| s.trim_end_matches('/').to_string())
        // A spool at `/` or `` would match everything: nothing to hide that way.
        .filter(|s| s.len() > 1)
        .collect();
    // The longest first, so a spelling inside another does not cut it short.
    spellings.sort_by_key(|s| std::cmp::Reverse(s.len()));
    spellings.dedup();
    let in_path = |c: char| c.is_alphanumeric() || matches!(c, '/' | '.' | '_' | '-' | '~');
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    'scan: while !rest.is_empty() {
        let before = out.chars().next_back();
        if !before.is_some_and(in_path) {
            for spelling in &spellings {
                let Some(after) = rest.strip_prefix(spelling.as_str()) else {
                    continue;
                };
                if let Some(inside) = after.strip_prefix('/') {
                    rest = inside;
                    continue 'scan;
                }
                if !after.chars().next().is_some_and(in_path) {
                    out.push_str("the spool");
                    rest = after;
                    continue 'scan;
                }
            }
        }
        let c = rest.chars().next().expect("not empty");
        out.push(c);
        rest = &rest[c.len_utf8()..];
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Paths inside the spool are named relative to it, wherever they stand in a reason;
    /// a longer name that merely begins like the spool is not touched.
    #[test]
    fn reasons_name_spool_files_relative_to_it() {
        let spool = Path::new("/srv/crispen/spool");
        let cases = [
            (
                "spool /srv/crispen/spool/jobs/0001-a/job.json: unreadable job state: eof; \
                 the directory /srv/crispen/spool/jobs/0001-a is kept as it was",
                "spool jobs/0001-a/job.json: unreadable job state: eof; \
                 the directory jobs/0001-a is kept as it was",
            ),
            (
                "cannot load the G-code: \"/srv/crispen/spool/jobs/0002-b/b.gcode\":12: bad",
                "cannot load the G-code: \"jobs/0002-b/b.gcode\":12: bad",
            ),
            ("in /srv/crispen/spool: full", "in the spool: full"),
            ("/srv/crispen/spool/", ""),
            (
                "/srv/crispen/spool2/x and x/srv/crispen/spool/y and /srv/crispen/spoolx",
                "/srv/crispen/spool2/x and x/srv/crispen/spool/y and /srv/crispen/spoolx",
            ),
            ("café /srv/crispen/spool/jobs/é", "café jobs/é"),
            ("nothing to see", "nothing to see"),
        ];
        for (text, want) in cases {
            assert_eq!(spool_relative(text, spool), want, "{text}");
            // A spool named with a trailing slash is the same spool.
            assert_eq!(
                spool_relative(text, Path::new("/srv/crispen/spool/")),
                want,
                "{text}"
            );
        }
        // Under a symbolic link: both the link's path and the real one.
        let tmp = tempfile::tempdir().unwrap();
        let real = tmp.path().join("real");
        std::fs::create_dir(&real).unwrap();
        let link = tmp.path().join("link");
        std::os::unix::fs::symlink(&real, &link).unwrap();
        let real = real.canonicalize().unwrap();
        let text = format!("{}/jobs/a and {}/jobs/b", link.display(), real.display());
        assert_eq!(spool_relative(&text, &link), "jobs/a and jobs/b");
        // A spool at the root hides nothing (every path would match).
        assert_eq!(spool_relative("/etc/x", Path::new("/")), "/etc/x");
    }
}
