//! Links every plugin crate into the binary and names the cargo feature of each optional one.
//!
//! `inventory` registrations live in the crates that define them; a crate that is a dependency but
//! never referenced is not linked and its registrations vanish without a word. Every plugin crate
//! the binary depends on is therefore referenced here, and `tests/cli.rs` checks the names that
//! `vlem plugins` lists.
//!
//! Adding a plugin: add the crate as an optional dependency with a feature of the same name in the
//! root `Cargo.toml`, reference it below under that feature, and add a `feature_hint!` line so a
//! binary built without it tells the user which feature to enable.

// Its backends register only when their cargo features are on; its feature hints always do.
use vlem_backends as _;
use vlem_maps as _;
#[cfg(feature = "colour-names")]
use vlem_plugin_colour_names as _;
use vlem_query as _;
use vlem_trackers as _;

vlem_core::feature_hint!(Encoder, "colour-names", "colour-names");
vlem_core::feature_hint!(Map, "point-cloud", "point-cloud");
vlem_core::feature_hint!(Map, "voxel", "voxel");
vlem_core::feature_hint!(Map, "segment", "segment");
