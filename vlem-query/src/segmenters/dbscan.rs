//! DBSCAN on 3-D points (Ester et al. 1996): the paper's coordinate clustering, which splits a
//! query's points into objects and drops isolated outliers.
//!
//! Why two versions: [`reference`] is the textbook sequential algorithm (expand a cluster from
//! each unvisited core point through k-d tree radius queries); on a 1M-point map it takes seconds
//! and uses one core. [`dbscan`] gives exactly the same clusters in parallel, from what the
//! sequential order implies: a cluster is a connected component of core points (within `eps` of
//! each other), discovered at its lowest-index core point, so clusters come in the order of that
//! index; a border point belongs to the earliest-discovered cluster that has a core point within
//! `eps` of it. Neighbours come from a uniform grid whose cells are small enough that all points of
//! a cell are within `eps` of each other (the grid DBSCAN of Gunawan, 2013): a cell with
//! `min_points` points is all core at once, others count until they have enough, a cell's core
//! points form one component, and two neighbouring cells need one close pair to join. Components
//! are kept in a lock-free union-find whose roots are the lowest indices; border points pick the
//! lowest root among their core neighbours.

use std::sync::atomic::{AtomicU32, Ordering};

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;
use rustc_hash::FxHashMap;

/// Clusters of `points` (indices into it, ascending within a cluster, clusters in the order the
/// sequential algorithm discovers them); noise points are in none.
///
/// A point is a core point when at least `min_points` points (itself included, as in
/// scikit-learn) lie within `eps` of it (inclusive, squared distances in `f32`); clusters are the
/// points density-reachable from core points. Empty input, a non-positive or non-finite `eps`
/// give no clusters; a non-finite point has no neighbours (not even itself).
pub fn dbscan(points: &[[f32; 3]], eps: f32, min_points: usize) -> Vec<Vec<usize>> {
    if points.is_empty() || !(eps.is_finite() && eps > 0.0) {
        return Vec::new();
    }
    if points.len() >= NONE as usize {
        // Indices are u32 below.
        return reference(points, eps, min_points);
    }
    let grid = &Grid::new(points, eps);
    let r2 = eps * eps;
    let min = u32::try_from(min_points).unwrap_or(u32::MAX);
    let near: Vec<Vec<u32>> = (0..grid.cells.len())
        .into_par_iter()
        .map(|c| grid.around(c))
        .collect();
    let near = &near;
    // Core points, per cell in parallel, in the grid's point order. Every pair of points of one
    // cell is within eps, so a cell holding `min_points` makes all of its points core; otherwise a
    // point counts its neighbours until it has enough.
    let core: Vec<bool> = grid
        .cells
        .par_iter()
        .enumerate()
        .flat_map_iter(|(c, cell)| {
            let dense = cell.end - cell.start >= min;
            (cell.start..cell.end).map(move |a| {
                dense || {
                    let p = grid.sorted[a as usize];
                    let mut n = 0u32;
                    'cells: for &d in &near[c] {
                        for b in grid.range(d) {
                            n += u32::from(within(p, grid.sorted[b as usize], r2));
                            if n >= min {
                                break 'cells;
                            }
                        }
                    }
                    n >= min
                }
            })
        })
        .collect();
    let core = &core;
    let parent: Vec<AtomicU32> = (0..points.len() as u32).map(AtomicU32::new).collect();
    let parent = &parent;
    // Join core points within eps. In a cell they all are: one chain per cell. Between two
    // neighbouring cells one pair within eps joins them; a pair of cells already joined (through
    // other cells) is skipped.
    grid.cells.par_iter().enumerate().for_each(|(c, cell)| {
        let mut first = None;
        for a in cell.start..cell.end {
            if core[a as usize] {
                let i = grid.order[a as usize];
                match first {
                    None => first = Some(i),
                    Some(f) => union(parent, f, i),
                }
            }
        }
        let Some(f) = first else { return };
        for &d in near[c].iter().filter(|&&d| d as usize > c) {
            let others = grid.range(d);
            let Some(g) = others
                .clone()
                .find(|&b| core[b as usize])
                .map(|b| grid.order[b as usize])
            else {
                continue;
            };
            if find(parent, f) == find(parent, g) {
                continue;
            }
            let joined = (cell.start..cell.end)
                .filter(|&a| core[a as usize])
                .any(|a| {
                    let p = grid.sorted[a as usize];
                    others
                        .clone()
                        .any(|b| core[b as usize] && within(p, grid.sorted[b as usize], r2))
                });
            if joined {
                union(parent, f, g);
            }
        }
    });
    // Every point's cluster root: its own for a core point, the lowest root among its core
    // neighbours for a border point, none for noise.
    let labels: Vec<(u32, u32)> = grid
        .cells
        .par_iter()
        .enumerate()
        .flat_map_iter(|(c, cell)| {
            (cell.start..cell.end).filter_map(move |a| {
                let i = grid.order[a as usize];
                if core[a as usize] {
                    return Some((i, find(parent, i)));
                }
                let p = grid.sorted[a as usize];
                let mut best = NONE;
                for &d in &near[c] {
                    for b in grid.range(d) {
                        if core[b as usize] && within(p, grid.sorted[b as usize], r2) {
                            best = best.min(find(parent, grid.order[b as usize]));
                        }
                    }
                }
                (best != NONE).then_some((i, best))
            })
        })
        .collect();
    let mut root = vec![NONE; points.len()];
    for (i, r) in labels {
        root[i as usize] = r;
    }
    // A point that is not in the grid (not finite) has no neighbours: a cluster of its own only
    // when every point is core.
    if min == 0 {
        for (i, p) in points.iter().enumerate() {
            if !p.iter().all(|x| x.is_finite()) {
                root[i] = i as u32;
            }
        }
    }
    // Clusters in the order of their roots (their lowest core index); members ascending.
    let mut ordinal = vec![NONE; points.len()];
    let mut clusters: Vec<Vec<usize>> = Vec::new();
    for (i, &r) in root.iter().enumerate() {
        if r == i as u32 {
            ordinal[i] = clusters.len() as u32;
            clusters.push(Vec::new());
        }
    }
    for (i, &r) in root.iter().enumerate() {
        if r != NONE {
            clusters[ordinal[r as usize] as usize].push(i);
        }
    }
    clusters
}

/// No point, no root.
const NONE: u32 = u32::MAX;

/// `|p - q|² <= r2`, summed in the order the k-d tree sums it, so both versions agree at the
/// boundary.
#[inline]
fn within(p: [f32; 3], q: [f32; 3], r2: f32) -> bool {
    let d = |a: f32, b: f32| (a - b) * (a - b);
    d(p[0], q[0]) + d(p[1], q[1]) + d(p[2], q[2]) <= r2
}

/// The root of `x` (the lowest index of its component), halving the path on the way.
fn find(parent: &[AtomicU32], mut x: u32) -> u32 {
    loop {
        let p = parent[x as usize].load(Ordering::Acquire);
        if p == x {
            return x;
        }
        let grand = parent[p as usize].load(Ordering::Acquire);
        // Parents only ever point lower, so `grand` is an ancestor of `x` whatever else happens.
        let _ =
            parent[x as usize].compare_exchange_weak(p, grand, Ordering::AcqRel, Ordering::Relaxed);
        x = grand;
    }
}

/// Joins the components of `a` and `b`: the higher root is linked under the lower one, so every
/// root stays its component's lowest index.
fn union(parent: &[AtomicU32], a: u32, b: u32) {
    loop {
        let (ra, rb) = (find(parent, a), find(parent, b));
        if ra == rb {
            return;
        }
        let (high, low) = if ra > rb { (ra, rb) } else { (rb, ra) };
        if parent[high as usize]
            .compare_exchange(high, low, Ordering::AcqRel, Ordering::Acquire)
            .is_ok()
        {
            return;
        }
    }
}

/// Cells per `eps`: a cell's side is `eps / CELLS_PER_EPS`, short enough that its diagonal
/// (`√3 / 1.75 ≈ 0.99 eps`) keeps every pair in a cell within `eps` whatever the rounding, and a
/// point's neighbours lie within two cells along each axis.
const CELLS_PER_EPS: f32 = 1.75;
/// Cells searched along each axis on either side.
const REACH: i64 = 2;

/// A uniform grid over the finite points, each cell's points contiguous.
struct Grid {
    /// Original indices, sorted by cell.
    order: Vec<u32>,
    /// The points in that order.
    sorted: Vec<[f32; 3]>,
    /// Occupied cells, in key order.
    cells: Vec<Cell>,
    /// Cell key → position in `cells`.
    index: FxHashMap<[i64; 3], u32>,
}

struct Cell {
    key: [i64; 3],
    start: u32,
    end: u32,
}

impl Grid {
    fn new(points: &[[f32; 3]], eps: f32) -> Self {
        let side = eps / CELLS_PER_EPS;
        let key = |p: &[f32; 3]| p.map(|x| (x / side).floor() as i64);
        let mut keyed: Vec<([i64; 3], u32)> = points
            .par_iter()
            .enumerate()
            .filter(|(_, p)| p.iter().all(|x| x.is_finite()))
            .map(|(i, p)| (key(p), i as u32))
            .collect();
        keyed.par_sort_unstable();
        let mut cells: Vec<Cell> = Vec::new();
        for (k, (cell_key, _)) in keyed.iter().enumerate() {
            match cells.last_mut() {
                Some(last) if last.key == *cell_key => last.end = k as u32 + 1,
                _ => cells.push(Cell {
                    key: *cell_key,
                    start: k as u32,
                    end: k as u32 + 1,
                }),
            }
        }
        let index = cells
            .iter()
            .enumerate()
            .map(|(c, cell)| (cell.key, c as u32))
            .collect();
        let order: Vec<u32> = keyed.iter().map(|&(_, i)| i).collect();
        let sorted = order.iter().map(|&i| points[i as usize]).collect();
        Self {
            order,
            sorted,
            cells,
            index,
        }
    }

    /// The occupied cells within [`REACH`] cells of cell `c` along every axis (itself included).
    fn around(&self, c: usize) -> Vec<u32> {
        let k = self.cells[c].key;
        let mut out = Vec::new();
        for dx in -REACH..=REACH {
            for dy in -REACH..=REACH {
                for dz in -REACH..=REACH {
                    let n = [
                        k[0].saturating_add(dx),
                        k[1].saturating_add(dy),
                        k[2].saturating_add(dz),
                    ];
                    if let Some(&id) = self.index.get(&n) {
                        out.push(id);
                    }
                }
            }
        }
        // Saturated keys at the extremes can repeat a cell.
        out.sort_unstable();
        out.dedup();
        out
    }

    /// The grid positions of cell `c`'s points.
    fn range(&self, c: u32) -> std::ops::Range<u32> {
        let cell = &self.cells[c as usize];
        cell.start..cell.end
    }
}

/// The textbook sequential algorithm with k-d tree radius queries: what [`dbscan`] must give
/// exactly, kept to test and benchmark it against. Clusters of `points` (indices into it, ascending
/// within a cluster, clusters in the order they were discovered); noise points are in none.
///
/// A point is a core point when at least `min_points` points (itself included, as in
/// scikit-learn) lie within `eps` of it; clusters are the points density-reachable from core
/// points. Empty input, a non-positive or non-finite `eps` give no clusters.
pub fn reference(points: &[[f32; 3]], eps: f32, min_points: usize) -> Vec<Vec<usize>> {
    if points.is_empty() || !(eps.is_finite() && eps > 0.0) {
        return Vec::new();
    }
    let tree: ImmutableKdTree<f32, 3> = match ImmutableKdTree::new_from_slice(points) {
        Ok(tree) => tree,
        // Construction fails only for an empty slice, excluded above.
        Err(_) => return Vec::new(),
    };
    // kiddo's radius is in the metric's units: squared distance.
    let r2 = eps * eps;
    let neighbours = |i: usize| -> Vec<usize> {
        tree.query(&points[i])
            .within::<SquaredEuclidean<f32>>(r2)
            .unsorted()
            .execute()
            .into_iter()
            .map(|n| n.item as usize)
            .collect()
    };
    const UNVISITED: u32 = u32::MAX;
    const NOISE: u32 = u32::MAX - 1;
    let mut label = vec![UNVISITED; points.len()];
    let mut clusters: Vec<Vec<usize>> = Vec::new();
    let mut queue = Vec::new();
    for start in 0..points.len() {
        if label[start] != UNVISITED {
            continue;
        }
        let seeds = neighbours(start);
        if seeds.len() < min_points {
            label[start] = NOISE;
            continue;
        }
        let id = clusters.len() as u32;
        label[start] = id;
        let mut members = vec![start];
        queue.clear();
        queue.extend(seeds);
        while let Some(j) = queue.pop() {
            if label[j] == NOISE {
                // A border point: reachable, but not core (its neighbours were counted already).
                label[j] = id;
                members.push(j);
                continue;
            }
            if label[j] != UNVISITED {
                continue;
            }
            label[j] = id;
            members.push(j);
            let more = neighbours(j);
            if more.len() >= min_points {
                queue.extend(
                    more.into_iter()
                        .filter(|&m| label[m] == UNVISITED || label[m] == NOISE),
                );
            }
        }
        members.sort_unstable();
        clusters.push(members);
    }
    clusters
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Both versions, which must agree.
    fn both(points: &[[f32; 3]], eps: f32, min_points: usize) -> Vec<Vec<usize>> {
        let fast = dbscan(points, eps, min_points);
        assert_eq!(
            fast,
            reference(points, eps, min_points),
            "eps {eps}, min {min_points}"
        );
        fast
    }

    /// A 5×5×5 grid with 1 cm spacing around `c`.
    fn blob(c: [f32; 3]) -> Vec<[f32; 3]> {
        let mut out = Vec::new();
        for x in 0..5 {
            for y in 0..5 {
                for z in 0..5 {
                    out.push([
                        c[0] + 0.01 * x as f32,
                        c[1] + 0.01 * y as f32,
                        c[2] + 0.01 * z as f32,
                    ]);
                }
            }
        }
        out
    }

    #[test]
    fn two_blobs_and_noise_give_two_clusters() {
        let mut points = blob([0.0, 0.0, 0.0]);
        points.extend(blob([1.0, 0.0, 0.0]));
        // Isolated points, far from both blobs and each other.
        points.extend([[0.5, 0.5, 0.5], [-1.0, 2.0, 0.0], [3.0, -1.0, 1.0]]);
        let clusters = both(&points, 0.02, 5);
        assert_eq!(clusters.len(), 2);
        assert_eq!(clusters[0], (0..125).collect::<Vec<_>>());
        assert_eq!(clusters[1], (125..250).collect::<Vec<_>>());
    }

    #[test]
    fn border_points_join_and_sparse_sets_are_noise() {
        // A line of points 1 cm apart: with eps 1.5 cm every inner point has 3 neighbours.
        let line: Vec<[f32; 3]> = (0..10).map(|i| [0.01 * i as f32, 0.0, 0.0]).collect();
        let clusters = both(&line, 0.015, 3);
        // The ends have only 2 neighbours (not core) but are reachable: border points.
        assert_eq!(clusters, vec![(0..10).collect::<Vec<_>>()]);
        assert!(both(&line, 0.015, 4).is_empty());
    }

    /// Points from a small linear congruential generator: blobs of different densities, uniform
    /// noise, exact duplicates and points on a lattice (distances exactly at `eps`).
    fn scene(seed: u64, n: usize) -> Vec<[f32; 3]> {
        let mut state = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let mut next = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let mut points = Vec::with_capacity(n);
        while points.len() < n {
            match (next() * 4.0) as u32 {
                0 => points.push([next(), next(), next()]),
                1 => {
                    let spread = 0.02 + 0.05 * next();
                    let c = [next(), next(), next()];
                    for _ in 0..20 {
                        points.push(c.map(|x| x + spread * (next() - 0.5)));
                    }
                }
                2 => {
                    let c = [
                        (next() * 50.0).floor() * 0.02,
                        0.5,
                        (next() * 50.0).floor() * 0.02,
                    ];
                    for k in 0..5 {
                        points.push([c[0] + 0.02 * k as f32, c[1], c[2]]);
                    }
                }
                _ => {
                    if let Some(&p) = points.last() {
                        points.push(p);
                    }
                }
            }
        }
        points.truncate(n);
        points
    }

    #[test]
    fn the_parallel_version_gives_the_reference_clusters() {
        for seed in 0..12 {
            let points = scene(seed, 300 + 150 * seed as usize);
            for (eps, min_points) in [(0.02, 3), (0.05, 5), (0.05, 10), (0.1, 2), (0.2, 30)] {
                both(&points, eps, min_points);
            }
        }
    }

    #[test]
    fn a_border_point_between_two_clusters_joins_the_one_discovered_first() {
        // Exact binary coordinates: the border point is exactly eps from a core point of each.
        let a: Vec<[f32; 3]> = (0..5).map(|k| [0.125 * k as f32, 0.0, 0.0]).collect();
        let b: Vec<[f32; 3]> = (0..5).map(|k| [1.5 + 0.125 * k as f32, 0.0, 0.0]).collect();
        let border = [1.0, 0.0, 0.0];
        let first_a: Vec<[f32; 3]> = a.iter().chain(&b).copied().chain([border]).collect();
        let clusters = both(&first_a, 0.5, 5);
        assert_eq!(clusters, vec![vec![0, 1, 2, 3, 4, 10], vec![5, 6, 7, 8, 9]]);
        let first_b: Vec<[f32; 3]> = [border].into_iter().chain(b).chain(a).collect();
        let clusters = both(&first_b, 0.5, 5);
        assert_eq!(clusters, vec![vec![0, 1, 2, 3, 4, 5], vec![6, 7, 8, 9, 10]]);
    }

    #[test]
    fn non_finite_points_are_noise_unless_every_point_is_core() {
        let mut points = scene(3, 200);
        points[7] = [f32::NAN, 0.0, 0.0];
        points[50] = [0.0, f32::INFINITY, 0.0];
        let clusters = both(&points, 0.05, 3);
        assert!(clusters.iter().all(|c| !c.contains(&7) && !c.contains(&50)));
        let all_core = both(&points, 0.05, 0);
        assert!(all_core.contains(&vec![7]) && all_core.contains(&vec![50]));
    }

    #[test]
    fn degenerate_inputs_do_not_panic() {
        assert!(dbscan(&[], 0.05, 10).is_empty());
        assert!(dbscan(&[[0.0; 3]; 4], 0.0, 1).is_empty());
        assert!(dbscan(&[[0.0; 3]; 4], f32::NAN, 1).is_empty());
        // Identical points: one cluster.
        assert_eq!(
            both(&[[1.0; 3]; 20], 0.05, 10),
            vec![(0..20).collect::<Vec<_>>()]
        );
        // min_points 0 or 1: every point is core; a lone point is its own cluster.
        assert_eq!(both(&[[0.0; 3], [5.0; 3]], 0.05, 1).len(), 2);
    }
}
