//! The Hungarian (Kuhn–Munkres) algorithm: the one-to-one assignment of 2D to 3D segments of
//! maximal total overlap score in `association`.
//!
//! Why a file of its own: it is a general solver (a dense cost matrix in, an assignment out) with
//! its own tests, independent of how the segment map scores pairs.

/// Minimum-cost assignment on a dense `rows x cols` cost matrix (row-major) by the Hungarian
/// (Kuhn–Munkres) algorithm with potentials, O(n² m) for n = min, m = max of the two sizes.
/// Returns the column assigned to each row; with more rows than columns some rows get `None`.
pub fn hungarian(cost: &[f64], rows: usize, cols: usize) -> Vec<Option<usize>> {
    if rows == 0 || cols == 0 || cost.len() != rows * cols {
        return vec![None; rows];
    }
    if rows > cols {
        // Solve the transpose (the algorithm needs rows <= columns) and invert the assignment.
        let transposed: Vec<f64> = (0..cols)
            .flat_map(|c| (0..rows).map(move |r| cost[r * cols + c]))
            .collect();
        let mut out = vec![None; rows];
        for (c, r) in hungarian(&transposed, cols, rows).into_iter().enumerate() {
            if let Some(r) = r {
                out[r] = Some(c);
            }
        }
        return out;
    }
    let (n, m) = (rows, cols);
    let a = |i: usize, j: usize| cost[(i - 1) * m + (j - 1)];
    // 1-based with a virtual column 0, as in the classic formulation.
    let (mut u, mut v) = (vec![0.0f64; n + 1], vec![0.0f64; m + 1]);
    let (mut p, mut way) = (vec![0usize; m + 1], vec![0usize; m + 1]);
    for i in 1..=n {
        p[0] = i;
        let mut j0 = 0;
        let mut minv = vec![f64::INFINITY; m + 1];
        let mut used = vec![false; m + 1];
        loop {
            used[j0] = true;
            let i0 = p[j0];
            let mut delta = f64::INFINITY;
            let mut j1 = 0;
            for j in 1..=m {
                if !used[j] {
                    let cur = a(i0, j) - u[i0] - v[j];
                    if cur < minv[j] {
                        minv[j] = cur;
                        way[j] = j0;
                    }
                    if minv[j] < delta {
                        delta = minv[j];
                        j1 = j;
                    }
                }
            }
            if j1 == 0 {
                // Only reachable with non-finite costs: stop rather than loop.
                break;
            }
            for j in 0..=m {
                if used[j] {
                    u[p[j]] += delta;
                    v[j] -= delta;
                } else {
                    minv[j] -= delta;
                }
            }
            j0 = j1;
            if p[j0] == 0 {
                break;
            }
        }
        while j0 != 0 {
            let j1 = way[j0];
            p[j0] = p[j1];
            j0 = j1;
        }
    }
    let mut out = vec![None; rows];
    for j in 1..=m {
        if p[j] != 0 {
            out[p[j] - 1] = Some(j - 1);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn total(cost: &[f64], cols: usize, assignment: &[Option<usize>]) -> f64 {
        assignment
            .iter()
            .enumerate()
            .filter_map(|(r, c)| c.map(|c| cost[r * cols + c]))
            .sum()
    }

    /// The best assignment of every row (rows <= cols) by trying all injections.
    fn brute_force(cost: &[f64], rows: usize, cols: usize) -> f64 {
        fn go(cost: &[f64], r: usize, rows: usize, cols: usize, used: &mut [bool]) -> f64 {
            if r == rows {
                return 0.0;
            }
            let mut best = f64::INFINITY;
            for c in 0..cols {
                if !used[c] {
                    used[c] = true;
                    best = best.min(cost[r * cols + c] + go(cost, r + 1, rows, cols, used));
                    used[c] = false;
                }
            }
            best
        }
        go(cost, 0, rows, cols, &mut vec![false; cols])
    }

    #[test]
    fn hungarian_solves_hand_computed_matrices() {
        // Square: 1 + 2 + 2 = 5 beats every other permutation.
        let cost = [4.0, 1.0, 3.0, 2.0, 0.0, 5.0, 3.0, 2.0, 2.0];
        assert_eq!(hungarian(&cost, 3, 3), vec![Some(1), Some(0), Some(2)]);
        // Wide: r0 -> c1 (2) + r1 -> c0 (2) = 4 beats 1 + 4 and 3 + 2.
        let cost = [1.0, 2.0, 3.0, 2.0, 4.0, 6.0];
        assert_eq!(hungarian(&cost, 2, 3), vec![Some(1), Some(0)]);
        // Tall: the same two rows plus one that is too expensive to use.
        let cost = [1.0, 2.0, 2.0, 4.0, 9.0, 9.0];
        assert_eq!(hungarian(&cost, 3, 2), vec![Some(1), Some(0), None]);
        assert_eq!(hungarian(&[], 0, 3), Vec::<Option<usize>>::new());
        assert_eq!(hungarian(&[], 2, 0), vec![None, None]);
    }

    #[test]
    fn hungarian_matches_brute_force_on_random_matrices() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        for _ in 0..200 {
            let rows = rng.random_range(1..=5);
            let cols = rng.random_range(1..=5);
            let cost: Vec<f64> = (0..rows * cols)
                .map(|_| f64::from(rng.random_range(-10i32..10)))
                .collect();
            let a = hungarian(&cost, rows, cols);
            let assigned: Vec<usize> = a.iter().flatten().copied().collect();
            assert_eq!(assigned.len(), rows.min(cols));
            let mut unique = assigned.clone();
            unique.sort_unstable();
            unique.dedup();
            assert_eq!(unique.len(), assigned.len(), "a column used twice");
            let best = if rows <= cols {
                brute_force(&cost, rows, cols)
            } else {
                let cost = &cost;
                let t: Vec<f64> = (0..cols)
                    .flat_map(|c| (0..rows).map(move |r| cost[r * cols + c]))
                    .collect();
                brute_force(&t, cols, rows)
            };
            assert_eq!(total(&cost, cols, &a), best, "{rows}x{cols} {cost:?}");
        }
    }
}
