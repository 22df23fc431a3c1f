//! Links every plugin crate into every program built on the library (the `vlem` command, the
//! examples, a user's program).
//!
//! `inventory` registrations live in the crates that define them; a crate that is a dependency but
//! never referenced is not linked and its registrations vanish without a word. Every plugin crate
//! the library depends on is therefore referenced here, and `tests/cli.rs` checks the names that
//! `vlem plugins` lists (the examples, which name no plugin crate, build their stages by name).
//!
//! Each crate also declares, with `feature_hint!`, the cargo feature of every optional
//! implementation it owns, whether or not that feature is on, so that a binary built without it
//! tells the user which feature to enable. For that hint to be linked the crate must be linked in
//! every build: a cargo feature of the `vlem` package turns on what a crate registers (as
//! `colour-names` turns on `vlem-plugin-colour-names/colour-names`), never whether it is a
//! dependency.
//!
//! Adding a plugin: add the crate as a dependency in the root `Cargo.toml` with its registering
//! feature off, a feature of the `vlem` package that turns it on, reference the crate below, and
//! declare the feature with `feature_hint!` in the plugin crate.

use vlem_backends as _;
use vlem_datasets as _;
use vlem_maps as _;
use vlem_plugin_colour_names as _;
use vlem_plugin_python as _;
use vlem_query as _;
use vlem_trackers as _;
