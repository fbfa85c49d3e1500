//! Any bytes as a camera's MJPEG stream, cut into pieces anywhere: the reader never panics,
//! never returns a frame over its limit nor one that is not a JPEG, keeps no more than a
//! frame's worth of bytes, and gives the same frames whatever the cuts, or an error
//! whatever the cuts (an error ends a stream).
//!
//! Input layout: the first byte seeds the cuts and picks the frame limit (64 bytes times
//! one more than its value mod 64); the rest is the stream, whose boundary is `frame`.
#![no_main]

use crispen::camera::mjpeg::{is_jpeg, MjpegReader, Part};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&control, stream)) = data.split_first() else {
        return;
    };
    let max = 64 * (1 + usize::from(control % 64));
    let whole = read(stream, max, &mut std::iter::repeat(stream.len().max(1)));
    let mut state = u32::from(control).wrapping_mul(0x9E37_79B9) | 1;
    let mut cuts = std::iter::from_fn(move || {
        state ^= state << 13;
        state ^= state >> 17;
        state ^= state << 5;
        Some(1 + (state % 40) as usize)
    });
    let pieces = read(stream, max, &mut cuts);
    if whole.1 || pieces.1 {
        assert!(whole.1 && pieces.1, "an error whatever the cuts: {whole:?} {pieces:?}");
    } else {
        assert_eq!(whole.0, pieces.0, "the same frames whatever the cuts");
    }
});

/// The frames read from `stream` in pieces of the lengths `cuts` gives, up to the first
/// error, and whether there was one.
fn read(stream: &[u8], max: usize, cuts: &mut dyn Iterator<Item = usize>) -> (Vec<Vec<u8>>, bool) {
    let mut reader = MjpegReader::new("frame", max);
    let mut frames = Vec::new();
    let mut rest = stream;
    while !rest.is_empty() {
        let n = cuts.next().unwrap_or(1).min(rest.len());
        let (piece, tail) = rest.split_at(n);
        rest = tail;
        match reader.feed(piece) {
            Ok(got) => {
                // A part refused (not a JPEG, cut short, over the limit) is skipped, and
                // the stream goes on: only whole frames are compared.
                for part in got {
                    let Part::Frame(f) = part else { continue };
                    assert!(f.len() <= max, "{} bytes over the limit {max}", f.len());
                    assert!(is_jpeg(&f), "not a JPEG: {f:?}");
                    frames.push(f);
                }
            }
            Err(_) => return (frames, true),
        }
        assert!(reader.buffered() <= max + 8192 + 64, "{} bytes kept", reader.buffered());
    }
    (frames, false)
}
