//! Percent-encoding of names in addresses: a printer, job or folder name as one path
//! segment (or query value), and back. Plain ASCII out, so a link also fits in a header.

/// `%XX` decoded (a folder's name in an address); invalid sequences stay as they are.
pub fn percent_decode(text: &str) -> String {
    let bytes = text.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        let hex = |b: u8| (b as char).to_digit(16);
        match (bytes[i], bytes.get(i + 1), bytes.get(i + 2)) {
            (b'%', Some(&h), Some(&l)) if hex(h).is_some() && hex(l).is_some() => {
                out.push((hex(h).unwrap() * 16 + hex(l).unwrap()) as u8);
                i += 3;
            }
            (b, _, _) => {
                out.push(b);
                i += 1;
            }
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// A name as one segment of an address: everything but unreserved characters escaped.
pub fn percent_encode(text: &str) -> String {
    text.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'.' | b'_' | b'~' => {
                (b as char).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
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
    }
}
