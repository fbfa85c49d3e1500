//! The commands an operator sends to a print in progress (pause, resume, cancel, cancel a
//! part of its plate), in one
//! leaf module: the printer supervisors carry them out, the control operations send them,
//! and the farm database carries them between hosts as words. Nothing here depends on
//! the rest of the daemon, so the store and the farm both use it without a cycle.

/// What a control command asks of a print in progress. Between hosts of a shared farm it
/// travels as a word in the database's `commands` table ([`PrintCommand::word`],
/// [`PrintCommand::parse`]: the one place a word becomes a command).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum PrintCommand {
    Pause,
    Resume,
    Cancel,
    /// Stop printing the part of the plate of this name; the others print on.
    CancelPart(String),
}

impl PrintCommand {
    /// The word that stands for it in the farm database (a part's name goes beside it:
    /// [`PrintCommand::part`]).
    pub(crate) fn word(&self) -> &'static str {
        match self {
            PrintCommand::Pause => "pause",
            PrintCommand::Resume => "resume",
            PrintCommand::Cancel => "cancel",
            PrintCommand::CancelPart(_) => "cancel-part",
        }
    }

    /// The part it names, if any.
    pub(crate) fn part(&self) -> Option<&str> {
        match self {
            PrintCommand::CancelPart(part) => Some(part),
            _ => None,
        }
    }

    /// The command a word (and the part beside it) read from the farm database stands
    /// for. Anything else (a newer host's command, a hand-written row, a part's cancel
    /// without a part) is an error: it must never be taken for a cancel, which would stop
    /// a print.
    pub(crate) fn parse(word: &str, part: Option<&str>) -> Result<PrintCommand, UnknownCommand> {
        match (word, part) {
            ("pause", _) => Ok(PrintCommand::Pause),
            ("resume", _) => Ok(PrintCommand::Resume),
            ("cancel", _) => Ok(PrintCommand::Cancel),
            ("cancel-part", Some(part)) => Ok(PrintCommand::CancelPart(part.to_string())),
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
            PrintCommand::CancelPart("box.stl id:0 copy 3".into()),
        ] {
            assert_eq!(PrintCommand::parse(c.word(), c.part()), Ok(c.clone()));
        }
        for word in ["stop", "", "Cancel", "cancel ", "abort", "cancel-part"] {
            assert!(PrintCommand::parse(word, None).is_err(), "{word:?}");
        }
        let long = format!("x\n\u{1b}[2J{}", "y".repeat(500));
        let e = PrintCommand::parse(&long, None).unwrap_err();
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
