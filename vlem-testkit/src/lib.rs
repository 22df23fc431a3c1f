//! vlem-testkit: conformance suites that every implementation of a vlem stage runs.
//!
//! Each suite is a macro that expands into `#[test]` functions inside the implementing crate, so a
//! plugin gets the whole contract checked by adding one line to a file under `tests/`. The macros
//! call plain functions of this crate, which are public so that a failing check can also be rerun
//! by hand.
//!
//! - [`encoder_conformance!`]: for [`vlem_core::Encoder`] implementations.
//! - [`map_conformance!`]: for [`vlem_core::EmbeddingMap`] implementations.
//! - [`map_properties!`]: property tests (arbitrary frame sequences) for [`vlem_core::EmbeddingMap`]
//!   implementations.
//! - [`region_proposer_conformance!`]: for [`vlem_core::RegionProposer`] implementations.
//! - [`segmenter_conformance!`]: for [`vlem_core::Segmenter`] implementations.
//! - [`tracker_conformance!`]: for [`vlem_core::Tracker`] implementations, on frames the
//!   implementing crate supplies.

pub mod encoder;
pub mod images;
pub mod map;
pub mod properties;
pub mod proposer;
pub mod segmenter;
pub mod tracker;
