//! One picture at the working size, the form every step of the check reads.

use image::{GenericImageView, RgbImage, SubImage};

/// One picture at the working size: its three channels and luminance, row by row.
#[derive(Debug, Clone)]
pub(super) struct Planes {
    pub(super) w: usize,
    pub(super) h: usize,
    pub(super) rgb: [Vec<f32>; 3],
    pub(super) luma: Vec<f32>,
}

impl Planes {
    /// The picture's region `view`, brought to `w` × `h` by area averages.
    pub(super) fn of(view: &SubImage<&RgbImage>, w: u32, h: u32) -> Planes {
        let small = if (w, h) == view.dimensions() {
            view.to_image()
        } else {
            image::imageops::thumbnail(&**view, w, h)
        };
        let n = (w * h) as usize;
        let mut rgb = [vec![0f32; n], vec![0f32; n], vec![0f32; n]];
        let mut luma = vec![0f32; n];
        for (i, px) in small.pixels().enumerate() {
            let [r, g, b] = px.0.map(f32::from);
            rgb[0][i] = r;
            rgb[1][i] = g;
            rgb[2][i] = b;
            luma[i] = 0.299 * r + 0.587 * g + 0.114 * b;
        }
        Planes {
            w: w as usize,
            h: h as usize,
            rgb,
            luma,
        }
    }
}
