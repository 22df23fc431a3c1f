//! vlem-server: the live map of a running pipeline over HTTP/JSON, and the client that asks it.
//!
//! Why it exists: a robot, a notebook or a second terminal wants to ask "where is the mug?" while
//! `vlem run` is still mapping. [`QueryServer`] serves a [`vlem_core::live::LiveMap`] on a
//! loopback address, a thread per connection with every connection, request and map pass bounded
//! (`server.rs` lists the bounds, `http.rs` the per-connection limits); every answer comes from `vlem-query`, the same
//! code `vlem query --map` runs, so a live answer and a saved-map answer print the same. A request
//! never stops the mapping run: bad requests get a 4xx status with a message, and a handler that
//! fails unexpectedly answers 500.
//!
//! Who may ask is decided in `guard.rs` before a request is routed: a loopback `Host` with
//! the server's port, no cross-site `Origin`, JSON POSTs only, and an optional bearer token (the
//! docs/server.md's threat model says why each one).
//!
//! Endpoints (JSON unless said otherwise; see [`api`] for the bodies):
//! - `GET /status`: the run's counters, the latest pose and the map's size ([`api::Status`]);
//! - `POST /query`: texts → answers ([`api::QueryRequest`] → [`vlem_query::answer::Answer`]);
//! - `GET /heatmap.ply?text=...`: one text's heatmap as binary PLY;
//! - `POST /snapshot`: save the map as it is into the run's output folder, under the next free
//!   name `snapshot-NNNN.vlem` (the request names no path);
//! - `GET /map.vlem`: the map as it is, as a map file in the response body, encoded while it is
//!   sent (one copy of the map per download, no encoded file in memory).

pub mod api;
mod client;
mod error;
mod guard;
mod http;
mod server;

pub use client::Client;
pub use error::ServerError;
pub use server::{QueryServer, RequestLimits, ServeOptions};

/// Entry points for `fuzz/` (not a public API: hidden and unstable).
#[doc(hidden)]
pub mod __fuzz {
    /// Parses `bytes` as the start of a request, with the server's limits, as a connection does:
    /// `Ok(Some(length))` for a complete head, `Ok(None)` for one that needs more bytes, and the
    /// status a refusal would get.
    ///
    /// # Errors
    /// The HTTP status of a refused head (400, 414, 431, 505).
    pub fn request_head(bytes: &[u8]) -> Result<Option<usize>, u16> {
        match crate::http::parse_head(bytes, &crate::http::Limits::SERVER) {
            Ok(head) => Ok(head.map(|(_, length)| length)),
            Err(crate::http::ReadError::Refuse { status, .. }) => Err(status),
            Err(crate::http::ReadError::Closed) => Err(0),
        }
    }
}
