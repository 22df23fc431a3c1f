//! Open3D `PinholeCameraIntrinsic` JSON ([`vlem_datasets::open3d_intrinsics_from_str`]).
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    // The path version reads the file with `read_to_string`: non-UTF-8 never reaches the parser.
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(k) = vlem_datasets::open3d_intrinsics_from_str(text, Path::new("intrinsics.json")) {
        k.validate().expect("parsed intrinsics are valid");
    }
});
