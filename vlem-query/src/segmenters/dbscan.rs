//! DBSCAN on 3-D points (Ester et al. 1996), with k-d tree radius queries: the paper's coordinate
//! clustering, which splits a query's points into objects and drops isolated outliers.

use kiddo::{ImmutableKdTree, SquaredEuclidean};

/// Clusters of `points` (indices into it, ascending within a cluster, clusters in the order they
/// were discovered); noise points are in none.
///
/// A point is a core point when at least `min_points` points (itself included, as in
/// scikit-learn) lie within `eps` of it; clusters are the points density-reachable from core
/// points. Empty input, a non-positive or non-finite `eps` give no clusters.
pub fn dbscan(points: &[[f32; 3]], eps: f32, min_points: usize) -> Vec<Vec<usize>> {
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
        let clusters = dbscan(&points, 0.02, 5);
        assert_eq!(clusters.len(), 2);
        assert_eq!(clusters[0], (0..125).collect::<Vec<_>>());
        assert_eq!(clusters[1], (125..250).collect::<Vec<_>>());
    }

    #[test]
    fn border_points_join_and_sparse_sets_are_noise() {
        // A line of points 1 cm apart: with eps 1.5 cm every inner point has 3 neighbours.
        let line: Vec<[f32; 3]> = (0..10).map(|i| [0.01 * i as f32, 0.0, 0.0]).collect();
        let clusters = dbscan(&line, 0.015, 3);
        // The ends have only 2 neighbours (not core) but are reachable: border points.
        assert_eq!(clusters, vec![(0..10).collect::<Vec<_>>()]);
        assert!(dbscan(&line, 0.015, 4).is_empty());
    }

    #[test]
    fn degenerate_inputs_do_not_panic() {
        assert!(dbscan(&[], 0.05, 10).is_empty());
        assert!(dbscan(&[[0.0; 3]; 4], 0.0, 1).is_empty());
        assert!(dbscan(&[[0.0; 3]; 4], f32::NAN, 1).is_empty());
        // Identical points: one cluster.
        assert_eq!(
            dbscan(&[[1.0; 3]; 20], 0.05, 10),
            vec![(0..20).collect::<Vec<_>>()]
        );
        // min_points 0 or 1: every point is core; a lone point is its own cluster.
        assert_eq!(dbscan(&[[0.0; 3], [5.0; 3]], 0.05, 1).len(), 2);
    }
}
