//! Estimates of the heap bytes of the `std` collections the maps keep, for
//! [`EmbeddingMap::memory_bytes`](vlem_core::EmbeddingMap::memory_bytes): capacity is not enough
//! for hash tables (control bytes, load factor) and B-trees (node headers and slack).

/// Buckets of a `std` hash table whose full capacity (no tombstones) is `capacity`: the table
/// keeps 1/8 of its buckets free (one bucket below 8 buckets), and bucket counts are powers of two.
/// Each bucket holds one entry and one control byte.
#[cfg_attr(
    not(any(feature = "voxel", feature = "segment")),
    allow(dead_code, reason = "only the voxel and segment maps have hash tables")
)]
pub(crate) fn hash_buckets(capacity: usize) -> usize {
    match capacity {
        0 => 0,
        c if c < 8 => (c + 1).next_power_of_two(),
        c => (c / 7 * 8).next_power_of_two(),
    }
}

/// A lower bound on the bytes of a `std` B-tree map of `len` entries of `entry` (key plus value)
/// bytes: nodes of up to 11 entries after a 12-byte header (parent pointer, index, length), so
/// at least `len / 11` of them; when there are several, one is internal, with 12 edge pointers
/// besides. Nodes are often only half full, so the real figure is up to about twice this.
#[cfg_attr(
    not(feature = "segment"),
    allow(dead_code, reason = "only the segment map has B-trees")
)]
pub(crate) fn btree_bytes(len: usize, entry: usize) -> usize {
    const CAPACITY: usize = 11;
    let nodes = len.div_ceil(CAPACITY);
    let leaf = (12 + CAPACITY * entry).next_multiple_of(8);
    let edges = if nodes > 1 { (CAPACITY + 1) * 8 } else { 0 };
    nodes * leaf + edges
}
