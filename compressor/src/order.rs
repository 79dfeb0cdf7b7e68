//! Significance ordering with the paper's spatial clustering (§4.3, Fig. 11).
//!
//! Input is one packet's coefficients sorted by decreasing score S = E·I. Without clustering
//! that is the coding order. With clustering, after each coefficient the next one is the
//! best-scoring not-yet-emitted coefficient within `radius` voxels (Chebyshev distance between
//! the coefficients' positions in voxel units, pos·2^level) whose score is at least
//! `threshold` × the best remaining score; if there is none, the best remaining coefficient is
//! taken wherever it is. Short hops make the position deltas small and cheap to code; the
//! threshold bounds how far the order may stray from pure significance (1 = no clustering).

use std::collections::HashMap;

/// Spatial clustering parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Clustering {
    /// Neighbourhood radius in voxels (Chebyshev).
    pub radius: u32,
    /// A neighbour qualifies if its score ≥ threshold × best remaining score (0..=1).
    pub threshold: f64,
}

/// An item to order: its score and its position in voxel units.
#[derive(Debug, Clone, Copy)]
pub struct Item {
    /// Significance score.
    pub score: f64,
    /// Position in voxels (band position << level).
    pub voxel: [u32; 3],
}

/// Returns the coding order (indices into `items`, which must be sorted by decreasing score).
pub fn cluster_order(items: &[Item], clustering: Option<Clustering>) -> Vec<usize> {
    let n = items.len();
    let Some(c) = clustering.filter(|c| c.radius > 0 && c.threshold < 1.0) else {
        return (0..n).collect();
    };
    let cell = c.radius.max(1);
    let key = |v: [u32; 3]| [v[0] / cell, v[1] / cell, v[2] / cell];
    // Cell → item indices in decreasing score order (items are sorted, so push order works).
    let mut grid: HashMap<[u32; 3], Vec<usize>> = HashMap::new();
    for (i, it) in items.iter().enumerate() {
        grid.entry(key(it.voxel)).or_default().push(i);
    }
    // Per cell, entries before the cursor are all done: the scan below never revisits them, so
    // the ordering stays O(n · neighbourhood) even in dense cells.
    let mut cursor: HashMap<[u32; 3], usize> = HashMap::new();
    let mut done = vec![false; n];
    let mut next_best = 0usize;
    let mut order = Vec::with_capacity(n);
    let mut current = 0usize;
    while order.len() < n {
        done[current] = true;
        order.push(current);
        if order.len() == n {
            break;
        }
        while done[next_best] {
            next_best += 1;
        }
        let bar = c.threshold * items[next_best].score;
        let here = items[current].voxel;
        let k = key(here);
        let mut best: Option<usize> = None;
        for dz in -1i64..=1 {
            for dy in -1i64..=1 {
                for dx in -1i64..=1 {
                    let nk = [k[0] as i64 + dx, k[1] as i64 + dy, k[2] as i64 + dz];
                    if nk.iter().any(|v| *v < 0) {
                        continue;
                    }
                    let nk = [nk[0] as u32, nk[1] as u32, nk[2] as u32];
                    let Some(list) = grid.get(&nk) else { continue };
                    let start = cursor.entry(nk).or_insert(0);
                    while *start < list.len() && done[list[*start]] {
                        *start += 1;
                    }
                    // The first not-done entry within the radius is that cell's best.
                    for &i in &list[*start..] {
                        if done[i] {
                            continue;
                        }
                        if items[i].score < bar {
                            break;
                        }
                        let v = items[i].voxel;
                        let near = (0..3).all(|a| v[a].abs_diff(here[a]) <= c.radius);
                        if near {
                            if best.is_none_or(|b| i < b) {
                                best = Some(i);
                            }
                            break;
                        }
                    }
                }
            }
        }
        current = best.unwrap_or(next_best);
    }
    order
}

#[cfg(test)]
mod tests {
    use super::*;

    fn items(v: &[(f64, [u32; 3])]) -> Vec<Item> {
        v.iter()
            .map(|(s, p)| Item {
                score: *s,
                voxel: *p,
            })
            .collect()
    }

    #[test]
    fn without_clustering_order_is_significance() {
        let it = items(&[(5.0, [0, 0, 0]), (4.0, [9, 9, 9]), (3.0, [1, 0, 0])]);
        assert_eq!(cluster_order(&it, None), vec![0, 1, 2]);
    }

    #[test]
    fn clustering_prefers_qualifying_neighbours() {
        let it = items(&[
            (5.0, [0, 0, 0]),
            (4.0, [9, 9, 9]),
            (3.0, [1, 0, 0]),
            (0.1, [2, 0, 0]),
        ]);
        let c = Clustering {
            radius: 2,
            threshold: 0.5,
        };
        // After 0, neighbour 2 (score 3 ≥ 0.5·4) is taken; 3 is too weak; then 1, then 3.
        assert_eq!(cluster_order(&it, Some(c)), vec![0, 2, 1, 3]);
        let weak = Clustering {
            radius: 2,
            threshold: 0.9,
        };
        assert_eq!(cluster_order(&it, Some(weak)), vec![0, 1, 2, 3]);
    }

    #[test]
    fn every_item_appears_once() {
        let it: Vec<Item> = (0..500u32)
            .map(|i| Item {
                score: 1000.0 - i as f64,
                voxel: [(i * 7) % 13, (i * 3) % 11, i % 5],
            })
            .collect();
        let mut o = cluster_order(
            &it,
            Some(Clustering {
                radius: 3,
                threshold: 0.1,
            }),
        );
        o.sort();
        assert_eq!(o, (0..500).collect::<Vec<_>>());
    }
}
