//! The server: a loopback listener, a thread per connection (at most [`MAX_CONNECTIONS`]), and
//! one handler per endpoint.
//!
//! Why it is shaped this way: every request is a blocking pass over the map or a status line, so
//! threads fit better than an async runtime; what makes it safe to leave running beside a
//! mapping run for hours is that every resource is bounded:
//! - connections: at most [`MAX_CONNECTIONS`]; one more is answered 503 by the accept loop itself,
//!   which never exits on an error (a full file table only pauses it) and never waits on a
//!   refused client (one thread closes those, [`crate::http::Closer`]);
//! - each connection's reads and writes: sizes and timeouts in [`crate::http`];
//! - the map work: at most [`WORK_SLOTS`] queries, heatmaps and snapshots at once (more wait up to
//!   [`WORK_WAIT`], then 503), and at most [`DOWNLOADS`] map downloads at once, each holding one
//!   snapshot (more get 503 at once);
//! - `/status` reads copies of the counters and the map's size, never the map's lock, so it
//!   answers at once under any query load.
//!
//! Every handler turns its failures into an HTTP status with a JSON message; a panic inside one
//! (a bug) is caught and answered with 500, so no request can end the mapping run that owns the
//! live map.

use std::collections::HashMap;
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serde::Serialize;
use vlem_core::live::LiveMap;
use vlem_core::{BuildContext, message_chain};
use vlem_query::QueryError;
use vlem_query::answer::{AnswerOptions, Selection, answer_live};
use vlem_query::grasp::GraspParams;
use vlem_query::heatmap::{gripper_vertices, heatmap_ply};

use crate::api::{ErrorReply, MapStatus, QueryRequest, SnapshotSaved, Status};
use crate::error::ServerError;
use crate::guard::{Access, RequestHead, validate_token};
use crate::http::{Closer, Connection, Head, Limits, ReadError};

/// Open connections; one more is answered 503. Each costs a thread and at most a few tens of KiB
/// of buffers, so the cap keeps a flood of idle connections (which once exhausted the threads of
/// the process and killed the old server's accept loop) from touching the mapping run.
pub(crate) const MAX_CONNECTIONS: usize = 64;
/// Queries, heatmaps and snapshots served at once: each is a pass over the map (and a snapshot a
/// copy of it), so more at once would only share the same cores and memory.
pub(crate) const WORK_SLOTS: usize = 4;
/// How long a request waits for a work slot before it is answered 503.
pub(crate) const WORK_WAIT: Duration = Duration::from_secs(30);
/// Map downloads at once; each holds one snapshot of the map (its size in `/status` `map.bytes`)
/// while it is sent.
pub(crate) const DOWNLOADS: usize = 2;
/// How long [`QueryServer::shutdown`] lets answers in flight finish before it closes their
/// connections.
const GRACE: Duration = Duration::from_secs(5);
/// How long the accept loop pauses after a failed accept (a full file table, say).
const ACCEPT_BACKOFF: Duration = Duration::from_millis(50);

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
    shared: Arc<Shared>,
    accept: Option<JoinHandle<()>>,
}

/// What the accept loop and the connection threads share.
struct Shared {
    handler: Handler,
    stop: AtomicBool,
    /// Open connections by id (a second handle on each socket, to close it on shutdown).
    open: Mutex<HashMap<u64, TcpStream>>,
    /// Signalled when a connection closes.
    closed: Condvar,
    next_id: AtomicU64,
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
        let listen_error = |e: std::io::Error| ServerError::Listen {
            address: address.into(),
            reason: if e.kind() == std::io::ErrorKind::AddrInUse {
                format!(
                    "{e}: another program listens on that port; choose another, or port 0 for a \
                     free one (the address is printed when serving starts)"
                )
            } else {
                e.to_string()
            },
        };
        let listener = TcpListener::bind(socket).map_err(listen_error)?;
        let bound = listener.local_addr().map_err(listen_error)?;
        let access = Access::new(bound.port(), options.token.clone());
        let shared = Arc::new(Shared {
            handler: Handler {
                live,
                options,
                access,
                snapshot_lock: Mutex::new(()),
                work: Arc::new(Slots::new(WORK_SLOTS)),
                downloads: Arc::new(Slots::new(DOWNLOADS)),
            },
            stop: AtomicBool::new(false),
            open: Mutex::new(HashMap::new()),
            closed: Condvar::new(),
            next_id: AtomicU64::new(0),
        });
        let closer = Closer::start(Limits::SERVER).map_err(listen_error)?;
        let accept = std::thread::Builder::new()
            .name("vlem-http-accept".into())
            .spawn({
                let shared = shared.clone();
                move || accept_loop(&listener, &shared, &closer)
            })
            .map_err(listen_error)?;
        Ok(Self {
            address: bound,
            shared,
            accept: Some(accept),
        })
    }

    /// The address the server listens on.
    pub fn address(&self) -> SocketAddr {
        self.address
    }

    /// Blocks until the server is stopped (it is only stopped by [`QueryServer::shutdown`] from
    /// another owner, so in practice this serves until the process ends).
    pub fn wait(mut self) {
        if let Some(accept) = self.accept.take() {
            let _ = accept.join();
        }
    }

    /// Stops accepting connections, lets the answers in flight finish (for up to 5 s), and
    /// closes every connection: idle keep-alive connections and requests whose bodies never
    /// come end at once, so a stalled client cannot keep the process from exiting.
    pub fn shutdown(mut self) {
        self.stop();
    }

    fn stop(&mut self) {
        let Some(accept) = self.accept.take() else {
            return;
        };
        self.shared.stop.store(true, Ordering::SeqCst);
        // The accept loop blocks in accept(): one connection wakes it to see the flag. If even
        // that cannot connect (no file descriptors left), the loop is left to end with the
        // process rather than joined.
        if TcpStream::connect_timeout(&self.address, Duration::from_secs(1)).is_ok() {
            let _ = accept.join();
        }
        // Reads end now (idle connections, stalled bodies); answers being written go on.
        for stream in lock(&self.shared.open).values() {
            let _ = stream.shutdown(std::net::Shutdown::Read);
        }
        let deadline = Instant::now() + GRACE;
        let mut open = lock(&self.shared.open);
        while !open.is_empty() {
            let Some(left) = deadline.checked_duration_since(Instant::now()) else {
                break;
            };
            open = self
                .shared
                .closed
                .wait_timeout(open, left)
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
        for stream in open.values() {
            let _ = stream.shutdown(std::net::Shutdown::Both);
        }
    }
}

impl Drop for QueryServer {
    fn drop(&mut self) {
        self.stop();
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

/// A plain counter's mutex: a panic elsewhere leaves nothing half-changed, so a poisoned lock is
/// still used.
fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Accepts connections until the server stops. Nothing ends it early: a failed accept (a full
/// file table) pauses it briefly, and a connection it cannot take (the cap, or no thread) is
/// answered 503 and handed to `closer`.
fn accept_loop(listener: &TcpListener, shared: &Arc<Shared>, closer: &Closer) {
    loop {
        let accepted = listener.accept();
        if shared.stop.load(Ordering::SeqCst) {
            return;
        }
        let Ok((stream, _peer)) = accepted else {
            std::thread::sleep(ACCEPT_BACKOFF);
            continue;
        };
        let id = shared.next_id.fetch_add(1, Ordering::Relaxed);
        {
            let mut open = lock(&shared.open);
            if open.len() >= MAX_CONNECTIONS {
                drop(open);
                refuse_busy(
                    closer,
                    stream,
                    &format!(
                        "the server has {MAX_CONNECTIONS} open connections, its limit; close idle \
                         ones or try again"
                    ),
                );
                continue;
            }
            let Ok(handle) = stream.try_clone() else {
                continue;
            };
            open.insert(id, handle);
        }
        let spawned = std::thread::Builder::new().name("vlem-http".into()).spawn({
            let shared = shared.clone();
            move || {
                // A bug on one connection must not keep its place under the cap.
                let _ = catch_unwind(AssertUnwindSafe(|| serve_connection(&shared, stream)));
                lock(&shared.open).remove(&id);
                shared.closed.notify_all();
            }
        });
        if spawned.is_err()
            && let Some(stream) = lock(&shared.open).remove(&id)
        {
            refuse_busy(
                closer,
                stream,
                "the server cannot start a thread for this connection",
            );
        }
    }
}

/// Answers 503 on a connection that will not be served, without waiting for the client: the
/// answer fits the empty socket's send buffer, and `closer` closes the connection without losing
/// it (the client may have sent its request already).
fn refuse_busy(closer: &Closer, stream: TcpStream, message: &str) {
    let body = error_body(message);
    let answer = format!(
        "HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\nRetry-After: 1\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    let mut stream = stream;
    if stream.set_nonblocking(true).is_ok() {
        let _ = stream.write_all(answer.as_bytes());
        let _ = stream.write_all(&body);
    }
    closer.close(stream);
}

/// One connection's requests, in turn, until it closes, fails, or the server stops.
fn serve_connection(shared: &Shared, stream: TcpStream) {
    let mut connection = Connection::new(stream, Limits::SERVER);
    while !shared.stop.load(Ordering::SeqCst) {
        let (reply, keep_alive, send_body) = match connection.read_head() {
            Ok(head) => {
                let (reply, keep_alive) = shared.handler.answer(&mut connection, &head);
                // The answer to HEAD has the headers of a body it does not carry.
                (reply, keep_alive, head.method != "HEAD")
            }
            Err(ReadError::Closed) => return,
            Err(ReadError::Refuse { status, message }) => {
                (Reply::error(status, message), false, true)
            }
        };
        let keep_alive = keep_alive && !shared.stop.load(Ordering::SeqCst);
        if write_reply(&mut connection, reply, send_body, !keep_alive).is_err() {
            return;
        }
        if !keep_alive {
            // The peer may still be sending (the rest of a refused head or body): a plain drop
            // would reset the connection and could take the answer with it.
            connection.close();
            return;
        }
    }
}

fn write_reply(
    connection: &mut Connection,
    reply: Reply,
    send_body: bool,
    close: bool,
) -> std::io::Result<()> {
    let mut headers = vec![("Content-Type", reply.content_type.to_owned())];
    if let Some(allow) = reply.allow {
        headers.push(("Allow", allow.to_owned()));
    }
    if let Some(name) = &reply.file_name {
        headers.push((
            "Content-Disposition",
            format!("attachment; filename=\"{name}\""),
        ));
    }
    // Only a server with a token answers 401, with its scheme (RFC 6750).
    if reply.status == 401 {
        headers.push(("WWW-Authenticate", "Bearer realm=\"vlem\"".into()));
    }
    if reply.status == 503 {
        headers.push(("Retry-After", "1".into()));
    }
    match reply.body {
        Body::Bytes(bytes) => connection.write_answer(
            reply.status,
            &headers,
            &mut bytes.as_slice(),
            bytes.len() as u64,
            send_body,
            close,
        ),
        Body::Stream { mut reader, len } => {
            connection.write_answer(reply.status, &headers, &mut reader, len, send_body, close)
        }
    }
}

/// A counting semaphore for the map work.
struct Slots {
    free: Mutex<usize>,
    released: Condvar,
}

/// A taken slot, given back on drop.
struct Slot(Arc<Slots>);

impl Drop for Slot {
    fn drop(&mut self) {
        *lock(&self.0.free) += 1;
        self.0.released.notify_one();
    }
}

impl Slots {
    fn new(count: usize) -> Self {
        Self {
            free: Mutex::new(count),
            released: Condvar::new(),
        }
    }

    /// A slot, waiting up to `wait` for one.
    fn take(self: &Arc<Self>, wait: Duration) -> Option<Slot> {
        let deadline = Instant::now() + wait;
        let mut free = lock(&self.free);
        while *free == 0 {
            let left = deadline.checked_duration_since(Instant::now())?;
            free = self
                .released
                .wait_timeout(free, left)
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
        *free -= 1;
        Some(Slot(self.clone()))
    }
}

/// A reply's body: bytes in memory, or a stream of known length (a map file encoded while it is
/// sent, so a download never holds the encoded file in memory).
enum Body {
    Bytes(Vec<u8>),
    Stream {
        reader: Box<dyn Read + Send>,
        len: u64,
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
    /// The methods a 405 names (RFC 9110 asks for them).
    allow: Option<&'static str>,
}

fn error_body(message: &str) -> Vec<u8> {
    serde_json::to_vec(&ErrorReply {
        error: message.into(),
    })
    .unwrap_or_default()
}

impl Reply {
    fn json(status: u16, value: &impl Serialize) -> Self {
        match serde_json::to_vec(value) {
            Ok(body) => Self {
                status,
                content_type: "application/json",
                body: body.into(),
                file_name: None,
                allow: None,
            },
            Err(e) => Self::error(500, format!("cannot encode the answer: {e}")),
        }
    }

    fn error(status: u16, message: impl Into<String>) -> Self {
        Self {
            status,
            content_type: "application/json",
            body: error_body(&message.into()).into(),
            file_name: None,
            allow: None,
        }
    }

    fn binary(body: impl Into<Body>, file_name: String) -> Self {
        Self {
            status: 200,
            content_type: "application/octet-stream",
            body: body.into(),
            file_name: Some(file_name),
            allow: None,
        }
    }

    fn busy(what: &str) -> Self {
        Self::error(503, format!("the server is busy: {what}; try again"))
    }
}

struct Handler {
    live: LiveMap,
    options: ServeOptions,
    access: Access,
    /// One snapshot at a time: choosing a free file name and writing it is one step, and two
    /// encodings of a large map at once would double the memory a snapshot takes.
    snapshot_lock: Mutex<()>,
    /// Queries, heatmaps and snapshots running.
    work: Arc<Slots>,
    /// Map downloads being sent.
    downloads: Arc<Slots>,
}

impl Handler {
    /// The access checks of [`crate::guard`], before the body is read.
    fn admit(&self, head: &Head) -> Result<(), Reply> {
        let request = RequestHead {
            post: head.method == "POST",
            host: head.header("Host"),
            origin: head.header("Origin"),
            content_type: head.header("Content-Type"),
            authorization: head.header("Authorization"),
        };
        self.access
            .check(&request)
            .map_err(|refusal| Reply::error(refusal.status, refusal.message))
    }

    /// The reply to one request, and whether the connection may stay open after it (not when a
    /// refused request's body is left unread).
    fn answer(&self, connection: &mut Connection, head: &Head) -> (Reply, bool) {
        if let Err(reply) = self.admit(head) {
            return (reply, head.keep_alive && !head.has_body());
        }
        let body = match connection.read_body(head) {
            Ok(body) => body,
            Err(ReadError::Closed) => return (Reply::error(400, "the body did not arrive"), false),
            Err(ReadError::Refuse { status, message }) => {
                return (Reply::error(status, message), false);
            }
        };
        let reply = catch_unwind(AssertUnwindSafe(|| {
            self.route(&head.method, &head.target, &body)
        }))
        .unwrap_or_else(|_| {
            Reply::error(
                500,
                "the server failed on this request (a bug: please report it)",
            )
        });
        (reply, head.keep_alive)
    }

    fn route(&self, method: &str, url: &str, body: &[u8]) -> Reply {
        let (path, query) = url.split_once('?').unwrap_or((url, ""));
        match (method, path) {
            ("GET", "/status") => self.status(),
            ("POST", "/query") => self.with_work_slot(|| self.query(body)),
            ("GET", "/heatmap.ply") => self.with_work_slot(|| self.heatmap(query)),
            ("POST", "/snapshot") => self.with_work_slot(|| self.snapshot(body)),
            ("GET", "/map.vlem") => self.map_file(),
            (_, "/status" | "/heatmap.ply" | "/map.vlem") => Reply {
                allow: Some("GET"),
                ..Reply::error(405, format!("{method} is not allowed on {path}; use GET"))
            },
            (_, "/query" | "/snapshot") => Reply {
                allow: Some("POST"),
                ..Reply::error(405, format!("{method} is not allowed on {path}; use POST"))
            },
            _ => Reply::error(
                404,
                format!(
                    "no endpoint {path}: GET /status, POST /query, GET /heatmap.ply?text=..., \
                     POST /snapshot, GET /map.vlem"
                ),
            ),
        }
    }

    /// Runs `work` (a pass over the map) in one of the [`WORK_SLOTS`], or answers 503 when none
    /// frees up within [`WORK_WAIT`].
    fn with_work_slot(&self, work: impl FnOnce() -> Reply) -> Reply {
        match self.work.take(WORK_WAIT) {
            Some(_slot) => work(),
            None => Reply::busy(&format!(
                "{WORK_SLOTS} queries, heatmaps or snapshots are running and none finished \
                 within {} s",
                WORK_WAIT.as_secs()
            )),
        }
    }

    /// `GET /status`: copies of the counters and the map's size, never the map's lock, so it
    /// answers at once whatever queries are running.
    fn status(&self) -> Reply {
        let map = self.live.summary().map(|summary| MapStatus {
            kind: summary.kind,
            points: summary.points,
            dim: summary.dim,
            bytes: summary.host_bytes,
            device_bytes: summary.device_bytes,
            frames_integrated: summary.frames_integrated,
        });
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
            Err(e) => return Reply::error(400, message_chain(&e)),
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
            Err(e) => return Reply::error(500, message_chain(&e)),
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
            Err(e) => Reply::error(500, message_chain(&e)),
        }
    }

    /// `GET /map.vlem`: one of the [`DOWNLOADS`] slots (503 at once when all are taken, since
    /// a download lasts as long as its client reads), held until the file is sent.
    fn map_file(&self) -> Reply {
        let Some(slot) = self.downloads.take(Duration::ZERO) else {
            return Reply::busy(&format!("{DOWNLOADS} map downloads are being sent"));
        };
        let snapshot = match self.live.snapshot() {
            Ok(s) => s,
            Err(vlem_core::CoreError::MissingStage { message }) => {
                return Reply::error(409, message);
            }
            Err(e) => return Reply::error(500, message_chain(&e)),
        };
        match stream_map_file(snapshot, slot) {
            Ok(body) => Reply::binary(body, "map.vlem".into()),
            Err(e) => Reply::error(500, message_chain(&e)),
        }
    }
}

/// The map file of `snapshot` as a stream: a thread encodes it into a pipe while the response
/// reads the other end, so a download holds the snapshot (one copy of the map, taken under the
/// read lock) and a pipe's buffer, never the encoded file. A client that goes away closes the
/// pipe, which ends the encoding thread.
fn stream_map_file(snapshot: vlem_core::MapSnapshot, slot: Slot) -> vlem_core::Result<Body> {
    let len = vlem_core::mapfile::map_file_len(&snapshot)?;
    let (reader, writer) =
        std::io::pipe().map_err(|e| vlem_core::CoreError::io("(map download pipe)", e))?;
    std::thread::Builder::new()
        .name("vlem-map-download".into())
        .spawn(move || {
            let writer = std::io::BufWriter::with_capacity(1 << 16, writer);
            // A failed write is the client leaving (or stalling past the write timeout); the
            // answer side reports nothing more.
            if let Ok(mut writer) = vlem_core::mapfile::write_map_to(writer, &snapshot) {
                let _ = writer.flush();
            }
            // The slot frees only once the snapshot's memory is.
            drop(snapshot);
            drop(slot);
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
    Reply::error(status, message_chain(e))
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
