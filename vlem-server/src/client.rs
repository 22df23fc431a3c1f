//! The client of the query server, as `vlem query --connect` uses it.

use std::time::Duration;

use serde::Serialize;
use serde::de::DeserializeOwned;
use ureq::Agent;
use ureq::http::Response;
use vlem_query::answer::Answer;

use crate::api::{ErrorReply, QueryRequest, SnapshotSaved, Status};
use crate::error::ServerError;

/// A connection to a query server at `host:port` (plain HTTP, loopback).
pub struct Client {
    base: String,
    address: String,
    agent: Agent,
    /// `Authorization: Bearer …` for a server started with a token.
    authorization: Option<String>,
}

impl Client {
    /// A client for the server at `address` (`127.0.0.1:8765` or `http://127.0.0.1:8765`).
    /// Nothing is sent until the first request.
    pub fn new(address: &str) -> Self {
        let base = if address.starts_with("http://") {
            address.trim_end_matches('/').to_owned()
        } else {
            format!("http://{}", address.trim_end_matches('/'))
        };
        let agent = Agent::config_builder()
            .http_status_as_error(false)
            // Clustering a large map can take seconds; a hung server should not hang the client.
            .timeout_global(Some(Duration::from_secs(300)))
            .build()
            .new_agent();
        Self {
            base,
            address: address.to_owned(),
            agent,
            authorization: None,
        }
    }

    /// Sends `Authorization: Bearer TOKEN` with every request (for a server started with
    /// `--serve-token`).
    #[must_use]
    pub fn with_token(mut self, token: &str) -> Self {
        self.authorization = Some(format!("Bearer {token}"));
        self
    }

    fn get(&self, path: &str) -> ureq::RequestBuilder<ureq::typestate::WithoutBody> {
        let request = self.agent.get(format!("{}{path}", self.base));
        match &self.authorization {
            Some(value) => request.header("Authorization", value),
            None => request,
        }
    }

    /// `GET /status`.
    ///
    /// # Errors
    /// [`ServerError::Connect`] when the server cannot be reached, [`ServerError::Status`] for an
    /// error answer, [`ServerError::Body`] for an unreadable one.
    pub fn status(&self) -> Result<Status, ServerError> {
        let response = self.get("/status").call().map_err(|e| self.connect(&e))?;
        json(response)
    }

    /// `POST /query`.
    ///
    /// # Errors
    /// As [`Client::status`].
    pub fn query(&self, request: &QueryRequest) -> Result<Answer, ServerError> {
        self.post("/query", request)
    }

    /// `POST /snapshot`: the server saves its map into its output folder under a name it
    /// chooses, and says where.
    ///
    /// # Errors
    /// As [`Client::status`].
    pub fn snapshot(&self) -> Result<SnapshotSaved, ServerError> {
        self.post("/snapshot", &serde_json::json!({}))
    }

    /// `GET /heatmap.ply?text=...`: the binary PLY heatmap of one text.
    ///
    /// # Errors
    /// As [`Client::status`].
    pub fn heatmap(&self, text: &str, grasp: bool) -> Result<Vec<u8>, ServerError> {
        let response = self
            .get("/heatmap.ply")
            .query("text", text)
            .query("grasp", if grasp { "1" } else { "0" })
            .call()
            .map_err(|e| self.connect(&e))?;
        bytes(response)
    }

    /// `GET /map.vlem`: the map as a map file.
    ///
    /// # Errors
    /// As [`Client::status`].
    pub fn map_file(&self) -> Result<Vec<u8>, ServerError> {
        let response = self.get("/map.vlem").call().map_err(|e| self.connect(&e))?;
        bytes(response)
    }

    fn post<T: DeserializeOwned>(
        &self,
        path: &str,
        body: &impl Serialize,
    ) -> Result<T, ServerError> {
        let mut request = self.agent.post(format!("{}{path}", self.base));
        if let Some(value) = &self.authorization {
            request = request.header("Authorization", value);
        }
        // send_json declares `Content-Type: application/json`, which the server requires.
        let response = request.send_json(body).map_err(|e| self.connect(&e))?;
        json(response)
    }

    fn connect(&self, e: &ureq::Error) -> ServerError {
        ServerError::Connect {
            address: self.address.clone(),
            reason: e.to_string(),
        }
    }
}

fn body_error(e: &ureq::Error) -> ServerError {
    ServerError::Body {
        reason: e.to_string(),
    }
}

/// The body of a successful answer, or the server's error message.
fn bytes(mut response: Response<ureq::Body>) -> Result<Vec<u8>, ServerError> {
    let status = response.status().as_u16();
    let body = response
        .body_mut()
        .with_config()
        .limit(u64::MAX)
        .read_to_vec()
        .map_err(|e| body_error(&e))?;
    if status >= 400 {
        let message = serde_json::from_slice::<ErrorReply>(&body)
            .map(|r| r.error)
            .unwrap_or_else(|_| String::from_utf8_lossy(&body).into_owned());
        return Err(ServerError::Status { status, message });
    }
    Ok(body)
}

fn json<T: DeserializeOwned>(response: Response<ureq::Body>) -> Result<T, ServerError> {
    let body = bytes(response)?;
    serde_json::from_slice(&body).map_err(|e| ServerError::Body {
        reason: e.to_string(),
    })
}
