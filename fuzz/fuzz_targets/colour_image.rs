//! Colour image decoding as the dataset readers do it: bytes of a PNG / JPEG / PNM → 8-bit RGB
//! ([`vlem_datasets::colour_from_bytes`]), and the resampled variant of the ScanNet reader
//! ([`vlem_datasets::colour_resized_from_bytes`]).
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let origin = Path::new("colour.jpg");
    if let Ok(rgb) = vlem_datasets::colour_from_bytes(data, origin) {
        let pixels = rgb.width() as usize * rgb.height() as usize;
        assert_eq!(rgb.as_raw().len(), pixels * 3);
        // Resampling to a small depth camera, as ScanNet colour is registered to its depth.
        let resized = vlem_datasets::colour_resized_from_bytes(data, 8, 6, origin);
        let resized = resized.expect("decoded once, so it decodes again");
        assert_eq!((resized.width(), resized.height()), (8, 6));
    }
});
