//! A picture of what the enhancement changed in the G-code: a few layers' outer walls,
//! plain (wide, grey) and enhanced (thin, red) drawn over each other, one square panel per
//! layer, each fitted to its layer. Where the red line leaves the grey one, the nozzle
//! draws something different.

use super::Image;
use crate::slice::walls::{OuterWalls, Segment, WallComparison};

/// The name of the picture in a job's directory.
pub const WALLS_PNG: &str = "walls.png";

const PLAIN: [u8; 4] = [170, 170, 170, 255];
const ENHANCED: [u8; 4] = [200, 30, 60, 255];
const BACKGROUND: [u8; 4] = [255, 255, 255, 255];
const GAP_PX: u32 = 8;

/// The layers worth showing: the compared layers split into `count` runs from bottom to
/// top, and in each the layer where the wall moved most on average. Z in µm, as
/// [`OuterWalls::layers`] keys them.
pub fn layers_to_show(comparison: &WallComparison, count: usize) -> Vec<i64> {
    let layers = &comparison.per_layer;
    if layers.is_empty() || count == 0 {
        return Vec::new();
    }
    let count = count.min(layers.len());
    (0..count)
        .filter_map(|k| {
            let run = &layers[k * layers.len() / count..(k + 1) * layers.len() / count];
            run.iter()
                .max_by(|a, b| a.mean_mm.total_cmp(&b.mean_mm))
                .map(|l| (l.z_mm * 1000.0).round() as i64)
        })
        .collect()
}

/// Draws `layers` (Z in µm) side by side, each panel `panel` pixels square. `None` when
/// none of the layers has a wall in both files.
pub fn walls_picture(
    plain: &OuterWalls,
    enhanced: &OuterWalls,
    layers: &[i64],
    panel: u32,
) -> Option<Image> {
    let shown: Vec<(&[Segment], &[Segment])> = layers
        .iter()
        .filter_map(|z| {
            Some((
                plain.layers.get(z)?.as_slice(),
                enhanced.layers.get(z)?.as_slice(),
            ))
        })
        .collect();
    if shown.is_empty() || panel < 16 {
        return None;
    }
    let n = shown.len() as u32;
    let width = n * panel + (n - 1) * GAP_PX;
    let mut image = Image {
        width,
        height: panel,
        rgba: [0u8; 4].repeat((width * panel) as usize),
    };
    for (k, (p, e)) in shown.into_iter().enumerate() {
        let x0 = k as u32 * (panel + GAP_PX);
        fill(&mut image, x0, panel, BACKGROUND);
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        for q in p.iter().chain(e).flatten() {
            for i in 0..2 {
                lo[i] = lo[i].min(q[i]);
                hi[i] = hi[i].max(q[i]);
            }
        }
        let extent = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(1e-3);
        let scale = 0.92 * panel as f64 / extent;
        let center = [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0];
        let to_px = |q: [f64; 2]| {
            [
                x0 as f64 + panel as f64 / 2.0 + (q[0] - center[0]) * scale,
                // Y up on the bed, down in the picture.
                panel as f64 / 2.0 - (q[1] - center[1]) * scale,
            ]
        };
        let clip = (x0, x0 + panel);
        for s in p {
            line(&mut image, to_px(s[0]), to_px(s[1]), 2, PLAIN, clip);
        }
        for s in e {
            line(&mut image, to_px(s[0]), to_px(s[1]), 0, ENHANCED, clip);
        }
    }
    Some(image)
}

fn fill(image: &mut Image, x0: u32, panel: u32, color: [u8; 4]) {
    for y in 0..image.height {
        for x in x0..(x0 + panel).min(image.width) {
            put(image, x, y, color);
        }
    }
}

fn put(image: &mut Image, x: u32, y: u32, color: [u8; 4]) {
    let i = 4 * (y as usize * image.width as usize + x as usize);
    image.rgba[i..i + 4].copy_from_slice(&color);
}

/// A line `radius` pixels either side, stamped every half pixel, kept within columns
/// `clip`.
fn line(
    image: &mut Image,
    a: [f64; 2],
    b: [f64; 2],
    radius: i64,
    color: [u8; 4],
    clip: (u32, u32),
) {
    let length = (b[0] - a[0]).hypot(b[1] - a[1]);
    if !length.is_finite() {
        return;
    }
    let steps = ((length * 2.0).ceil() as usize).clamp(1, 100_000);
    for k in 0..=steps {
        let t = k as f64 / steps as f64;
        let (x, y) = (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]));
        let (x, y) = (x.floor() as i64, y.floor() as i64);
        for dx in -radius..=radius {
            for dy in -radius..=radius {
                let (px, py) = (x + dx, y + dy);
                if px >= clip.0 as i64 && px < clip.1 as i64 && py >= 0 && py < image.height as i64
                {
                    put(image, px as u32, py as u32, color);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::slice::walls::{compare, LayerFigures};

    fn square(half: f64) -> Vec<Segment> {
        let c = [[-half, -half], [half, -half], [half, half], [-half, half]];
        (0..4).map(|i| [c[i], c[(i + 1) % 4]]).collect()
    }

    #[test]
    fn draws_plain_and_enhanced_walls_per_layer() {
        let mut plain = OuterWalls::default();
        let mut enhanced = OuterWalls::default();
        for z in [200, 400, 600] {
            plain.layers.insert(z, square(10.0));
            enhanced
                .layers
                .insert(z, square(if z == 400 { 11.0 } else { 10.0 }));
        }
        let c = compare(&plain, &enhanced, 0.4);
        assert_eq!(layers_to_show(&c, 1), [400]);
        assert_eq!(layers_to_show(&c, 5).len(), 3);
        let image = walls_picture(&plain, &enhanced, &[200, 400], 100).unwrap();
        assert_eq!((image.width, image.height), (208, 100));
        let count = |color: [u8; 4], x0: u32| {
            (0..100)
                .flat_map(|y| (x0..x0 + 100).map(move |x| (x, y)))
                .filter(|&(x, y)| image.pixel(x, y) == color)
                .count()
        };
        // Same walls: the red line lies on the grey one, both show. Moved walls: the grey
        // square sits inside the red one.
        assert!(count(ENHANCED, 0) > 100 && count(PLAIN, 0) > 100);
        assert!(count(ENHANCED, 108) > 300 && count(PLAIN, 108) > 300);
        assert_eq!(image.pixel(104, 50), [0, 0, 0, 0], "the gap is transparent");
        assert!(walls_picture(&plain, &enhanced, &[800], 100).is_none());
        let none = WallComparison {
            per_layer: vec![LayerFigures {
                z_mm: 0.2,
                mean_mm: 0.0,
                share_over_0_1_mm: 0.0,
            }],
            ..WallComparison::default()
        };
        assert_eq!(layers_to_show(&none, 3), [200]);
    }
}
