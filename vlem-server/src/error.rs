//! The error type of `vlem-server`.

/// Failures of starting the server and of the client's requests.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ServerError {
    /// An address that is not a loopback address, or not an address at all.
    #[error("cannot serve on {address}: {reason}")]
    Address {
        /// The address as given.
        address: String,
        /// Why not.
        reason: String,
    },
    /// A server option that cannot work (an empty or short token, a zero limit).
    #[error("cannot serve with this {option}: {reason}")]
    Option {
        /// The option's name.
        option: &'static str,
        /// Why not.
        reason: String,
    },
    /// The listening socket could not be opened.
    #[error("cannot listen on {address}: {reason}")]
    Listen {
        /// The address.
        address: String,
        /// The system's reason.
        reason: String,
    },
    /// The server could not be reached or the connection failed.
    #[error("cannot reach the vlem server at {address}: {reason}")]
    Connect {
        /// The address.
        address: String,
        /// The transport's reason.
        reason: String,
    },
    /// The server answered with an error status.
    #[error("the vlem server answered {status}: {message}")]
    Status {
        /// HTTP status code.
        status: u16,
        /// The server's message.
        message: String,
    },
    /// The server's answer could not be read.
    #[error("unreadable answer from the vlem server: {reason}")]
    Body {
        /// Why.
        reason: String,
    },
}
