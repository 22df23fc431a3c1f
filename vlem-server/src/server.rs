//! The HTTP side: a loopback listener, a few worker threads, and one handler per endpoint.
//!
//! Every handler turns its failures into an HTTP status with a JSON message; a panic inside one
//! (a bug) is caught and answered with 500, so no request can end the mapping run that owns the
//! live map.

use std::io::Read;
use std::net::{SocketAddr, ToSocketAddrs};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

use serde::Serialize;
use tiny_http::{Header, Method, Request, Response, Server};
use vlem_core::BuildContext;
use vlem_core::live::LiveMap;
use vlem_query::QueryError;
use vlem_query::answer::{AnswerOptions, Selection, answer_live};
use vlem_query::grasp::GraspParams;
use vlem_query::heatmap::{gripper_vertices, heatmap_ply};

use crate::api::{ErrorReply, MapStatus, QueryRequest, SnapshotRequest, Status};
use crate::error::ServerError;

/// Largest request body accepted (texts and options only).
const MAX_BODY_BYTES: usize = 1 << 20;
/// Worker threads: a slow query (clustering a large map) does not hold up status requests.
const WORKERS: usize = 4;
/// How often an idle worker looks at the stop flag.
const POLL: Duration = Duration::from_millis(100);

/// Where the server resolves things.
#[derive(Clone, Debug)]
pub struct ServeOptions {
    /// Folder that relative snapshot paths are taken from (the run's output folder).
    pub out_dir: PathBuf,
    /// Build context for segmenters named in requests.
    pub ctx: BuildContext,
}

/// A running query server; dropping it (or [`QueryServer::shutdown`]) stops it.
pub struct QueryServer {
    address: SocketAddr,
    stop: Arc<AtomicBool>,
    workers: Vec<JoinHandle<()>>,
}

impl QueryServer {
    /// Starts serving `live` on `address` (a loopback address such as `127.0.0.1:8765`; port 0
    /// picks a free port, see [`QueryServer::address`]).
    ///
    /// # Errors
    /// [`ServerError::Address`] for an address that does not parse or is not loopback (the server
    /// has no authentication), [`ServerError::Listen`] when the port cannot be bound.
    pub fn start(address: &str, live: LiveMap, options: ServeOptions) -> Result<Self, ServerError> {
        let socket = loopback_address(address)?;
        let server = Server::http(socket).map_err(|e| ServerError::Listen {
            address: address.into(),
            reason: e.to_string(),
        })?;
        let bound = server
            .server_addr()
            .to_ip()
            .ok_or_else(|| ServerError::Listen {
                address: address.into(),
                reason: "not an IP socket".into(),
            })?;
        let server = Arc::new(server);
        let stop = Arc::new(AtomicBool::new(false));
        let shared = Arc::new(Handler { live, options });
        let workers = (0..WORKERS)
            .map(|_| {
                let (server, stop, handler) = (server.clone(), stop.clone(), shared.clone());
                std::thread::spawn(move || serve(&server, &stop, &handler))
            })
            .collect();
        Ok(Self {
            address: bound,
            stop,
            workers,
        })
    }

    /// The address the server listens on.
    pub fn address(&self) -> SocketAddr {
        self.address
    }

    /// Blocks until the server is stopped (it is only stopped by [`QueryServer::shutdown`] from
    /// another owner, so in practice this serves until the process ends).
    pub fn wait(mut self) {
        for worker in self.workers.drain(..) {
            let _ = worker.join();
        }
    }

    /// Stops accepting requests, lets the ones in flight finish, and joins the workers.
    pub fn shutdown(mut self) {
        self.stop_workers();
    }

    fn stop_workers(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for worker in self.workers.drain(..) {
            let _ = worker.join();
        }
    }
}

impl Drop for QueryServer {
    fn drop(&mut self) {
        self.stop_workers();
    }
}

fn loopback_address(address: &str) -> Result<SocketAddr, ServerError> {
    let bad = |reason: &str| ServerError::Address {
        address: address.into(),
        reason: reason.into(),
    };
    let socket = address
        .to_socket_addrs()
        .map_err(|e| bad(&format!("not a host:port address ({e})")))?
        .next()
        .ok_or_else(|| bad("the name resolves to no address"))?;
    if !socket.ip().is_loopback() {
        return Err(bad(
            "the query server has no authentication, so it listens on loopback only \
             (127.0.0.1:PORT or [::1]:PORT)",
        ));
    }
    Ok(socket)
}

fn serve(server: &Server, stop: &AtomicBool, handler: &Handler) {
    while !stop.load(Ordering::Relaxed) {
        match server.recv_timeout(POLL) {
            Ok(Some(request)) => handler.respond(request),
            Ok(None) => {}
            // A broken connection concerns that client only.
            Err(_) => {}
        }
    }
}

/// A reply before it is written: status, content type and body.
struct Reply {
    status: u16,
    content_type: &'static str,
    body: Vec<u8>,
    file_name: Option<String>,
}

impl Reply {
    fn json(status: u16, value: &impl Serialize) -> Self {
        match serde_json::to_vec(value) {
            Ok(body) => Self {
                status,
                content_type: "application/json",
                body,
                file_name: None,
            },
            Err(e) => Self::error(500, format!("cannot encode the answer: {e}")),
        }
    }

    fn error(status: u16, message: impl Into<String>) -> Self {
        let body = serde_json::to_vec(&ErrorReply {
            error: message.into(),
        })
        .unwrap_or_default();
        Self {
            status,
            content_type: "application/json",
            body,
            file_name: None,
        }
    }

    fn binary(body: Vec<u8>, file_name: String) -> Self {
        Self {
            status: 200,
            content_type: "application/octet-stream",
            body,
            file_name: Some(file_name),
        }
    }
}

struct Handler {
    live: LiveMap,
    options: ServeOptions,
}

impl Handler {
    fn respond(&self, mut request: Request) {
        let reply = match read_body(&mut request) {
            Ok(body) => {
                let (method, url) = (request.method().clone(), request.url().to_owned());
                catch_unwind(AssertUnwindSafe(|| self.route(&method, &url, &body))).unwrap_or_else(
                    |_| {
                        Reply::error(
                            500,
                            "the server failed on this request (a bug: please report it)",
                        )
                    },
                )
            }
            Err(reply) => reply,
        };
        let mut response = Response::from_data(reply.body).with_status_code(reply.status);
        if let Ok(h) = Header::from_bytes("Content-Type", reply.content_type) {
            response.add_header(h);
        }
        if let Some(name) = reply.file_name
            && let Ok(h) = Header::from_bytes(
                "Content-Disposition",
                format!("attachment; filename=\"{name}\""),
            )
        {
            response.add_header(h);
        }
        // The client may have gone; nothing to do about it here.
        let _ = request.respond(response);
    }

    fn route(&self, method: &Method, url: &str, body: &[u8]) -> Reply {
        let (path, query) = url.split_once('?').unwrap_or((url, ""));
        match (method, path) {
            (Method::Get, "/status") => self.status(),
            (Method::Post, "/query") => self.query(body),
            (Method::Get, "/heatmap.ply") => self.heatmap(query),
            (Method::Post, "/snapshot") => self.snapshot(body),
            (Method::Get, "/map.vlem") => self.map_file(),
            (_, "/status" | "/query" | "/heatmap.ply" | "/snapshot" | "/map.vlem") => {
                Reply::error(405, format!("{method} is not allowed on {path}"))
            }
            _ => Reply::error(
                404,
                format!(
                    "no endpoint {path}: GET /status, POST /query, GET /heatmap.ply?text=..., \
                     POST /snapshot, GET /map.vlem"
                ),
            ),
        }
    }

    fn status(&self) -> Reply {
        let map = self
            .live
            .read(|view| MapStatus {
                kind: view.map.name().into(),
                points: view.map.len(),
                dim: view.map.dim(),
                bytes: view.map.memory_bytes(),
                frames_integrated: view.frames_integrated,
            })
            .ok();
        Reply::json(
            200,
            &Status {
                run: self.live.status(),
                map,
                encoder: self.live.encoder().map(|e| e.name().to_owned()),
            },
        )
    }

    fn query(&self, body: &[u8]) -> Reply {
        let request: QueryRequest = match serde_json::from_slice(body) {
            Ok(r) => r,
            Err(e) => return Reply::error(400, format!("bad query request: {e}")),
        };
        let selection = Selection {
            segmenter: request
                .segmenter
                .clone()
                .unwrap_or_else(|| Selection::threshold().segmenter),
            threshold: request.threshold,
            baseline: request.baseline.clone(),
        };
        let segmenter = match selection.build(&self.options.ctx) {
            Ok(s) => s,
            Err(e) => return Reply::error(400, e.to_string()),
        };
        let options = AnswerOptions {
            grasp: request.grasp.then(GraspParams::default),
            indices: request.indices,
        };
        match answer_live(&self.live, segmenter.as_ref(), &request.texts, &options) {
            Ok((answered, _)) => Reply::json(200, &answered.answer),
            Err(e) => query_error(&e),
        }
    }

    fn heatmap(&self, query: &str) -> Reply {
        let params = form_params(query);
        let texts: Vec<String> = params
            .iter()
            .filter(|(k, _)| k == "text")
            .map(|(_, v)| v.clone())
            .collect();
        let [text] = texts.as_slice() else {
            return Reply::error(400, "give exactly one text: /heatmap.ply?text=mug");
        };
        let grasp = params
            .iter()
            .any(|(k, v)| k == "grasp" && v != "0" && v != "false");
        let segmenter = match Selection::threshold().build(&self.options.ctx) {
            Ok(s) => s,
            Err(e) => return Reply::error(500, e.to_string()),
        };
        let options = AnswerOptions {
            grasp: grasp.then(GraspParams::default),
            indices: false,
        };
        match answer_live(
            &self.live,
            segmenter.as_ref(),
            std::slice::from_ref(text),
            &options,
        ) {
            Ok((answered, positions)) => {
                let markers = answered
                    .grasps
                    .first()
                    .and_then(Option::as_ref)
                    .map(gripper_vertices)
                    .unwrap_or_default();
                let scores = answered
                    .scores
                    .scores
                    .first()
                    .map_or(&[][..], Vec::as_slice);
                Reply::binary(
                    heatmap_ply(&positions, scores, &markers),
                    format!("heat-{}.ply", vlem_query::answer::slug(text)),
                )
            }
            Err(e) => query_error(&e),
        }
    }

    fn snapshot(&self, body: &[u8]) -> Reply {
        let request: SnapshotRequest = if body.iter().all(u8::is_ascii_whitespace) {
            SnapshotRequest::default()
        } else {
            match serde_json::from_slice(body) {
                Ok(r) => r,
                Err(e) => return Reply::error(400, format!("bad snapshot request: {e}")),
            }
        };
        let path = match &request.path {
            Some(p) if Path::new(p).is_absolute() => PathBuf::from(p),
            Some(p) => self.options.out_dir.join(p),
            None => self.options.out_dir.join("snapshot.vlem"),
        };
        match self.live.save(&path) {
            Ok(saved) => Reply::json(
                200,
                &serde_json::json!({
                    "path": path.display().to_string(),
                    "points": saved.points,
                    "frames_integrated": saved.frames_integrated,
                    "bytes": saved.bytes,
                }),
            ),
            Err(vlem_core::CoreError::MissingStage { message }) => Reply::error(409, message),
            Err(e) => Reply::error(500, e.to_string()),
        }
    }

    fn map_file(&self) -> Reply {
        let snapshot = match self.live.snapshot() {
            Ok(s) => s,
            Err(vlem_core::CoreError::MissingStage { message }) => {
                return Reply::error(409, message);
            }
            Err(e) => return Reply::error(500, e.to_string()),
        };
        match vlem_core::mapfile::map_file_bytes(&snapshot) {
            Ok(bytes) => Reply::binary(bytes, "map.vlem".into()),
            Err(e) => Reply::error(500, e.to_string()),
        }
    }
}

/// The status a query failure gets: the client's fault (4xx) unless the server broke.
fn query_error(e: &QueryError) -> Reply {
    let status = match e {
        QueryError::NoTexts | QueryError::InvalidParameter { .. } => 400,
        QueryError::GeometryOnly { .. } | QueryError::EncoderDimension { .. } => 409,
        QueryError::Embed { .. } | QueryError::Baseline { .. } => 422,
        QueryError::Core(vlem_core::CoreError::MissingStage { .. }) => 409,
        _ => 500,
    };
    Reply::error(status, e.to_string())
}

fn read_body(request: &mut Request) -> Result<Vec<u8>, Reply> {
    if request.body_length().is_some_and(|n| n > MAX_BODY_BYTES) {
        return Err(Reply::error(
            413,
            format!("request bodies are limited to {MAX_BODY_BYTES} bytes"),
        ));
    }
    let mut body = Vec::new();
    request
        .as_reader()
        .take(MAX_BODY_BYTES as u64 + 1)
        .read_to_end(&mut body)
        .map_err(|e| Reply::error(400, format!("cannot read the request body: {e}")))?;
    if body.len() > MAX_BODY_BYTES {
        return Err(Reply::error(
            413,
            format!("request bodies are limited to {MAX_BODY_BYTES} bytes"),
        ));
    }
    Ok(body)
}

/// `a=1&b=two+words` → pairs, percent-decoded.
fn form_params(query: &str) -> Vec<(String, String)> {
    query
        .split('&')
        .filter(|pair| !pair.is_empty())
        .map(|pair| {
            let (k, v) = pair.split_once('=').unwrap_or((pair, ""));
            (percent_decode(k), percent_decode(v))
        })
        .collect()
}

fn percent_decode(text: &str) -> String {
    let bytes = text.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        match bytes[i] {
            b'+' => out.push(b' '),
            b'%' if i + 2 < bytes.len() => {
                let hex = std::str::from_utf8(&bytes[i + 1..i + 3]).ok();
                match hex.and_then(|h| u8::from_str_radix(h, 16).ok()) {
                    Some(b) => {
                        out.push(b);
                        i += 2;
                    }
                    None => out.push(b'%'),
                }
            }
            b => out.push(b),
        }
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn form_parameters_are_percent_decoded() {
        assert_eq!(
            form_params("text=coffee+machine&grasp=1&x=%E2%9C%93&bad=%zz&end=%4"),
            vec![
                ("text".into(), "coffee machine".into()),
                ("grasp".into(), "1".into()),
                ("x".into(), "✓".into()),
                ("bad".into(), "%zz".into()),
                ("end".into(), "%4".into()),
            ]
        );
    }

    #[test]
    fn only_loopback_addresses_are_served() {
        assert!(loopback_address("127.0.0.1:0").is_ok());
        assert!(loopback_address("[::1]:0").is_ok());
        let err = loopback_address("0.0.0.0:8080").unwrap_err().to_string();
        assert!(err.contains("loopback only"), "{err}");
        assert!(loopback_address("not an address").is_err());
    }
}
