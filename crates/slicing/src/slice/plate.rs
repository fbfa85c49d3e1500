//! A plate: several parts sliced together onto one bed, each labelled in the G-code so
//! that one can be cancelled while the others print on ([`crispen_marlin::plate`]).
//!
//! PrusaSlicer lays out a plate itself: its command line duplicates a model
//! (`--duplicate N`) and arranges every object it is given on the bed, and
//! `gcode_label_objects` labels each one (`; printing object NAME`). CuraEngine's command
//! line has neither: arranging is its front end's (Cura's Python `Arrange`), so crispen
//! places each part's copy itself ([`arrange`]: rows of footprints, the whole centred on
//! the bed) and hands CuraEngine one mesh file per part, which it labels by the file's
//! name (`;MESH:NAME`).

use crispen_geometry::mesh::Mesh;

/// The most parts one plate may hold (copies included).
pub const MAX_PER_PLATE: u32 = 50;

/// Room between two parts' footprints, mm (PrusaSlicer's arrange keeps about as much).
pub(crate) const GAP_MM: f64 = 6.0;

/// One model of a plate.
#[derive(Clone, Copy, Debug)]
pub struct PlatePart<'a> {
    /// The name its label carries (its file's stem).
    pub name: &'a str,
    /// Placed: lowest point at Z = 0, footprint centred on X = Y = 0.
    pub mesh: &'a Mesh,
}

/// Why parts do not fit a bed together.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct NoRoom {
    /// How many of them, in order, do.
    pub fit: usize,
}

/// Places footprints (X, Y sizes, mm) in rows with [`GAP_MM`] between them, the whole
/// centred on the origin, within `area` (X, Y): the centre of each. Of the row lengths
/// that fit, the one whose plate is the most square (the smallest larger side) is taken,
/// the longer rows of two alike.
pub(crate) fn arrange(footprints: &[[f64; 2]], area: [f64; 2]) -> Result<Vec<[f64; 2]>, NoRoom> {
    let n = footprints.len();
    let mut best: Option<(f64, Vec<[f64; 2]>)> = None;
    for per_row in 1..=n.max(1) {
        let (size, centres) = rows(footprints, per_row);
        if size[0] > area[0] + 1e-9 || size[1] > area[1] + 1e-9 {
            continue;
        }
        let side = size[0].max(size[1]);
        if best.as_ref().is_none_or(|(b, _)| side <= *b) {
            best = Some((side, centres));
        }
    }
    if let Some((_, centres)) = best {
        return Ok(centres);
    }
    let fit = (0..n)
        .rev()
        .find(|&k| arrange(&footprints[..k], area).is_ok())
        .unwrap_or(0);
    Err(NoRoom { fit })
}

/// Footprints laid `per_row` to a row, rows front to back: the plate's size and each
/// centre, the plate centred on the origin.
fn rows(footprints: &[[f64; 2]], per_row: usize) -> ([f64; 2], Vec<[f64; 2]>) {
    let mut centres = Vec::with_capacity(footprints.len());
    let (mut width, mut y) = (0.0f64, 0.0f64);
    for row in footprints.chunks(per_row.max(1)) {
        let depth = row.iter().map(|f| f[1]).fold(0.0, f64::max);
        let mut x = 0.0;
        for f in row {
            centres.push([x + f[0] / 2.0, y + depth / 2.0]);
            x += f[0] + GAP_MM;
        }
        width = width.max(x - GAP_MM);
        y += depth + GAP_MM;
    }
    let size = [width, (y - GAP_MM).max(0.0)];
    for c in &mut centres {
        c[0] -= size[0] / 2.0;
        c[1] -= size[1] / 2.0;
    }
    (size, centres)
}

/// `mesh` moved by `offset` (X, Y), mm.
pub(crate) fn moved(mesh: &Mesh, offset: [f64; 2]) -> Mesh {
    let mut out = mesh.clone();
    for v in &mut out.vertices {
        v[0] += offset[0];
        v[1] += offset[1];
    }
    out
}

/// A part's footprint (X, Y), mm.
pub(crate) fn footprint(mesh: &Mesh) -> [f64; 2] {
    mesh.bounds()
        .map_or([0.0; 2], |(lo, hi)| [hi[0] - lo[0], hi[1] - lo[1]])
}

/// A name a part's file may carry: letters, digits, `-`, `_` and `.` of `name`, never
/// empty.
pub(crate) fn file_stem(name: &str) -> String {
    let stem: String = name
        .chars()
        .map(|c| {
            if c.is_alphanumeric() || matches!(c, '-' | '_' | '.') {
                c
            } else {
                '_'
            }
        })
        .take(60)
        .collect();
    if stem.is_empty() {
        "part".into()
    } else {
        stem
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn six_copies_go_in_the_squarest_rows_that_fit() {
        let six = vec![[20.0, 20.0]; 6];
        let centres = arrange(&six, [200.0, 200.0]).unwrap();
        // 3 to a row, 2 rows: 72 x 46 mm, centred.
        assert_eq!(centres.len(), 6);
        assert_eq!(centres[0], [-26.0, -13.0]);
        assert_eq!(centres[5], [26.0, 13.0]);
        // No two overlap, gaps kept.
        for (i, a) in centres.iter().enumerate() {
            for b in &centres[i + 1..] {
                let apart = (a[0] - b[0]).abs().max((a[1] - b[1]).abs());
                assert!(apart >= 20.0 + GAP_MM - 1e-9, "{a:?} {b:?}");
            }
        }
        // On a narrow bed, one row of them stands.
        let narrow = arrange(&six, [30.0, 200.0]).unwrap();
        assert!(narrow.iter().all(|c| c[0] == 0.0));
        // Too many: how many fit is said.
        assert_eq!(arrange(&six, [50.0, 50.0]), Err(NoRoom { fit: 4 }));
        assert_eq!(arrange(&six, [10.0, 10.0]), Err(NoRoom { fit: 0 }));
    }

    #[test]
    fn file_stems_are_plain() {
        assert_eq!(file_stem("bunny 1/2.stl"), "bunny_1_2.stl");
        assert_eq!(file_stem(""), "part");
    }
}
