//! Association lists: TUM `rgb.txt` / `depth.txt` (`timestamp file` per line) and their
//! association ([`vlem_datasets::tum::list_from_str`], [`vlem_datasets::tum::associate`]), and the
//! ICL-NUIM / Redwood `rgbd.match` (`depth colour` per line,
//! [`vlem_datasets::match_pairs_from_str`]).
//!
//! The input is the depth list, a NUL byte, then the colour list (without a NUL, the same text is
//! both); the whole input is also parsed as an `rgbd.match`.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use vlem_datasets::tum::{TUM_MAX_TIME_DIFFERENCE, associate, list_from_str};

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let _ = vlem_datasets::match_pairs_from_str(text, Path::new("rgbd.match"));

    let (depth, colour) = text.split_once('\0').unwrap_or((text, text));
    let (Ok(depth), Ok(colour)) = (
        list_from_str(depth, Path::new("depth.txt")),
        list_from_str(colour, Path::new("rgb.txt")),
    ) else {
        return;
    };
    let times = |list: &[vlem_datasets::tum::ListEntry<'_>]| {
        let mut t: Vec<f64> = list.iter().map(|e| e.time).collect();
        t.sort_by(f64::total_cmp);
        t
    };
    let (depth, colour) = (times(&depth), times(&colour));
    let pairs = associate(&depth, &colour, TUM_MAX_TIME_DIFFERENCE);
    let mut taken = vec![false; colour.len()];
    for &(d, c) in &pairs {
        assert!((depth[d] - colour[c]).abs() <= TUM_MAX_TIME_DIFFERENCE);
        assert!(
            !std::mem::replace(&mut taken[c], true),
            "colour {c} used twice"
        );
    }
    assert!(pairs.windows(2).all(|w| w[0].0 < w[1].0));
});
