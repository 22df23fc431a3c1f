//! The map file loader ([`vlem_core::mapfile::map_file_from_bytes`]).
//!
//! Each input is tried as it is and, so that the fuzzer gets past the checksum, with its last
//! four bytes replaced by the CRC-32 of the bytes before them.
#![no_main]

use std::path::Path;

use libfuzzer_sys::fuzz_target;
use vlem_core::mapfile::map_file_from_bytes;

fn check(bytes: &[u8]) {
    if let Ok(map) = map_file_from_bytes(bytes, Path::new("map.vlem")) {
        map.validate().expect("a loaded map is consistent");
        // Nothing is allocated beyond what the file holds.
        assert!(map.len() * (12 + 3) + map.embeddings.len() * 4 <= bytes.len());
    }
}

fuzz_target!(|data: &[u8]| {
    check(data);
    if let Some(body_len) = data.len().checked_sub(4) {
        let mut fixed = data.to_vec();
        let crc = crc32fast::hash(&data[..body_len]);
        fixed[body_len..].copy_from_slice(&crc.to_le_bytes());
        check(&fixed);
    }
});
