//! Depth image decoding as the dataset readers do it: bytes of a 16-bit PNG (or anything else) →
//! depth in metres ([`vlem_datasets::depth_from_bytes`]).
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    // 1000 units per metre (ICL, ScanNet); TUM's 5000 takes the same path.
    if let Ok(depth) = vlem_datasets::depth_from_bytes(data, 1000.0, Path::new("depth.png")) {
        let pixels = depth.width() as usize * depth.height() as usize;
        assert_eq!(depth.as_raw().len(), pixels);
        assert!(depth.as_raw().iter().all(|d| d.is_finite() && *d >= 0.0));
    }
});
