//! The one error type of the ROS 2 node.

use vlem_core::CoreError;

/// Every way starting or running the node can fail. Bad messages are not errors: they are
/// counted and skipped ([`crate::status`]).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Ros2Error {
    /// Settings that cannot work, or a node that cannot start its threads.
    #[error("{0}")]
    Config(String),
    /// The DDS participant, a topic, a publisher or a subscription could not be created.
    #[error("ROS 2 / DDS: {0}")]
    Dds(String),
    /// The pipeline's error.
    #[error(transparent)]
    Core(#[from] CoreError),
}

/// Result with [`Ros2Error`].
pub type Result<T, E = Ros2Error> = std::result::Result<T, E>;
