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
}
