//! The query server's request heads (`vlem-server/src/http.rs`): whatever a client sends, the
//! parser answers "complete", "more bytes" or one of its refusal statuses, and never panics.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    match vlem_server::__fuzz::request_head(data) {
        Ok(Some(length)) => assert!(length <= data.len()),
        Ok(None) => {}
        Err(status) => assert!(
            [400, 414, 431, 505].contains(&status),
            "unexpected status {status}"
        ),
    }
});
