//! The commands an operator sends to a print in progress (pause, resume, cancel), in one
//! leaf module: the printer supervisors carry them out, the control operations send them,
//! and the farm database carries them between hosts as words. Nothing here depends on
//! the rest of the daemon, so the store and the farm both use it without a cycle.

/// What a control command asks of a print in progress. Between hosts of a shared farm it
/// travels as a word in the database's `commands` table ([`PrintCommand::word`],
/// [`PrintCommand::parse`]: the one place a word becomes a command).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum PrintCommand {
    Pause,
    Resume,
    Cancel,
}

impl PrintCommand {
    /// The word that stands for it in the farm database.
    pub(crate) fn word(self) -> &'static str {
        match self {
            PrintCommand::Pause => "pause",
            PrintCommand::Resume => "resume",
            PrintCommand::Cancel => "cancel",
        }
    }

    /// The command a word read from the farm database stands for. Anything else (a newer
    /// host's command, a hand-written row) is an error: it must never be taken for a
    /// cancel, which would stop a print.
    pub(crate) fn parse(word: &str) -> Result<PrintCommand, UnknownCommand> {
        match word {
            "pause" => Ok(PrintCommand::Pause),
            "resume" => Ok(PrintCommand::Resume),
            "cancel" => Ok(PrintCommand::Cancel),
            _ => Err(UnknownCommand::new(word)),
        }
    }
}

/// A command word that is not one of [`PrintCommand`]'s; it keeps the text shortened (the
/// database does not bound it), and shows it escaped.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown command {text:?}")]
pub(crate) struct UnknownCommand {
    /// At most [`UnknownCommand::SHOWN`] characters of the word, `…` after a longer one.
    pub text: String,
}

impl UnknownCommand {
    const SHOWN: usize = 40;

    fn new(word: &str) -> UnknownCommand {
        let mut text: String = word.chars().take(Self::SHOWN).collect();
        if word.chars().nth(Self::SHOWN).is_some() {
            text.push('…');
        }
        UnknownCommand { text }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every command reads back as itself; any other word is refused, never a cancel
    /// (it once fell through to cancel and stopped the print).
    #[test]
    fn print_commands_parse_in_one_place() {
        for c in [
            PrintCommand::Pause,
            PrintCommand::Resume,
            PrintCommand::Cancel,
        ] {
            assert_eq!(PrintCommand::parse(c.word()), Ok(c));
        }
        for word in ["stop", "", "Cancel", "cancel ", "abort"] {
            assert!(PrintCommand::parse(word).is_err(), "{word:?}");
        }
        let long = format!("x\n\u{1b}[2J{}", "y".repeat(500));
        let e = PrintCommand::parse(&long).unwrap_err();
        assert_eq!(e.text.chars().count(), UnknownCommand::SHOWN + 1);
        assert!(e.text.ends_with('…'));
        let shown = e.to_string();
        assert!(
            !shown.contains('\n') && !shown.contains('\u{1b}'),
            "{shown}"
        );
        assert!(
            shown.contains("\\n") && shown.contains("\\u{1b}"),
            "{shown}"
        );
    }
}
