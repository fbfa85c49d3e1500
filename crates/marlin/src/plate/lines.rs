//! A job's lines as the protocol core takes them: each line is asked for once, in order,
//! when it is about to be sent, so a plate's [`PartFilter`] decides it then (and a part
//! cancelled meanwhile is dropped from the next line on). Without a filter, the job's
//! commands go as they are.

use super::filter::PartFilter;
use crate::gcode::GcodeCommands;

/// The lines of one part of a job (between the pauses its file asks for), for the host.
#[derive(Debug, Clone, Default)]
pub struct JobLines {
    /// This part's commands (its index 0 is the job's command `offset`).
    commands: GcodeCommands,
    plate: Option<Plate>,
}

#[derive(Debug, Clone)]
struct Plate {
    filter: PartFilter,
    /// The whole job's commands, which the filter's indices count.
    all: GcodeCommands,
    offset: usize,
    /// The next line decided but not taken yet: its index here and its text.
    decided: Option<(usize, String)>,
    /// The next index of this part not decided yet.
    cursor: usize,
}

impl JobLines {
    /// Commands `offset..offset + part.len()` of `all` (the whole job's), filtered; the
    /// commands before `offset` the filter has not seen (a pause the host made itself) are
    /// followed first.
    pub fn filtered(
        part: GcodeCommands,
        all: GcodeCommands,
        offset: usize,
        mut filter: PartFilter,
    ) -> JobLines {
        while filter.next() < offset && filter.decide(&all).is_some() {}
        JobLines {
            commands: part,
            plate: Some(Plate {
                filter,
                all,
                offset,
                decided: None,
                cursor: 0,
            }),
        }
    }

    /// How many commands the job has (lines not sent count too).
    pub fn len(&self) -> usize {
        self.commands.len()
    }

    pub fn is_empty(&self) -> bool {
        self.commands.is_empty()
    }

    /// The next line to send at or after index `from`: its index and its length. None when
    /// there is none left.
    pub(crate) fn peek(&mut self, from: usize) -> Option<(usize, usize)> {
        let Some(plate) = &mut self.plate else {
            return self.commands.get(from).map(|c| (from, c.len()));
        };
        loop {
            if let Some((i, line)) = &plate.decided {
                if *i >= from {
                    return Some((*i, line.len()));
                }
                plate.decided = None;
            }
            if plate.cursor >= self.commands.len() {
                return None;
            }
            let i = plate.cursor;
            plate.cursor += 1;
            let line = plate.filter.decide(&plate.all)?.line();
            if let Some(line) = line {
                plate.decided = Some((i, line.into_owned()));
            }
            debug_assert_eq!(plate.filter.next(), plate.offset + plate.cursor);
        }
    }

    /// Takes the line [`JobLines::peek`] found at or after `from`.
    pub(crate) fn take(&mut self, from: usize) -> Option<(usize, String)> {
        let (i, _) = self.peek(from)?;
        match &mut self.plate {
            None => Some((i, self.commands[i].to_owned())),
            Some(plate) => plate.decided.take(),
        }
    }

    pub(crate) fn filter_mut(&mut self) -> Option<&mut PartFilter> {
        self.plate.as_mut().map(|p| &mut p.filter)
    }

    /// The filter, once this part of the job is over (for the next part).
    pub(crate) fn take_filter(&mut self) -> Option<PartFilter> {
        self.plate.take().map(|p| p.filter)
    }
}

impl From<GcodeCommands> for JobLines {
    fn from(commands: GcodeCommands) -> JobLines {
        JobLines {
            commands,
            plate: None,
        }
    }
}

impl From<Vec<String>> for JobLines {
    fn from(commands: Vec<String>) -> JobLines {
        GcodeCommands::from(commands).into()
    }
}
