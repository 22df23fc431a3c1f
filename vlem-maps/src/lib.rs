//! vlem-maps: embedding maps and query segmenters.
//!
//! Each map is behind a cargo feature named after it (`point-cloud`); segmenters are always built.
//! Everything registers itself with the vlem registry; binaries reference this crate so that the
//! registrations are linked.

pub mod error;
#[cfg(feature = "point-cloud")]
pub mod point_cloud;
pub mod segmenters;

pub use error::MapError;
