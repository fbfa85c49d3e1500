//! A printer's picture made from its camera's frame: cropped to the printer (one camera may
//! watch a shelf), flipped and turned as the camera is mounted. A frame taken as it is
//! needs none of this and is passed on byte for byte.

use crate::daemon::config::camera::CameraTransform;
use image::ImageReader;

/// JPEG quality of a made picture: a camera's own frames are usually about this.
const QUALITY: u8 = 85;
/// Frames larger than this many pixels are not decoded (a lying header).
const MAX_PIXELS: u64 = 64 * 1024 * 1024;

/// Why a picture could not be made.
#[derive(Debug, thiserror::Error)]
pub enum PictureError {
    #[error("the frame is not a readable JPEG: {0}")]
    Decode(String),
    #[error("the crop [{x}, {y}, {w}, {h}] lies outside the {width}x{height} frame")]
    CropOutside {
        x: u32,
        y: u32,
        w: u32,
        h: u32,
        width: u32,
        height: u32,
    },
    #[error("cannot encode the picture: {0}")]
    Encode(String),
}

/// Frames wider or higher than this are not decoded.
const MAX_SIDE: usize = 16_384;

/// Whether the JPEG `frame` decodes whole. Strictly: a decoder that forgives (the `image`
/// crate's) fills what is missing or wrong with a flat colour, which is how a cut frame
/// shows its bottom half green; within [`MAX_PIXELS`], as [`make`]. The decoder's words
/// when it does not. (Even strict, it takes an end marker that comes before the last
/// block for the end of the picture: a frame cut and then closed is found by nothing
/// short of counting its blocks.)
pub fn decodes(frame: &[u8]) -> Result<(), String> {
    use zune_core::bytestream::ZCursor;
    use zune_core::options::DecoderOptions;
    let options = DecoderOptions::default()
        .set_strict_mode(true)
        .set_max_width(MAX_SIDE)
        .set_max_height(MAX_SIDE);
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(ZCursor::new(frame), options);
    decoder.decode_headers().map_err(|e| e.to_string())?;
    let (w, h) = decoder.dimensions().ok_or("no frame header")?;
    if w as u64 * h as u64 > MAX_PIXELS {
        return Err(format!("{w}x{h} is more than {MAX_PIXELS} pixels"));
    }
    decoder.decode().map(drop).map_err(|e| e.to_string())
}

/// The picture `transform` makes of the JPEG `frame`.
pub fn make(frame: &[u8], transform: &CameraTransform) -> Result<Vec<u8>, PictureError> {
    if transform.is_identity() {
        return Ok(frame.to_vec());
    }
    let mut reader =
        ImageReader::with_format(std::io::Cursor::new(frame), image::ImageFormat::Jpeg);
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(MAX_PIXELS * 4);
    reader.limits(limits);
    let mut picture = reader
        .decode()
        .map_err(|e| PictureError::Decode(e.to_string()))?;
    if let Some([x, y, w, h]) = transform.crop {
        let (width, height) = (picture.width(), picture.height());
        if x >= width || y >= height {
            return Err(PictureError::CropOutside {
                x,
                y,
                w,
                h,
                width,
                height,
            });
        }
        // A crop reaching past the frame is cut at its edge.
        picture = picture.crop_imm(x, y, w.min(width - x), h.min(height - y));
    }
    if transform.flip_horizontal {
        picture = picture.fliph();
    }
    if transform.flip_vertical {
        picture = picture.flipv();
    }
    picture = match transform.quarter_turns {
        1 => picture.rotate90(),
        2 => picture.rotate180(),
        3 => picture.rotate270(),
        _ => picture,
    };
    let mut out = Vec::new();
    let encoder = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, QUALITY);
    picture
        .to_rgb8()
        .write_with_encoder(encoder)
        .map_err(|e| PictureError::Encode(e.to_string()))?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 40x20 JPEG: left half black, right half white.
    fn frame() -> Vec<u8> {
        let img = image::RgbImage::from_fn(40, 20, |x, _| {
            if x < 20 {
                image::Rgb([0, 0, 0])
            } else {
                image::Rgb([255, 255, 255])
            }
        });
        let mut out = Vec::new();
        img.write_with_encoder(image::codecs::jpeg::JpegEncoder::new_with_quality(
            &mut out, 95,
        ))
        .unwrap();
        out
    }

    fn decode(jpeg: &[u8]) -> image::RgbImage {
        image::load_from_memory_with_format(jpeg, image::ImageFormat::Jpeg)
            .unwrap()
            .to_rgb8()
    }

    #[test]
    fn crop_flip_and_turn_as_the_camera_is_mounted() {
        let f = frame();
        assert_eq!(make(&f, &CameraTransform::default()).unwrap(), f);
        // The right half alone is white.
        let right = CameraTransform {
            crop: Some([20, 0, 20, 20]),
            ..Default::default()
        };
        let p = decode(&make(&f, &right).unwrap());
        assert_eq!(p.dimensions(), (20, 20));
        assert!(p.pixels().all(|px| px.0[0] > 200));
        // Flipped: white on the left.
        let flipped = CameraTransform {
            flip_horizontal: true,
            ..Default::default()
        };
        let p = decode(&make(&f, &flipped).unwrap());
        assert!(p.get_pixel(2, 10).0[0] > 200 && p.get_pixel(37, 10).0[0] < 50);
        // A quarter turn clockwise: 20 wide, 40 high, white at the bottom.
        let turned = CameraTransform {
            quarter_turns: 1,
            ..Default::default()
        };
        let p = decode(&make(&f, &turned).unwrap());
        assert_eq!(p.dimensions(), (20, 40));
        assert!(p.get_pixel(10, 37).0[0] > 200 && p.get_pixel(10, 2).0[0] < 50);
        // A crop past the edge is cut there; one outside the frame is an error.
        let past = CameraTransform {
            crop: Some([30, 10, 100, 100]),
            ..Default::default()
        };
        assert_eq!(decode(&make(&f, &past).unwrap()).dimensions(), (10, 10));
        let outside = CameraTransform {
            crop: Some([40, 0, 10, 10]),
            ..Default::default()
        };
        assert!(matches!(
            make(&f, &outside),
            Err(PictureError::CropOutside { .. })
        ));
        assert!(matches!(
            make(b"\xff\xd8\xffjunk", &right),
            Err(PictureError::Decode(_))
        ));
    }

    /// A frame with detail all over, so that most of its bytes are the picture's.
    fn busy_frame() -> Vec<u8> {
        let img = image::RgbImage::from_fn(256, 192, |x, y| {
            let v = (x * 7 + y * 13 + (x * y) % 17) as u8;
            image::Rgb([v, v.wrapping_mul(3), 255 - v])
        });
        let mut out = Vec::new();
        img.write_with_encoder(image::codecs::jpeg::JpegEncoder::new_with_quality(
            &mut out, 90,
        ))
        .unwrap();
        out
    }

    /// A frame cut short decodes with the forgiving decoder (the rest filled in) and not
    /// with the strict one; nor one without its quantisation tables, nor one whose header
    /// claims too many pixels.
    #[test]
    fn a_cut_or_broken_frame_does_not_decode() {
        use crate::camera::mjpeg::check_jpeg;
        let f = busy_frame();
        assert_eq!(decodes(&f), Ok(()));
        let cut = &f[..f.len() * 2 / 3];
        assert!(image::load_from_memory_with_format(cut, image::ImageFormat::Jpeg).is_ok());
        assert!(decodes(cut).is_err());
        // Its DQT segments taken out: whole by its markers, no picture.
        let mut no_tables = f[..2].to_vec();
        let mut at = 2;
        while f[at + 1] != 0xDA {
            let len = 2 + usize::from(u16::from_be_bytes([f[at + 2], f[at + 3]]));
            if f[at + 1] != 0xDB {
                no_tables.extend_from_slice(&f[at..at + len]);
            }
            at += len;
        }
        no_tables.extend_from_slice(&f[at..]);
        assert!(no_tables.len() < f.len());
        assert_eq!(check_jpeg(&no_tables), Ok(no_tables.len()));
        assert!(decodes(&no_tables).is_err());
        // A frame header claiming 60000 x 60000.
        let mut huge = f.clone();
        let sof = huge.windows(2).position(|w| w == [0xFF, 0xC0]).unwrap();
        huge[sof + 5..sof + 9].copy_from_slice(&[0xEA, 0x60, 0xEA, 0x60]);
        assert!(decodes(&huge).is_err());
    }
}
