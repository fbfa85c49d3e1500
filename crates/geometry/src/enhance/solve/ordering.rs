//! Fill-reducing ordering for the Cholesky factorisation of large meshes: geometric
//! nested dissection. A surface mesh cut by a plane splits along a curve of O(√n)
//! vertices; numbering both halves first (recursively) and the cut last confines the
//! fill to the halves and the cut, which for surface meshes gives much less fill and
//! work than approximate minimum degree, and is computed in O(n log n) without the
//! symbolic elimination AMD simulates. The two halves of a cut are independent, so
//! large ones are dissected in parallel.

use std::sync::atomic::{AtomicU32, Ordering::Relaxed};

/// Returns the elimination order (`order[k]` = the vertex eliminated k-th) for the
/// symmetric pattern given as a lower-triangular CSC (`col_ptr`, `row_idx`, diagonal
/// entries included or not).
pub(crate) fn nested_dissection(
    positions: &[[f64; 3]],
    col_ptr: &[usize],
    row_idx: &[usize],
) -> Vec<usize> {
    let n = positions.len();
    // Symmetric adjacency (CSR, both directions, no diagonal).
    let mut start = vec![0usize; n + 1];
    for j in 0..n {
        for &i in &row_idx[col_ptr[j]..col_ptr[j + 1]] {
            if i != j {
                start[i + 1] += 1;
                start[j + 1] += 1;
            }
        }
    }
    for i in 0..n {
        start[i + 1] += start[i];
    }
    let mut cursor = start.clone();
    let mut adjacent = vec![0u32; start[n]];
    for j in 0..n {
        for &i in &row_idx[col_ptr[j]..col_ptr[j + 1]] {
            if i != j {
                adjacent[cursor[i]] = j as u32;
                cursor[i] += 1;
                adjacent[cursor[j]] = i as u32;
                cursor[j] += 1;
            }
        }
    }
    drop(cursor);

    let dissection = Dissection {
        positions,
        start,
        adjacent,
        part: (0..n).map(|_| AtomicU32::new(0)).collect(),
        next_part: AtomicU32::new(1),
    };
    let mut order = Vec::with_capacity(n);
    dissection.dissect((0..n as u32).collect(), &mut order);
    order
}

/// Subsets this small are numbered as they come: their fill is negligible.
const LEAF_SIZE: usize = 64;
/// Subsets this large have their two halves dissected on separate threads.
const PARALLEL_MIN: usize = 20_000;

struct Dissection<'a> {
    positions: &'a [[f64; 3]],
    start: Vec<usize>,
    adjacent: Vec<u32>,
    /// Which subset each vertex is in, by a fresh id per subset. Concurrent dissections
    /// write only their own vertices and compare only against their own ids, so relaxed
    /// atomics suffice.
    part: Vec<AtomicU32>,
    next_part: AtomicU32,
}

impl Dissection<'_> {
    /// Appends `set`'s elimination order to `order`: its halves, then its separator.
    fn dissect(&self, set: Vec<u32>, order: &mut Vec<usize>) {
        if set.len() <= LEAF_SIZE {
            order.extend(set.iter().map(|&v| v as usize));
            return;
        }
        let (left, right, separator) = self.split(set);
        if left.len() + right.len() >= PARALLEL_MIN {
            let mut right_order = Vec::with_capacity(right.len());
            rayon::join(
                || self.dissect(left, order),
                || self.dissect(right, &mut right_order),
            );
            order.append(&mut right_order);
        } else {
            self.dissect(left, order);
            self.dissect(right, order);
        }
        order.extend(separator.iter().map(|&v| v as usize));
    }

    /// Splits `set` into two halves and a separator between them. Tries a median cut
    /// across each axis and keeps the smallest separator: the longest side of the
    /// bounding box is a poor guide on curved surfaces, and the separators' sizes decide
    /// the factor's fill.
    fn split(&self, set: Vec<u32>) -> (Vec<u32>, Vec<u32>, Vec<u32>) {
        let mut best: Option<(Vec<u32>, Vec<u32>, Vec<u32>)> = None;
        for axis in 0..3 {
            let mut trial = set.clone();
            let mid = trial.len() / 2;
            trial.select_nth_unstable_by(mid, |&a, &b| {
                self.positions[a as usize][axis].total_cmp(&self.positions[b as usize][axis])
            });
            let right = trial.split_off(mid);
            let left = trial;
            let left_id = self.mark(&left);
            let right_id = self.mark(&right);
            // The separator is one side's vertices with a neighbour on the other side:
            // whichever side has fewer.
            let from_left = left.iter().filter(|&&v| self.touches(v, right_id)).count();
            let from_right = right.iter().filter(|&&v| self.touches(v, left_id)).count();
            let (size, cut, keep, other_id) = if from_left <= from_right {
                (from_left, left, right, right_id)
            } else {
                (from_right, right, left, left_id)
            };
            if best.as_ref().is_none_or(|b| size < b.2.len()) {
                let (separator, rest): (Vec<u32>, Vec<u32>) =
                    cut.into_iter().partition(|&v| self.touches(v, other_id));
                best = Some((rest, keep, separator));
            }
        }
        let (left, right, separator) = best.expect("three trial cuts");
        // Later trials re-marked the vertices: mark the chosen halves again so that each
        // half's own dissection sees its neighbours across the cut as outside.
        self.mark(&left);
        self.mark(&right);
        self.mark(&separator);
        (left, right, separator)
    }

    /// Gives `vertices` a fresh subset id and returns it.
    fn mark(&self, vertices: &[u32]) -> u32 {
        let id = self.next_part.fetch_add(1, Relaxed);
        for &v in vertices {
            self.part[v as usize].store(id, Relaxed);
        }
        id
    }

    fn touches(&self, v: u32, part: u32) -> bool {
        let v = v as usize;
        self.adjacent[self.start[v]..self.start[v + 1]]
            .iter()
            .any(|&u| self.part[u as usize].load(Relaxed) == part)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn orders_every_vertex_once_with_separators_last() {
        // A 30×30 grid: the first cut splits it, so the last vertices are a separator
        // column (all with the same x) and everything else comes before.
        let n = 30;
        let positions: Vec<[f64; 3]> = (0..n * n)
            .map(|k| [(k % n) as f64, (k / n) as f64 * 0.5, 0.0])
            .collect();
        let mut col_ptr = vec![0];
        let mut row_idx = Vec::new();
        for k in 0..n * n {
            row_idx.push(k);
            if k % n + 1 < n {
                row_idx.push(k + 1);
            }
            if k + n < n * n {
                row_idx.push(k + n);
            }
            col_ptr.push(row_idx.len());
        }
        let order = nested_dissection(&positions, &col_ptr, &row_idx);
        let mut seen = vec![false; n * n];
        for &v in &order {
            assert!(!seen[v]);
            seen[v] = true;
        }
        assert!(seen.iter().all(|&s| s));
        let last_column: Vec<f64> = order[order.len() - n..]
            .iter()
            .map(|&v| positions[v][0])
            .collect();
        assert!(
            last_column.iter().all(|&x| x == last_column[0]),
            "{last_column:?}"
        );
    }
}
