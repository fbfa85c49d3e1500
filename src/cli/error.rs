//! An error as a command prints it.

/// The error and its causes on one line. The library's errors already name their cause
/// in their own message, so a cause is added only when its text is not there yet.
pub(crate) fn describe(err: &anyhow::Error) -> String {
    let mut message = err.to_string();
    for cause in err.chain().skip(1) {
        let cause = cause.to_string();
        if !message.contains(&cause) {
            message = format!("{message}: {cause}");
        }
    }
    message
}
