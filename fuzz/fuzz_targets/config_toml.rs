//! The TOML run configuration ([`vlem_core::Config::from_toml`]) and the checks that need no
//! built stage ([`vlem_core::config::PipelineConfig::validate`] and the real-time frame period);
//! for a config that parses, also that its TOML form ([`vlem_core::Config::to_toml`]) parses back
//! to the same config.
#![no_main]

use libfuzzer_sys::fuzz_target;
use vlem_core::Config;

fuzz_target!(|data: &[u8]| {
    // `Config::from_file` reads with `read_to_string`: non-UTF-8 never reaches the parser.
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(config) = Config::from_toml(text) else {
        return;
    };
    let _ = config.pipeline.validate();
    let _ = config.pipeline.frame_period();
    let written = config.to_toml();
    let again = Config::from_toml(&written)
        .unwrap_or_else(|e| panic!("to_toml wrote a config that does not parse: {e}\n{written}"));
    // Compared as text: NaN parameters are allowed and NaN != NaN.
    assert_eq!(again.to_toml(), written);
});
