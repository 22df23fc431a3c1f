//! The `cluster` segmenter on a 1M-point map (issue: "segmentation in milliseconds"): DBSCAN
//! alone, the parallel version against the sequential reference in the same run, and the whole
//! segmenter (argmax partition, GMM, DBSCAN) as `vlem query --segmenter cluster` runs it.
//!
//! The map is generated: a 4 × 3 × 2.5 m room (floor, ceiling, walls) and twelve boxes on the
//! floor, sampled at about 1 cm with 2 mm noise, as a fused point-cloud map of a room scan is;
//! two queries score the boxes high (each half of them) and a baseline the rest.
//!
//!     cargo bench -p vlem-query --bench cluster [-- POINTS]      (default 1000000)

use std::time::Instant;

use vlem_core::{QueryScores, Segmenter};
use vlem_query::segmenters::{ClusterSegmenter, dbscan};

/// A small deterministic generator (no dependency for a bench).
struct Lcg(u64);

impl Lcg {
    fn unit(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// `n` points on the room's surfaces and boxes, and which box (if any) each lies on.
fn room(n: usize) -> (Vec<[f32; 3]>, Vec<Option<usize>>) {
    let mut rng = Lcg(7);
    let boxes: Vec<[f32; 3]> = (0..12)
        .map(|b| [0.4 + 0.6 * (b % 6) as f32, 0.8 + 1.2 * (b / 6) as f32, 0.0])
        .collect();
    let (mut points, mut on) = (Vec::with_capacity(n), Vec::with_capacity(n));
    while points.len() < n {
        let noise = |rng: &mut Lcg| 0.004 * (rng.unit() - 0.5);
        let (u, v) = (rng.unit(), rng.unit());
        // By area: the boxes are 5.4 of the 64.4 m² of surface.
        if rng.unit() < 0.084 {
            // A box: 30 cm cube, a random face (not the bottom).
            let b = (rng.unit() * 12.0) as usize % 12;
            let c = boxes[b];
            let p = match (rng.unit() * 5.0) as u32 {
                0 => [c[0] + 0.3 * u, c[1] + 0.3 * v, 0.3],
                1 => [c[0], c[1] + 0.3 * u, 0.3 * v],
                2 => [c[0] + 0.3, c[1] + 0.3 * u, 0.3 * v],
                3 => [c[0] + 0.3 * u, c[1], 0.3 * v],
                _ => [c[0] + 0.3 * u, c[1] + 0.3, 0.3 * v],
            };
            points.push(p.map(|x| x + noise(&mut rng)));
            on.push(Some(b));
        } else {
            let p = match (rng.unit() * 6.0) as u32 {
                0 => [4.0 * u, 3.0 * v, 0.0],
                1 => [4.0 * u, 3.0 * v, 2.5],
                2 => [0.0, 3.0 * u, 2.5 * v],
                3 => [4.0, 3.0 * u, 2.5 * v],
                4 => [4.0 * u, 0.0, 2.5 * v],
                _ => [4.0 * u, 3.0, 2.5 * v],
            };
            points.push(p.map(|x| x + noise(&mut rng)));
            on.push(None);
        }
    }
    (points, on)
}

fn seconds(f: impl FnOnce() -> usize) -> (f64, usize) {
    let t = Instant::now();
    let n = f();
    (t.elapsed().as_secs_f64(), n)
}

fn main() -> anyhow::Result<()> {
    let n: usize = std::env::args()
        .skip(1)
        .find_map(|a| a.parse().ok())
        .unwrap_or(1_000_000);
    let (points, on) = room(n);
    let mut rng = Lcg(11);
    let mut jitter = move || 0.05 * rng.unit();
    let score = |query: usize, b: Option<usize>, j: f32| match b {
        Some(b) if b % 2 == query => 0.85 + j,
        _ => 0.55 + j,
    };
    let scores = QueryScores {
        queries: vec!["even boxes".into(), "odd boxes".into()],
        scores: (0..2)
            .map(|q| on.iter().map(|&b| score(q, b, jitter())).collect())
            .collect(),
        baseline: Some(
            on.iter()
                .map(|b| if b.is_some() { 0.6 } else { 0.7 })
                .collect(),
        ),
    };
    let threads = rayon::current_num_threads();
    println!("{n} points, {threads} threads, eps 0.05 m, 10 points");
    let subset: Vec<[f32; 3]> = points
        .iter()
        .zip(&on)
        .filter(|(_, b)| b.is_some())
        .map(|(p, _)| *p)
        .collect();
    for (name, input) in [("box points", &subset), ("all points", &points)] {
        let (fast, clusters) = seconds(|| dbscan::dbscan(input, 0.05, 10).len());
        let (slow, same) = seconds(|| dbscan::reference(input, 0.05, 10).len());
        println!(
            "{{\"bench\":\"dbscan\",\"input\":\"{name}\",\"points\":{},\"clusters\":{clusters},\"reference_s\":{slow:.3},\"parallel_s\":{fast:.3},\"speedup\":{:.1}}}",
            input.len(),
            slow / fast
        );
        anyhow::ensure!(
            clusters == same,
            "the versions found {clusters} and {same} clusters"
        );
    }
    let segmenter = ClusterSegmenter::default();
    for _ in 0..2 {
        let t = Instant::now();
        let sets = segmenter.segment(&points, &scores)?.len();
        let t = t.elapsed().as_secs_f64();
        println!(
            "{{\"bench\":\"cluster segmenter\",\"points\":{n},\"queries\":2,\"sets\":{sets},\"seconds\":{t:.3}}}"
        );
    }
    Ok(())
}
