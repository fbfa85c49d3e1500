//! Commands between hosts: an operator's pause, resume or cancel of a print, left in the
//! database for the host of the printer, which takes them. Apart because the table is a
//! mailbox with rules of its own (a row taken is a row answered).

use super::error::PgError;
use super::lease::PgStore;

impl PgStore {
    /// Asks the host of `printer` to pause, resume or cancel its print; false when the
    /// farm has no such printer.
    pub(crate) async fn push_command(
        &self,
        printer: &str,
        command: &crate::daemon::command::PrintCommand,
    ) -> Result<bool, PgError> {
        let client = self.client().await?;
        let added = client
            .execute(
                "INSERT INTO commands (host, printer, command, part) \
                 SELECT host, name, $2, $3 FROM printers WHERE name = $1",
                &[&printer, &command.word(), &command.part()],
            )
            .await?;
        Ok(added == 1)
    }

    /// Takes the commands other hosts left for this host's printers, oldest first, each
    /// parsed: an unknown one is taken out of the table all the same (the table has no
    /// state; a row taken is a row answered), for the caller to log and refuse.
    #[allow(clippy::type_complexity)]
    pub(crate) async fn take_commands(
        &self,
    ) -> Result<
        Vec<(
            String,
            Result<crate::daemon::command::PrintCommand, crate::daemon::command::UnknownCommand>,
        )>,
        PgError,
    > {
        let client = self.client().await?;
        let mut rows = client
            .query(
                "DELETE FROM commands WHERE host = $1 \
                 AND EXISTS (SELECT 1 FROM hosts WHERE name = $1 AND token = $2) \
                 RETURNING id, printer, command, part",
                &[&self.host, &self.token],
            )
            .await?;
        rows.sort_by_key(|r| r.get::<_, i64>(0));
        Ok(rows
            .iter()
            .map(|r| {
                let word: String = r.get(2);
                let part: Option<String> = r.get(3);
                (
                    r.get(1),
                    crate::daemon::command::PrintCommand::parse(&word, part.as_deref()),
                )
            })
            .collect())
    }
}
