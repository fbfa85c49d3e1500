//! What each part of a plate is on the bed: its name, its outline (the convex hull of its
//! extruding moves, where the firmware puts them: [`crate::motion`]), the filament
//! it takes and its layers; and the plate's layers, so that a cancel can say at which
//! layer it took effect.

use crate::firmware::Firmware;
use crate::labels::Marks;
use crate::motion::Motion;
use crate::reader;
use serde::{Deserialize, Serialize};

/// Points gathered per part before they are reduced to their hull (bounds the memory a
/// part of millions of moves takes).
const HULL_EVERY: usize = 4096;

/// One part of a plate, as its G-code lays it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PartInfo {
    pub name: String,
    /// Its outline on the bed: the convex hull of its extruding moves, machine X and Y in
    /// mm, counter-clockwise.
    pub outline: Vec<[f64; 2]>,
    /// Filament its extruding moves push, mm.
    pub extruded_mm: f64,
    /// The Z of its lowest and highest layer, mm.
    pub z_mm: [f64; 2],
}

/// A plate's parts and layers.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlateMap {
    pub parts: Vec<PartInfo>,
    /// Where each layer starts: the index of its first extruding command and its Z, bottom
    /// up (a layer starts where an extruding move first reaches a higher Z).
    layers: Vec<(usize, f64)>,
}

/// A layer of a plate: its number from 1 and its Z, mm.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Layer {
    pub number: usize,
    pub z_mm: f64,
}

impl PlateMap {
    /// Follows `commands` (as the host sends them) on `firmware` with the parts of
    /// `marks`.
    pub fn read<'a>(
        commands: impl IntoIterator<Item = &'a str>,
        marks: &Marks,
        firmware: Firmware,
    ) -> PlateMap {
        let mut motion = Motion::new(firmware);
        let mut points: Vec<Vec<[f64; 2]>> = vec![Vec::new(); marks.names().len()];
        let mut parts: Vec<PartInfo> = marks
            .names()
            .iter()
            .map(|name| PartInfo {
                name: name.clone(),
                outline: Vec::new(),
                extruded_mm: 0.0,
                z_mm: [f64::INFINITY, f64::NEG_INFINITY],
            })
            .collect();
        let mut layers: Vec<(usize, f64)> = Vec::new();
        for (index, line) in commands.into_iter().enumerate() {
            let Ok(Some(cmd)) = reader::read(line) else {
                continue;
            };
            let Ok(Some(m)) = motion.apply(&cmd) else {
                continue;
            };
            if !(m.extruded() > 0.0 && m.moves_xy()) {
                continue;
            }
            // The firmware's float, to a tenth of a micrometre: the layer's height as written.
            let z = (m.to[2] * 1e4).round() / 1e4;
            if layers.last().is_none_or(|&(_, top)| z > top + 1e-6) {
                layers.push((index, z));
            }
            let Some(part) = marks.part_at(index) else {
                continue;
            };
            let p = usize::from(part);
            let info = &mut parts[p];
            info.extruded_mm += m.extruded();
            info.z_mm = [info.z_mm[0].min(z), info.z_mm[1].max(z)];
            let pts = &mut points[p];
            if m.curved {
                // The box it sweeps holds the curve.
                pts.extend([[m.lo[0], m.lo[1]], [m.hi[0], m.hi[1]]]);
                pts.extend([[m.lo[0], m.hi[1]], [m.hi[0], m.lo[1]]]);
            } else {
                pts.extend([[m.from[0], m.from[1]], [m.to[0], m.to[1]]]);
            }
            if pts.len() > HULL_EVERY {
                *pts = hull(std::mem::take(pts));
            }
        }
        for (info, pts) in parts.iter_mut().zip(points) {
            info.outline = hull(pts);
            if !info.z_mm[0].is_finite() {
                info.z_mm = [0.0, 0.0];
            }
        }
        PlateMap { parts, layers }
    }

    /// The layer command `index` is in (the last one started at or before it).
    pub fn layer_at(&self, index: usize) -> Option<Layer> {
        let after = self.layers.partition_point(|(at, _)| *at <= index);
        let i = after.checked_sub(1)?;
        Some(Layer {
            number: i + 1,
            z_mm: self.layers[i].1,
        })
    }

    pub fn layer_count(&self) -> usize {
        self.layers.len()
    }

    /// Where each layer starts: the index of its first extruding command.
    pub fn layer_starts(&self) -> impl Iterator<Item = usize> + '_ {
        self.layers.iter().map(|(at, _)| *at)
    }
}

/// The convex hull of `points`, counter-clockwise, without repeated or collinear points
/// (Andrew's monotone chain).
pub(crate) fn hull(mut points: Vec<[f64; 2]>) -> Vec<[f64; 2]> {
    points.retain(|p| p[0].is_finite() && p[1].is_finite());
    points.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    points.dedup();
    if points.len() < 3 {
        return points;
    }
    let cross = |o: [f64; 2], a: [f64; 2], b: [f64; 2]| {
        (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
    };
    let mut lower: Vec<[f64; 2]> = Vec::new();
    for &p in &points {
        while lower.len() >= 2 && cross(lower[lower.len() - 2], lower[lower.len() - 1], p) <= 0.0 {
            lower.pop();
        }
        lower.push(p);
    }
    let mut upper: Vec<[f64; 2]> = Vec::new();
    for &p in points.iter().rev() {
        while upper.len() >= 2 && cross(upper[upper.len() - 2], upper[upper.len() - 1], p) <= 0.0 {
            upper.pop();
        }
        upper.push(p);
    }
    lower.pop();
    upper.pop();
    lower.extend(upper);
    lower
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_hull_is_the_outline_counter_clockwise() {
        let pts = vec![
            [0.0, 0.0],
            [2.0, 0.0],
            [1.0, 1.0],
            [2.0, 2.0],
            [0.0, 2.0],
            [1.0, 0.0],
            [0.0, 0.0],
        ];
        assert_eq!(hull(pts), [[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]]);
        assert_eq!(hull(vec![[1.0, 1.0], [1.0, 1.0]]), [[1.0, 1.0]]);
        assert_eq!(hull(vec![[f64::NAN, 1.0]]), Vec::<[f64; 2]>::new());
    }

    #[test]
    fn parts_get_their_outline_filament_and_layers() {
        let mut reader = crate::labels::LabelReader::default();
        let text = "G28\nG1 Z0.2 F600\n; printing object a\nG1 X10 Y10\nG1 X20 Y10 E1\n\
                    G1 X20 Y20 E2\n; stop printing object a\n; printing object b\nG1 X50 Y50\n\
                    G1 X60 Y50 E3\n; stop printing object b\nG1 Z0.4\n; printing object a\n\
                    G1 X10 Y10\nG1 X10 Y20 E4\n; stop printing object a\n";
        let mut commands = Vec::new();
        for line in text.lines() {
            if reader.line(line, commands.len()) == crate::labels::LineLabel::No {
                commands.push(line.to_string());
            }
        }
        let marks = reader.finish(commands.len()).unwrap();
        let map = PlateMap::read(
            commands.iter().map(String::as_str),
            &marks,
            Firmware::Marlin2,
        );
        let a = &map.parts[0];
        assert_eq!(a.name, "a");
        assert_eq!(a.extruded_mm, 3.0);
        assert_eq!(a.z_mm, [0.2, 0.4]);
        assert_eq!(
            a.outline,
            [[10.0, 10.0], [20.0, 10.0], [20.0, 20.0], [10.0, 20.0]]
        );
        assert_eq!(map.parts[1].extruded_mm, 1.0);
        assert_eq!(map.layer_count(), 2);
        assert_eq!(map.layer_at(1), None);
        assert_eq!(map.layer_at(3).unwrap().number, 1);
        let second = map.layer_at(commands.len() - 1).unwrap();
        assert_eq!((second.number, second.z_mm), (2, 0.4));
    }
}
