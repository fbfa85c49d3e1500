//! The picture a check leaves for a person: the frame with the bed's region outlined and
//! each differing patch boxed, drawn by imageproc.

use super::{BedCheckError, Verdict};
use image::{Rgb, RgbImage};
use imageproc::drawing::draw_hollow_rect_mut;
use imageproc::rect::Rect;

/// JPEG quality of a marked picture.
const QUALITY: u8 = 85;
/// A patch's box: red, this many pixels thick, this far outside the patch.
const RED: Rgb<u8> = Rgb([230, 30, 30]);
const THICK: i32 = 3;
const PAD: i32 = 4;
/// The region's outline.
const REGION: Rgb<u8> = Rgb([250, 250, 250]);

/// `frame` (a JPEG) with `verdict`'s region and patches marked, as a JPEG.
pub fn marked_jpeg(frame: &[u8], verdict: &Verdict) -> Result<Vec<u8>, BedCheckError> {
    let mut picture = super::decode(frame, "frame")?;
    mark(&mut picture, verdict);
    let mut out = Vec::new();
    let encoder = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, QUALITY);
    picture
        .write_with_encoder(encoder)
        .map_err(|e| BedCheckError::Decode {
            what: "marked picture",
            message: e.to_string(),
        })?;
    Ok(out)
}

fn mark(picture: &mut RgbImage, verdict: &Verdict) {
    let r = verdict.region;
    draw_hollow_rect_mut(
        picture,
        Rect::at(r.x as i32, r.y as i32).of_size(r.w.max(1), r.h.max(1)),
        REGION,
    );
    for p in &verdict.patches {
        for k in 0..THICK {
            let grow = PAD + k;
            let x = p.x as i32 - grow;
            let y = p.y as i32 - grow;
            let w = p.w + 2 * grow as u32;
            let h = p.h + 2 * grow as u32;
            draw_hollow_rect_mut(picture, Rect::at(x, y).of_size(w, h), RED);
        }
    }
}
