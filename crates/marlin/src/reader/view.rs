//! What one firmware's parser finds in a line: each firmware's reader (`marlin2`,
//! `ultimaker2`) returns one, and `read_for` checks it against the plain reading. Kept
//! apart from the readers' root so they and the root share it without depending on
//! each other.

/// What one firmware's parser finds in a line: the command and, per letter A-Z, whether
/// it is there and the number it reads for it.
#[derive(Clone, Debug, PartialEq)]
pub struct View {
    /// Letter and number, or `None` when the firmware answers `Unknown command`.
    pub command: Option<(char, u32)>,
    /// Per letter A-Z: `None` not seen, `Some(None)` seen without a number the firmware
    /// takes, `Some(Some(v))` seen with `v`.
    pub params: [Option<Option<f64>>; 26],
    /// Whether the firmware takes the rest of the line as one string (Marlin 2's string
    /// commands): then the parameters are not read.
    pub string: bool,
}

impl View {
    pub(crate) fn new() -> View {
        View {
            command: None,
            params: [None; 26],
            string: false,
        }
    }

    #[cfg(any(test, fuzzing))]
    pub(crate) fn param(&self, letter: char) -> Option<Option<f64>> {
        letter
            .is_ascii_uppercase()
            .then(|| self.params[(letter as u8 - b'A') as usize])
            .flatten()
    }
}

impl Default for View {
    fn default() -> Self {
        View::new()
    }
}
