//! Association: which 3D segment each 2D segment of a frame joins (step 2 of the segment map).
//!
//! Why a file of its own: it is the part of the segment map that decides identity over time
//! (overlap scores of cells, the `min_overlap` threshold, the Hungarian assignment), and the
//! part most worth reading and changing on its own.

use std::collections::{BTreeMap, HashMap};

use super::hungarian::hungarian;
use super::{Observed, SegmentMap};

impl SegmentMap {
    /// For every 2D segment, the 3D segment it is matched with.
    pub(super) fn associate(&self, observed: &Observed) -> Vec<Option<u64>> {
        // Cells of each 3D segment that this frame observed.
        let mut in_frame: HashMap<u64, usize> = HashMap::new();
        for key in observed.cells.keys() {
            if let Some(&id) = self.owner.get(key) {
                *in_frame.entry(id).or_default() += 1;
            }
        }
        let mut rows = Vec::new();
        let mut overlaps: Vec<Vec<(u64, usize)>> = Vec::new();
        let mut cols: Vec<u64> = Vec::new();
        for (i, s) in observed.segments.iter().enumerate() {
            let mut counts: BTreeMap<u64, usize> = BTreeMap::new();
            for key in &s.cells {
                if let Some(&id) = self.owner.get(key) {
                    *counts.entry(id).or_default() += 1;
                }
            }
            if !counts.is_empty() {
                cols.extend(counts.keys());
                rows.push(i);
                overlaps.push(counts.into_iter().collect());
            }
        }
        let mut matches = vec![None; observed.segments.len()];
        if rows.is_empty() {
            return matches;
        }
        cols.sort_unstable();
        cols.dedup();
        let min_overlap = f64::from(self.config.min_overlap);
        let mut cost = vec![0.0f64; rows.len() * cols.len()];
        let mut score = vec![0.0f64; rows.len() * cols.len()];
        for (r, (&i, counts)) in rows.iter().zip(&overlaps).enumerate() {
            let size = observed.segments[i].cells.len();
            for &(id, overlap) in counts {
                let Ok(c) = cols.binary_search(&id) else {
                    continue;
                };
                let seen = in_frame.get(&id).copied().unwrap_or(overlap);
                let s = overlap as f64 / size.min(seen).max(1) as f64;
                score[r * cols.len() + c] = s;
                // Pairs below the threshold are no edge, so they never displace a valid pair.
                if s >= min_overlap {
                    cost[r * cols.len() + c] = -s;
                }
            }
        }
        for (r, c) in hungarian(&cost, rows.len(), cols.len())
            .into_iter()
            .enumerate()
        {
            if let Some(c) = c
                && score[r * cols.len() + c] >= min_overlap
            {
                matches[rows[r]] = Some(cols[c]);
            }
        }
        matches
    }
}
