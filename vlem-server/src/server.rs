//! The HTTP side: a loopback listener, a few worker threads, and one handler per endpoint.
//!
//! Every handler turns its failures into an HTTP status with a JSON message; a panic inside one
//! (a bug) is caught and answered with 500, so no request can end the mapping run that owns the
//! live map.

use std::io::{Read, Write};
use std::net::{SocketAddr, ToSocketAddrs};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;

use serde::Serialize;
use tiny_http::{Header, Method, Request, Response, Server, StatusCode};
use vlem_core::BuildContext;
use vlem_core::live::LiveMap;
use vlem_query::QueryError;
use vlem_query::answer::{AnswerOptions, Selection, answer_live};
use vlem_query::grasp::GraspParams;
use vlem_query::heatmap::{gripper_vertices, heatmap_ply};

use crate::api::{ErrorReply, MapStatus, QueryRequest, SnapshotSaved, Status};
use crate::error::ServerError;
use crate::guard::{Access, RequestHead, validate_token};

/// Largest request body accepted (texts and options only).
const MAX_BODY_BYTES: usize = 1 << 20;
/// Worker threads: a slow query (clustering a large map) does not hold up status requests.
const WORKERS: usize = 4;
/// How often an idle worker looks at the stop flag.
const POLL: Duration = Duration::from_millis(100);

/// Where the server resolves things, who may ask it, and how much one request may ask.
#[derive(Clone)]
pub struct ServeOptions {
    /// Folder that `POST /snapshot` writes into (the run's output folder), under names the
    /// server chooses.
    pub out_dir: PathBuf,
    /// Build context for segmenters named in requests.
    pub ctx: BuildContext,
    /// A bearer token every request must carry (`Authorization: Bearer TOKEN`), for users who
    /// reach the port through a tunnel; `None` (the default) serves loopback clients without one.
    pub token: Option<String>,
    /// Bounds on what one request may ask.
    pub limits: RequestLimits,
}

impl ServeOptions {
    /// Options for a run writing into `out_dir`: no token, default limits.
    pub fn new(out_dir: PathBuf, ctx: BuildContext) -> Self {
        Self {
            out_dir,
            ctx,
            token: None,
            limits: RequestLimits::default(),
        }
    }
}

impl std::fmt::Debug for ServeOptions {
    // The token stays out of logs.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ServeOptions")
            .field("out_dir", &self.out_dir)
            .field("token", &self.token.as_ref().map(|_| "<set>"))
            .field("limits", &self.limits)
            .finish_non_exhaustive()
    }
}

/// Bounds on one request: a query's work grows with its texts (one score per map point each), so
/// their number and length are capped; a request over a bound is answered 413 with the bound.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RequestLimits {
    /// Texts in one `POST /query` (default [`RequestLimits::DEFAULT_MAX_TEXTS`]).
    pub max_texts: usize,
    /// Bytes (UTF-8) of one query text or baseline (default
    /// [`RequestLimits::DEFAULT_MAX_TEXT_BYTES`]).
    pub max_text_bytes: usize,
}

impl RequestLimits {
    /// Default texts per query: more than an interactive user types, few enough that one query's
    /// scores stay small (32 × 4 bytes per map point).
    pub const DEFAULT_MAX_TEXTS: usize = 32;
    /// Default bytes per text: a sentence, not a document.
    pub const DEFAULT_MAX_TEXT_BYTES: usize = 256;
}

impl Default for RequestLimits {
    fn default() -> Self {
        Self {
            max_texts: Self::DEFAULT_MAX_TEXTS,
            max_text_bytes: Self::DEFAULT_MAX_TEXT_BYTES,
        }
    }
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
    /// [`ServerError::Address`] for an address that does not parse or is not loopback,
    /// [`ServerError::Option`] for a token or limit that cannot work, [`ServerError::Listen`] when
    /// the port cannot be bound.
    pub fn start(address: &str, live: LiveMap, options: ServeOptions) -> Result<Self, ServerError> {
        let socket = loopback_address(address)?;
        if let Some(token) = &options.token {
            validate_token(token).map_err(|reason| ServerError::Option {
                option: "token",
                reason,
            })?;
        }
        for (option, value) in [
            ("max_texts", options.limits.max_texts),
            ("max_text_bytes", options.limits.max_text_bytes),
        ] {
            if value == 0 {
                return Err(ServerError::Option {
                    option,
                    reason: "must be at least 1".into(),
                });
            }
        }
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
        let access = Access::new(bound.port(), options.token.clone());
        let shared = Arc::new(Handler {
            live,
            options,
            access,
            snapshot_lock: Mutex::new(()),
        });
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

/// A reply's body: bytes in memory, or a stream of known length (a map file encoded while it is
/// sent, so a download never holds the encoded file in memory).
enum Body {
    Bytes(Vec<u8>),
    Stream {
        reader: Box<dyn Read + Send>,
        len: usize,
    },
}

impl From<Vec<u8>> for Body {
    fn from(bytes: Vec<u8>) -> Self {
        Self::Bytes(bytes)
    }
}

/// A reply before it is written: status, content type and body.
struct Reply {
    status: u16,
    content_type: &'static str,
    body: Body,
    file_name: Option<String>,
}

impl Reply {
    fn json(status: u16, value: &impl Serialize) -> Self {
        match serde_json::to_vec(value) {
            Ok(body) => Self {
                status,
                content_type: "application/json",
                body: body.into(),
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
            body: body.into(),
            file_name: None,
        }
    }

    fn binary(body: impl Into<Body>, file_name: String) -> Self {
        Self {
            status: 200,
            content_type: "application/octet-stream",
            body: body.into(),
            file_name: Some(file_name),
        }
    }
}

struct Handler {
    live: LiveMap,
    options: ServeOptions,
    access: Access,
    /// One snapshot at a time: choosing a free file name and writing it is one step, and two
    /// encodings of a large map at once would double the memory a snapshot takes.
    snapshot_lock: Mutex<()>,
}

/// The value of the first header named `name`.
fn header<'a>(request: &'a Request, name: &'static str) -> Option<&'a str> {
    request
        .headers()
        .iter()
        .find(|h| h.field.equiv(name))
        .map(|h| h.value.as_str())
}

impl Handler {
    /// The access checks of [`crate::guard`], before the body is read.
    fn admit(&self, request: &Request) -> Result<(), Reply> {
        let head = RequestHead {
            post: *request.method() == Method::Post,
            host: header(request, "Host"),
            origin: header(request, "Origin"),
            content_type: header(request, "Content-Type"),
            authorization: header(request, "Authorization"),
        };
        self.access
            .check(&head)
            .map_err(|refusal| Reply::error(refusal.status, refusal.message))
    }

    fn respond(&self, mut request: Request) {
        let reply = match self.admit(&request).and_then(|()| read_body(&mut request)) {
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
        let mut headers = Vec::new();
        headers.extend(Header::from_bytes("Content-Type", reply.content_type).ok());
        if let Some(name) = &reply.file_name {
            headers.extend(
                Header::from_bytes(
                    "Content-Disposition",
                    format!("attachment; filename=\"{name}\""),
                )
                .ok(),
            );
        }
        // Only a server with a token answers 401, with its scheme (RFC 6750).
        if reply.status == 401 {
            headers.extend(Header::from_bytes("WWW-Authenticate", "Bearer realm=\"vlem\"").ok());
        }
        let status = StatusCode(reply.status);
        // The client may have gone; nothing to do about it here.
        let _ = match reply.body {
            Body::Bytes(bytes) => {
                let len = bytes.len();
                request.respond(Response::new(
                    status,
                    headers,
                    std::io::Cursor::new(bytes),
                    Some(len),
                    None,
                ))
            }
            Body::Stream { reader, len } => {
                request.respond(Response::new(status, headers, reader, Some(len), None))
            }
        };
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
                device_bytes: view.map.device_memory_bytes(),
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
        if let Err(reply) = self.within_limits(&request.texts, request.baseline.as_deref()) {
            return reply;
        }
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
        if let Err(reply) = self.within_limits(std::slice::from_ref(text), None) {
            return reply;
        }
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

    /// 413 with the bound when a request asks for more texts, or longer ones, than allowed.
    fn within_limits(&self, texts: &[String], baseline: Option<&str>) -> Result<(), Reply> {
        let limits = &self.options.limits;
        if texts.len() > limits.max_texts {
            return Err(Reply::error(
                413,
                format!(
                    "{} query texts in one request; the limit is {} (max_texts; \
                     `vlem run --serve-max-texts N` raises it)",
                    texts.len(),
                    limits.max_texts
                ),
            ));
        }
        let longest = texts
            .iter()
            .map(String::as_str)
            .chain(baseline)
            .map(str::len)
            .max()
            .unwrap_or(0);
        if longest > limits.max_text_bytes {
            return Err(Reply::error(
                413,
                format!(
                    "a query text of {longest} bytes; the limit is {} bytes per text \
                     (max_text_bytes; `vlem run --serve-max-text-bytes N` raises it)",
                    limits.max_text_bytes
                ),
            ));
        }
        Ok(())
    }

    /// `POST /snapshot`: the map as it is, saved into the run's output folder under the next free
    /// name `snapshot-NNNN.vlem`. The request names no path: a file path from the network could
    /// replace any file the server's user can write.
    fn snapshot(&self, body: &[u8]) -> Reply {
        if !body.iter().all(u8::is_ascii_whitespace) {
            match serde_json::from_slice::<serde_json::Value>(body) {
                Ok(serde_json::Value::Object(fields)) if fields.is_empty() => {}
                Ok(serde_json::Value::Object(fields)) => {
                    let names: Vec<&str> = fields.keys().map(String::as_str).collect();
                    return Reply::error(
                        400,
                        format!(
                            "POST /snapshot takes no options (got {}): the server saves into the \
                             run's output folder under a name it chooses (snapshot-NNNN.vlem) and \
                             answers with it; GET /map.vlem downloads the map instead",
                            names.join(", ")
                        ),
                    );
                }
                Ok(_) => return Reply::error(400, "bad snapshot request: expected {} or nothing"),
                Err(e) => return Reply::error(400, format!("bad snapshot request: {e}")),
            }
        }
        let _one_at_a_time = self
            .snapshot_lock
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let Some(name) = free_snapshot_name(&self.options.out_dir) else {
            return Reply::error(
                507,
                format!(
                    "{} holds {MAX_SNAPSHOTS} snapshots already; move them away to take more",
                    self.options.out_dir.display()
                ),
            );
        };
        let path = self.options.out_dir.join(&name);
        match self.live.save(&path) {
            Ok(saved) => Reply::json(
                200,
                &SnapshotSaved {
                    path: path.display().to_string(),
                    file: name,
                    points: saved.points,
                    frames_integrated: saved.frames_integrated,
                    bytes: saved.bytes,
                },
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
        match stream_map_file(snapshot) {
            Ok(body) => Reply::binary(body, "map.vlem".into()),
            Err(e) => Reply::error(500, e.to_string()),
        }
    }
}

/// The map file of `snapshot` as a stream: a thread encodes it into a pipe while the response
/// reads the other end, so a download holds the snapshot (one copy of the map, taken under the
/// read lock) and a pipe's buffer, never the encoded file. A client that goes away closes the
/// pipe, which ends the encoding thread.
fn stream_map_file(snapshot: vlem_core::MapSnapshot) -> vlem_core::Result<Body> {
    let len = vlem_core::mapfile::map_file_len(&snapshot)?;
    let len = usize::try_from(len).map_err(|_| vlem_core::CoreError::MapFile {
        path: "map.vlem".into(),
        reason: "larger than this platform can address".into(),
    })?;
    let (reader, writer) =
        std::io::pipe().map_err(|e| vlem_core::CoreError::io("(map download pipe)", e))?;
    std::thread::Builder::new()
        .name("vlem-map-download".into())
        .spawn(move || {
            let writer = std::io::BufWriter::with_capacity(1 << 16, writer);
            // A failed write is the client leaving; the response side reports nothing more.
            if let Ok(mut writer) = vlem_core::mapfile::write_map_to(writer, &snapshot) {
                let _ = writer.flush();
            }
        })
        .map_err(|e| vlem_core::CoreError::io("(map download thread)", e))?;
    Ok(Body::Stream {
        reader: Box::new(reader),
        len,
    })
}

/// Snapshots one output folder takes (`snapshot-0001.vlem` … `snapshot-9999.vlem`).
const MAX_SNAPSHOTS: u32 = 9999;

/// The first `snapshot-NNNN.vlem` that does not exist in `dir` (nothing is ever replaced, so
/// snapshots of an earlier run into the same folder stay); `None` when all are taken.
fn free_snapshot_name(dir: &std::path::Path) -> Option<String> {
    (1..=MAX_SNAPSHOTS)
        .map(|n| format!("snapshot-{n:04}.vlem"))
        .find(|name| {
            // A dangling symlink is taken too: saving would follow it.
            std::fs::symlink_metadata(dir.join(name)).is_err()
        })
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
    fn snapshot_names_skip_existing_files() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(
            free_snapshot_name(dir.path()).as_deref(),
            Some("snapshot-0001.vlem")
        );
        std::fs::write(dir.path().join("snapshot-0001.vlem"), b"x").unwrap();
        std::fs::create_dir(dir.path().join("snapshot-0002.vlem")).unwrap();
        assert_eq!(
            free_snapshot_name(dir.path()).as_deref(),
            Some("snapshot-0003.vlem")
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
