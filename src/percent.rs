//! Percent-encoding of names in addresses: a printer, job or folder name as one path
//! segment (or query value), and back. Plain ASCII out, so a link also fits in a header.

use percent_encoding::{AsciiSet, NON_ALPHANUMERIC};

/// What stays as it is in a segment: RFC 3986's unreserved characters.
const SEGMENT: &AsciiSet = &NON_ALPHANUMERIC
    .remove(b'-')
    .remove(b'.')
    .remove(b'_')
    .remove(b'~');

/// `%XX` decoded (a folder's name in an address); invalid sequences stay as they are.
pub(crate) fn percent_decode(text: &str) -> String {
    percent_encoding::percent_decode_str(text)
        .decode_utf8_lossy()
        .into_owned()
}

/// A name as one segment of an address: everything but unreserved characters escaped.
pub fn percent_encode(text: &str) -> String {
    percent_encoding::utf8_percent_encode(text, SEGMENT).to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_through_one_escaped_segment() {
        assert_eq!(percent_encode("a b/é.gcode"), "a%20b%2F%C3%A9.gcode");
        assert_eq!(percent_encode("0007-a b é"), "0007-a%20b%20%C3%A9");
        assert_eq!(percent_decode(&percent_encode("x y%z")), "x y%z");
        assert_eq!(percent_decode("100%"), "100%");
        assert_eq!(percent_decode("a%2Fb%zz%4"), "a/b%zz%4");
    }
}
