//! Spec step 0: weld vertices with identical coordinates, drop faces with a repeated
//! vertex or zero area, drop unreferenced vertices. Survivors keep their relative order
//! (the first of a welded group stands for it), so OBJ output can keep the input's order.

use super::{CleanReport, Mesh};
use std::collections::HashMap;

/// Cleans an indexed mesh. Face indices must be valid for `vertices`.
pub fn clean(vertices: Vec<[f64; 3]>, faces: Vec<[u32; 3]>) -> (Mesh, CleanReport) {
    clean_marked(vertices, faces, &mut [])
}

/// [`clean`], also moving each of `ends` (ascending face counts: where a run of faces
/// ends, a 3MF object's) to where that run ends among the faces kept.
pub(super) fn clean_marked(
    vertices: Vec<[f64; 3]>,
    faces: Vec<[u32; 3]>,
    ends: &mut [usize],
) -> (Mesh, CleanReport) {
    let mut report = CleanReport::default();

    // Weld: map every vertex to the first vertex with the same coordinates. -0.0 and 0.0
    // are the same coordinate, so the key normalises them.
    let key = |v: &[f64; 3]| v.map(|c| if c == 0.0 { 0u64 } else { c.to_bits() });
    let mut first_with: HashMap<[u64; 3], u32> = HashMap::with_capacity(vertices.len());
    let mut weld_to: Vec<u32> = Vec::with_capacity(vertices.len());
    for (i, v) in vertices.iter().enumerate() {
        let target = *first_with.entry(key(v)).or_insert(i as u32);
        if target != i as u32 {
            report.welded_vertices += 1;
        }
        weld_to.push(target);
    }
    drop(first_with);

    let mut kept_faces: Vec<[u32; 3]> = Vec::with_capacity(faces.len());
    let mut next_end = 0;
    for (at, f) in faces.iter().enumerate() {
        while ends.get(next_end) == Some(&at) {
            ends[next_end] = kept_faces.len();
            next_end += 1;
        }
        let g = f.map(|i| weld_to[i as usize]);
        if g[0] == g[1] || g[1] == g[2] || g[0] == g[2] || zero_area(&vertices, g) {
            report.dropped_degenerate_faces += 1;
            continue;
        }
        kept_faces.push(g);
    }
    for end in &mut ends[next_end..] {
        *end = kept_faces.len();
    }
    drop(faces);

    // Compact: keep referenced vertices in their original order.
    let mut referenced = vec![false; vertices.len()];
    for f in &kept_faces {
        for &i in f {
            referenced[i as usize] = true;
        }
    }
    let distinct = weld_to
        .iter()
        .enumerate()
        .filter(|&(i, &t)| t as usize == i)
        .count();
    let mut new_index = vec![u32::MAX; vertices.len()];
    let mut kept_vertices = Vec::with_capacity(distinct);
    for (i, v) in vertices.iter().enumerate() {
        if referenced[i] {
            new_index[i] = kept_vertices.len() as u32;
            kept_vertices.push(*v);
        }
    }
    report.dropped_unreferenced_vertices = distinct - kept_vertices.len();
    for f in &mut kept_faces {
        *f = f.map(|i| new_index[i as usize]);
    }
    (
        Mesh {
            vertices: kept_vertices,
            faces: kept_faces,
        },
        report,
    )
}

fn zero_area(vertices: &[[f64; 3]], f: [u32; 3]) -> bool {
    super::triangle_normal(vertices, f) == [0.0, 0.0, 0.0]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn welds_drops_and_keeps_order() {
        // Vertex 3 duplicates vertex 0; vertex 4 is unused; face 2 is collinear;
        // face 3 repeats an index once welded.
        let vertices = vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [-0.0, 0.0, 0.0],
            [5.0, 5.0, 5.0],
            [2.0, 0.0, 0.0],
            [0.0, 0.0, 1.0],
        ];
        let faces = vec![[0, 1, 2], [3, 2, 6], [0, 1, 5], [0, 3, 1]];
        let (mesh, report) = clean(vertices, faces);
        assert_eq!(
            report,
            CleanReport {
                welded_vertices: 1,
                dropped_degenerate_faces: 2,
                dropped_unreferenced_vertices: 2,
            }
        );
        assert_eq!(
            mesh.vertices,
            vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [0.0, 0.0, 1.0]
            ]
        );
        assert_eq!(mesh.faces, vec![[0, 1, 2], [0, 2, 3]]);
    }
}
