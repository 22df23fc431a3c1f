//! HTTP/1.1 on one connection, with every read and write bounded in size and time.
//!
//! Why this file exists: the server runs next to a mapping run for hours, on a port any local
//! program (or a web page, through the browser) can reach, so each connection must cost bounded
//! memory and end in bounded time whatever the peer sends or withholds. The HTTP library used
//! before had no timeouts and held any header line in memory; the maintained async stacks answer
//! some of these cases with empty bodies (a request line of `HTTP/2.0` gets 400, not 505) and
//! would bring an async runtime to a server whose handlers are blocking passes over the map. So
//! the grammar is `httparse`'s (the parser under hyper), and this file adds only the limits:
//! - the request head (request line and headers) must fit in [`Limits::head_bytes`] and arrive
//!   within [`Limits::head_time`] of its first byte: otherwise 414 (the request line alone is too
//!   long), 431 (headers), 408 (too slow);
//! - a keep-alive connection may wait [`Limits::idle`] for its next request, then it is closed;
//! - a body needs a `Content-Length` within [`Limits::body_bytes`] (413; 411 for chunked bodies)
//!   and must arrive within [`Limits::body_time`] (408); `Expect: 100-continue` is honoured once
//!   the request has been admitted, so a refused client never sends its body;
//! - a version other than HTTP/1.0 or 1.1 is answered 505;
//! - a write that makes no progress for [`Limits::write_stall`] ends the connection (a client
//!   that stops reading a download);
//! - a connection the server closes is closed in two steps ([`Connection::close`]): the answer's
//!   end is signalled, then what the peer still sends (the rest of a refused head or body) is
//!   read and dropped for up to [`Limits::linger`]. Closing a socket with unread bytes makes the
//!   kernel reset the connection, and a reset can discard the answer at the peer before it is read.
//!   Connections refused before they get a thread (the server's connection cap) are closed the
//!   same way by one [`Closer`] thread for all of them, so the accept loop never waits on a peer.

use std::io::{self, Read, Write};
use std::net::TcpStream;
use std::sync::mpsc::{self, Receiver, SyncSender, TryRecvError};
use std::time::{Duration, Instant};

/// Bounds on one connection's requests.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Limits {
    /// Bytes of a request head (request line and headers).
    pub head_bytes: usize,
    /// Bytes of a request target (path and query).
    pub url_bytes: usize,
    /// Headers in one request.
    pub headers: usize,
    /// Bytes of a request body.
    pub body_bytes: usize,
    /// How long a connection may wait for the first byte of its next request.
    pub idle: Duration,
    /// How long a request head may take from its first byte.
    pub head_time: Duration,
    /// How long a request body may take from the end of its head.
    pub body_time: Duration,
    /// How long one write may make no progress.
    pub write_stall: Duration,
    /// How long a closing connection reads and drops what its peer still sends.
    pub linger: Duration,
    /// How many bytes a closing connection reads and drops at most.
    pub linger_bytes: usize,
}

impl Limits {
    /// The server's bounds: generous for every client this server has (curl, a browser, ureq,
    /// Python's requests), small enough that 64 connections at their limits hold a few MiB.
    pub(crate) const SERVER: Self = Self {
        head_bytes: 16 * 1024,
        url_bytes: 8 * 1024,
        headers: 64,
        body_bytes: 1 << 20,
        idle: Duration::from_secs(30),
        head_time: Duration::from_secs(10),
        body_time: Duration::from_secs(10),
        write_stall: Duration::from_secs(30),
        // Enough for the rest of a refused head or body on loopback; a peer that sends more
        // or longer gets the reset it asked for.
        linger: Duration::from_secs(2),
        linger_bytes: 4 << 20,
    };
}

/// A request's line and headers, read and checked, its body not yet read.
#[derive(Debug)]
pub(crate) struct Head {
    /// The method as sent (`GET`, `POST`, …).
    pub method: String,
    /// The request target (path and query).
    pub target: String,
    /// Headers in the order sent; values that are not UTF-8 are read lossily.
    pub headers: Vec<(String, String)>,
    /// Whether the connection stays open after the answer (HTTP/1.1 without `Connection: close`).
    pub keep_alive: bool,
}

impl Head {
    /// The value of the first header named `name` (case-insensitively).
    pub(crate) fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }

    /// Whether the request announces a body (one that must be read or the connection closed).
    pub(crate) fn has_body(&self) -> bool {
        self.header("Transfer-Encoding").is_some()
            || self
                .header("Content-Length")
                .is_some_and(|n| n.trim() != "0")
    }
}

/// Why no request was read.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum ReadError {
    /// The peer closed, went quiet between requests, or the socket failed: close without an answer.
    Closed,
    /// Answer `status` with `message`, then close.
    Refuse {
        /// HTTP status.
        status: u16,
        /// The JSON error's message.
        message: String,
    },
}

fn refuse(status: u16, message: impl Into<String>) -> ReadError {
    ReadError::Refuse {
        status,
        message: message.into(),
    }
}

/// One accepted connection: its socket and the bytes read past the current request (a pipelined
/// next request).
pub(crate) struct Connection {
    stream: TcpStream,
    limits: Limits,
    buffer: Vec<u8>,
}

impl Connection {
    pub(crate) fn new(stream: TcpStream, limits: Limits) -> Self {
        Self {
            stream,
            limits,
            buffer: Vec::new(),
        }
    }

    /// Reads the next request's head; its body, if any, is left for [`Connection::read_body`].
    pub(crate) fn read_head(&mut self) -> Result<Head, ReadError> {
        let waiting_since = Instant::now();
        let mut first_byte = (!self.buffer.is_empty()).then_some(waiting_since);
        loop {
            if let Some(head) = self.parse_head()? {
                return Ok(head);
            }
            let deadline = match first_byte {
                None => waiting_since + self.limits.idle,
                Some(at) => at + self.limits.head_time,
            };
            match self.fill(deadline)? {
                Filled::Bytes => {
                    first_byte.get_or_insert_with(Instant::now);
                }
                Filled::TimedOut if first_byte.is_none() => return Err(ReadError::Closed),
                Filled::TimedOut => {
                    return Err(refuse(
                        408,
                        format!(
                            "the request head did not arrive within {} s of its first byte",
                            self.limits.head_time.as_secs()
                        ),
                    ));
                }
            }
        }
    }

    /// The head at the start of the buffer, if it is complete (taken off the buffer).
    fn parse_head(&mut self) -> Result<Option<Head>, ReadError> {
        let Some((head, length)) = parse_head(&self.buffer, &self.limits)? else {
            return Ok(None);
        };
        self.buffer.drain(..length);
        Ok(Some(head))
    }

    /// Reads the body `head` announces (empty when it announces none). Call it only for an
    /// admitted request: it answers `Expect: 100-continue`.
    pub(crate) fn read_body(&mut self, head: &Head) -> Result<Vec<u8>, ReadError> {
        if head.header("Transfer-Encoding").is_some() {
            return Err(refuse(
                411,
                "send the request body with a Content-Length (chunked bodies are not accepted)",
            ));
        }
        let mut lengths = head
            .headers
            .iter()
            .filter(|(n, _)| n.eq_ignore_ascii_case("Content-Length"))
            .map(|(_, v)| v.trim().parse::<u64>());
        let length = match (lengths.next(), lengths.next()) {
            (None, _) => 0,
            (Some(Ok(n)), None) => n,
            _ => {
                return Err(refuse(
                    400,
                    "the Content-Length header must be one whole number",
                ));
            }
        };
        let limit = self.limits.body_bytes;
        let length = match usize::try_from(length) {
            Ok(n) if n <= limit => n,
            _ => {
                return Err(refuse(
                    413,
                    format!(
                        "a request body of {length} bytes; request bodies are limited to {limit} \
                         bytes"
                    ),
                ));
            }
        };
        if length == 0 {
            return Ok(Vec::new());
        }
        if self.buffer.is_empty()
            && head
                .header("Expect")
                .is_some_and(|e| e.trim().eq_ignore_ascii_case("100-continue"))
        {
            self.write_all(b"HTTP/1.1 100 Continue\r\n\r\n")
                .map_err(|_| ReadError::Closed)?;
        }
        let deadline = Instant::now() + self.limits.body_time;
        while self.buffer.len() < length {
            if let Filled::TimedOut = self.fill(deadline)? {
                return Err(refuse(
                    408,
                    format!(
                        "the request body ({length} bytes) did not arrive within {} s",
                        self.limits.body_time.as_secs()
                    ),
                ));
            }
        }
        Ok(self.buffer.drain(..length).collect())
    }

    /// Reads what the peer has sent by `deadline` onto the buffer.
    fn fill(&mut self, deadline: Instant) -> Result<Filled, ReadError> {
        let mut chunk = [0u8; 8192];
        match read_by(&mut self.stream, &mut chunk, deadline) {
            Ok(Some(0)) | Err(_) => Err(ReadError::Closed),
            Ok(Some(n)) => {
                self.buffer.extend_from_slice(&chunk[..n]);
                Ok(Filled::Bytes)
            }
            Ok(None) => Ok(Filled::TimedOut),
        }
    }

    /// Closes the connection after its last answer without losing that answer: signals the
    /// answer's end, then reads and drops what the peer still sends until it closes too, or for
    /// up to [`Limits::linger`] and [`Limits::linger_bytes`] (the module doc says why).
    pub(crate) fn close(mut self) {
        if self.stream.shutdown(std::net::Shutdown::Write).is_err() {
            return;
        }
        let deadline = Instant::now() + self.limits.linger;
        let mut chunk = [0u8; 8192];
        let mut dropped = 0;
        while dropped < self.limits.linger_bytes {
            match read_by(&mut self.stream, &mut chunk, deadline) {
                Ok(Some(0) | None) | Err(_) => return,
                Ok(Some(n)) => dropped += n,
            }
        }
    }

    /// Writes an answer: the status line, `headers`, `Content-Length` and `Connection`, then the
    /// body (`body_len` bytes read from `body`; none for the answer to a HEAD request, which
    /// `send_body` false gives). A body that ends early is an error (the peer then sees a short
    /// answer and a closed connection, never a wrong one).
    pub(crate) fn write_answer(
        &mut self,
        status: u16,
        headers: &[(&str, String)],
        body: &mut dyn Read,
        body_len: u64,
        send_body: bool,
        close: bool,
    ) -> io::Result<()> {
        let mut head = format!("HTTP/1.1 {status} {}\r\n", reason(status));
        for (name, value) in headers {
            head.push_str(&format!("{name}: {value}\r\n"));
        }
        head.push_str(&format!(
            "Content-Length: {body_len}\r\nConnection: {}\r\n\r\n",
            if close { "close" } else { "keep-alive" }
        ));
        // The write timeout (set by `write_all`) bounds each write of the body too.
        self.write_all(head.as_bytes())?;
        if !send_body {
            return self.stream.flush();
        }
        let copied = io::copy(&mut body.take(body_len), &mut self.stream)?;
        if copied < body_len {
            return Err(io::Error::new(
                io::ErrorKind::UnexpectedEof,
                "the answer's body ended early",
            ));
        }
        self.stream.flush()
    }

    fn write_all(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.stream
            .set_write_timeout(Some(self.limits.write_stall))?;
        self.stream.write_all(bytes)
    }
}

/// Closes connections that were refused without a thread of their own (the accept loop's 503 at
/// the connection cap), each as [`Connection::close`] does: its side ended, then what the peer
/// still sends read and dropped until the peer closes, [`Limits::linger`] passes or
/// [`Limits::linger_bytes`] are dropped. One thread drains them all side by side with
/// non-blocking reads, so the accept loop hands a connection over and goes on at once.
///
/// It holds at most [`Closer::HELD`] connections (file descriptors, in a flood of refusals):
/// one handed over past that is closed at once, the plain close it would have had without the
/// closer. The thread ends by itself once the closer is dropped and its last connection closed.
pub(crate) struct Closer {
    handover: SyncSender<TcpStream>,
}

impl Closer {
    /// Connections draining plus waiting for the thread, at most.
    pub(crate) const HELD: usize = 64;
    /// How often the thread reads its connections again while any is open.
    const POLL: Duration = Duration::from_millis(10);

    /// Starts the closing thread.
    pub(crate) fn start(limits: Limits) -> io::Result<Self> {
        // Half wait in the hand-over, half drain: the thread takes a waiting one whenever a
        // draining one ends.
        let (handover, waiting) = mpsc::sync_channel(Self::HELD / 2);
        std::thread::Builder::new()
            .name("vlem-http-close".into())
            .spawn(move || drain_refused(&waiting, limits, Self::HELD - Self::HELD / 2))?;
        Ok(Self { handover })
    }

    /// Closes `stream`, whose answer has been written, without waiting for its peer.
    pub(crate) fn close(&self, stream: TcpStream) {
        let ended = stream.shutdown(std::net::Shutdown::Write).is_ok();
        if ended && stream.set_nonblocking(true).is_ok() {
            // Full (or the thread is gone): dropped here, closed at once.
            let _ = self.handover.try_send(stream);
        }
    }
}

/// The closer thread: see [`Closer`].
fn drain_refused(waiting: &Receiver<TcpStream>, limits: Limits, draining_at_most: usize) {
    struct Draining {
        stream: TcpStream,
        deadline: Instant,
        dropped: usize,
    }
    let mut draining: Vec<Draining> = Vec::new();
    let mut handed_over = true;
    let mut chunk = [0u8; 8192];
    loop {
        // Take what waits, while there is room; wait for one only when nothing drains.
        while handed_over && draining.len() < draining_at_most {
            let next = if draining.is_empty() {
                waiting.recv().map_err(|_| TryRecvError::Disconnected)
            } else {
                waiting.try_recv()
            };
            match next {
                Ok(stream) => draining.push(Draining {
                    stream,
                    deadline: Instant::now() + limits.linger,
                    dropped: 0,
                }),
                Err(TryRecvError::Empty) => break,
                Err(TryRecvError::Disconnected) => handed_over = false,
            }
        }
        if draining.is_empty() {
            return;
        }
        let now = Instant::now();
        draining.retain_mut(|connection| {
            loop {
                match connection.stream.read(&mut chunk) {
                    // The peer closed, or its socket failed: done.
                    Ok(0) => return false,
                    Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                    Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                        return now < connection.deadline;
                    }
                    Err(_) => return false,
                    Ok(n) => {
                        connection.dropped += n;
                        if connection.dropped >= limits.linger_bytes {
                            return false;
                        }
                    }
                }
            }
        });
        if !draining.is_empty() {
            std::thread::sleep(Closer::POLL);
        }
    }
}

/// One read of what `stream` has by `deadline`: `Some(0)` when the peer has closed, `None` when
/// the deadline passed first.
fn read_by(
    stream: &mut TcpStream,
    chunk: &mut [u8],
    deadline: Instant,
) -> io::Result<Option<usize>> {
    loop {
        let Some(left) = deadline
            .checked_duration_since(Instant::now())
            .filter(|d| !d.is_zero())
        else {
            return Ok(None);
        };
        stream.set_read_timeout(Some(left))?;
        match stream.read(chunk) {
            Ok(n) => return Ok(Some(n)),
            // Interrupted, or the read timed out: the deadline decides on the next turn.
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::Interrupted
                        | io::ErrorKind::WouldBlock
                        | io::ErrorKind::TimedOut
                ) => {}
            Err(e) => return Err(e),
        }
    }
}

/// The request head at the start of `buffer` and its length in bytes, if it is complete;
/// the limits' refusals otherwise. Pure, so the fuzz target runs what a connection runs.
pub(crate) fn parse_head(
    buffer: &[u8],
    limits: &Limits,
) -> Result<Option<(Head, usize)>, ReadError> {
    if buffer.is_empty() {
        return Ok(None);
    }
    let mut headers = vec![httparse::EMPTY_HEADER; limits.headers];
    let mut request = httparse::Request::new(&mut headers);
    let length = match request.parse(buffer) {
        Ok(httparse::Status::Complete(length)) => length,
        Ok(httparse::Status::Partial) => {
            return if buffer.len() < limits.head_bytes {
                Ok(None)
            } else if !buffer[..limits.head_bytes].contains(&b'\n') {
                Err(target_too_long(
                    limits,
                    format!("over {}", limits.head_bytes),
                ))
            } else {
                Err(head_too_large(limits))
            };
        }
        Err(httparse::Error::Version) => {
            return Err(refuse(
                505,
                "this server speaks HTTP/1.1 (and 1.0) only; send the request as HTTP/1.1",
            ));
        }
        Err(httparse::Error::TooManyHeaders) => return Err(head_too_large(limits)),
        Err(e) => return Err(refuse(400, format!("malformed HTTP request: {e}"))),
    };
    if length > limits.head_bytes {
        return Err(head_too_large(limits));
    }
    let target = request.path.unwrap_or("/");
    if target.len() > limits.url_bytes {
        return Err(target_too_long(limits, target.len().to_string()));
    }
    let http_1_1 = request.version == Some(1);
    let headers: Vec<(String, String)> = request
        .headers
        .iter()
        .map(|h| {
            (
                h.name.to_owned(),
                String::from_utf8_lossy(h.value).into_owned(),
            )
        })
        .collect();
    let close = headers
        .iter()
        .filter(|(n, _)| n.eq_ignore_ascii_case("Connection"))
        .any(|(_, v)| v.split(',').any(|t| t.trim().eq_ignore_ascii_case("close")));
    let head = Head {
        method: request.method.unwrap_or("").to_owned(),
        target: target.to_owned(),
        headers,
        keep_alive: http_1_1 && !close,
    };
    Ok(Some((head, length)))
}

/// 414 for a target of `bytes` (a count, or "over N" when the line did not end).
fn target_too_long(limits: &Limits, bytes: String) -> ReadError {
    refuse(
        414,
        format!(
            "a request target of {bytes} bytes; the limit is {} bytes (send long texts in a \
             POST /query body)",
            limits.url_bytes
        ),
    )
}

fn head_too_large(limits: &Limits) -> ReadError {
    refuse(
        431,
        format!(
            "the request's headers exceed the limit of {} bytes or {} headers",
            limits.head_bytes, limits.headers
        ),
    )
}

enum Filled {
    Bytes,
    TimedOut,
}

/// The reason phrase of the statuses this server sends.
pub(crate) fn reason(status: u16) -> &'static str {
    match status {
        100 => "Continue",
        200 => "OK",
        400 => "Bad Request",
        401 => "Unauthorized",
        403 => "Forbidden",
        404 => "Not Found",
        405 => "Method Not Allowed",
        408 => "Request Timeout",
        409 => "Conflict",
        411 => "Length Required",
        413 => "Content Too Large",
        414 => "URI Too Long",
        415 => "Unsupported Media Type",
        422 => "Unprocessable Content",
        431 => "Request Header Fields Too Large",
        500 => "Internal Server Error",
        503 => "Service Unavailable",
        505 => "HTTP Version Not Supported",
        507 => "Insufficient Storage",
        _ => "",
    }
}

#[cfg(test)]
mod tests {
    use std::net::TcpListener;

    use super::*;

    const QUICK: Limits = Limits {
        head_bytes: 1024,
        url_bytes: 256,
        headers: 8,
        body_bytes: 64,
        idle: Duration::from_millis(300),
        head_time: Duration::from_millis(300),
        body_time: Duration::from_millis(300),
        write_stall: Duration::from_millis(300),
        linger: Duration::from_millis(300),
        linger_bytes: 4 << 20,
    };

    /// A server-side connection and the client socket that talks to it.
    fn pair() -> (Connection, TcpStream) {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let client = TcpStream::connect(listener.local_addr().unwrap()).unwrap();
        let (server, _) = listener.accept().unwrap();
        (Connection::new(server, QUICK), client)
    }

    fn status_of(result: Result<Head, ReadError>) -> u16 {
        match result {
            Ok(_) => 200,
            Err(ReadError::Closed) => 0,
            Err(ReadError::Refuse { status, .. }) => status,
        }
    }

    #[test]
    fn pipelined_requests_and_their_bodies_are_read_in_turn() {
        let (mut connection, mut client) = pair();
        client
            .write_all(
                b"POST /query HTTP/1.1\r\nHost: h\r\nContent-Length: 5\r\n\r\nhello\
                  GET /status HTTP/1.1\r\nHost: h\r\nConnection: close\r\n\r\n",
            )
            .unwrap();
        let head = connection.read_head().unwrap();
        assert_eq!(
            (head.method.as_str(), head.target.as_str()),
            ("POST", "/query")
        );
        assert!(head.keep_alive && head.has_body());
        assert_eq!(head.header("content-length"), Some("5"));
        assert_eq!(connection.read_body(&head).unwrap(), b"hello");
        let head = connection.read_head().unwrap();
        assert_eq!(head.target, "/status");
        assert!(!head.keep_alive && !head.has_body());
        assert!(connection.read_body(&head).unwrap().is_empty());
    }

    #[test]
    fn oversized_heads_targets_and_bodies_get_their_statuses() {
        let cases: [(Vec<u8>, u16); 6] = [
            (
                format!("GET /{} HTTP/1.1\r\n\r\n", "a".repeat(300)).into_bytes(),
                414,
            ),
            // No line end within the head limit: a request line that never ends.
            (format!("GET /{}", "a".repeat(2000)).into_bytes(), 414),
            (
                format!("GET / HTTP/1.1\r\nX: {}\r\n\r\n", "a".repeat(2000)).into_bytes(),
                431,
            ),
            (
                (0..20)
                    .map(|i| format!("X-{i}: 1\r\n"))
                    .fold("GET / HTTP/1.1\r\n".to_owned(), |s, h| s + &h)
                    .into_bytes(),
                431,
            ),
            (b"GET / HTTP/2.0\r\n\r\n".to_vec(), 505),
            (b"GET\x01 / HTTP/1.1\r\n\r\n".to_vec(), 400),
        ];
        for (request, expected) in cases {
            let (mut connection, mut client) = pair();
            client.write_all(&request).unwrap();
            assert_eq!(
                status_of(connection.read_head()),
                expected,
                "{}",
                String::from_utf8_lossy(&request[..request.len().min(40)])
            );
        }
        let (mut connection, mut client) = pair();
        client
            .write_all(b"POST / HTTP/1.1\r\nContent-Length: 100\r\n\r\n")
            .unwrap();
        let head = connection.read_head().unwrap();
        let Err(ReadError::Refuse { status, message }) = connection.read_body(&head) else {
            panic!("a body over the limit is refused");
        };
        assert_eq!(status, 413);
        assert!(message.contains("limited to 64 bytes"), "{message}");
        for (headers, expected) in [
            ("Transfer-Encoding: chunked", 411),
            ("Content-Length: 1\r\nContent-Length: 2", 400),
            ("Content-Length: -1", 400),
        ] {
            let (mut connection, mut client) = pair();
            client
                .write_all(format!("POST / HTTP/1.1\r\n{headers}\r\n\r\n").as_bytes())
                .unwrap();
            let head = connection.read_head().unwrap();
            assert!(
                matches!(connection.read_body(&head), Err(ReadError::Refuse { status, .. }) if status == expected),
                "{headers}"
            );
        }
    }

    #[test]
    fn slow_and_silent_peers_are_timed_out() {
        // Silent before a request: closed without an answer.
        let (mut connection, _client) = pair();
        assert_eq!(connection.read_head().unwrap_err(), ReadError::Closed);
        // A head that starts and stalls: 408.
        let (mut connection, mut client) = pair();
        client.write_all(b"GET / HTTP/1.1\r\nHo").unwrap();
        assert_eq!(status_of(connection.read_head()), 408);
        // A body that stalls after its head: 408.
        let (mut connection, mut client) = pair();
        client
            .write_all(b"POST / HTTP/1.1\r\nContent-Length: 10\r\n\r\nabc")
            .unwrap();
        let head = connection.read_head().unwrap();
        assert!(matches!(
            connection.read_body(&head),
            Err(ReadError::Refuse { status: 408, .. })
        ));
        // A peer that closes mid-head: closed.
        let (mut connection, mut client) = pair();
        client.write_all(b"GET / HT").unwrap();
        drop(client);
        assert_eq!(connection.read_head().unwrap_err(), ReadError::Closed);
    }

    #[test]
    fn expect_continue_is_answered_before_the_body_and_answers_carry_their_length() {
        let (mut connection, mut client) = pair();
        client
            .write_all(b"POST / HTTP/1.1\r\nContent-Length: 2\r\nExpect: 100-continue\r\n\r\n")
            .unwrap();
        let head = connection.read_head().unwrap();
        let reader = std::thread::spawn(move || {
            let mut seen = [0u8; 25];
            client.read_exact(&mut seen).unwrap();
            assert_eq!(&seen, b"HTTP/1.1 100 Continue\r\n\r\n");
            client.write_all(b"{}").unwrap();
            let mut answer = String::new();
            client.read_to_string(&mut answer).unwrap();
            answer
        });
        assert_eq!(connection.read_body(&head).unwrap(), b"{}");
        connection
            .write_answer(
                200,
                &[("Content-Type", "text/plain".into())],
                &mut &b"ok"[..],
                2,
                true,
                true,
            )
            .unwrap();
        drop(connection);
        let answer = reader.join().unwrap();
        assert_eq!(
            answer,
            "HTTP/1.1 200 OK\r\nContent-Type: text/plain\r\nContent-Length: 2\r\n\
             Connection: close\r\n\r\nok"
        );
    }

    /// What a client reads when the server refuses its head while it is still sending the rest
    /// of it. (Dropping the connection instead of `close` made this a reset in 10 of 10 tries.)
    fn refuse_while_the_peer_sends() -> io::Result<Vec<u8>> {
        let (mut connection, mut client) = pair();
        let mut sender = client.try_clone().unwrap();
        let sending = std::thread::spawn(move || {
            let head = format!("GET / HTTP/1.1\r\nX: {}\r\n\r\n", "a".repeat(1 << 20));
            // A reset may end this write early; the answer is what is checked.
            let _ = sender.write_all(head.as_bytes());
            let _ = sender.shutdown(std::net::Shutdown::Write);
        });
        let Err(ReadError::Refuse { status, message }) = connection.read_head() else {
            panic!("an oversized head is refused");
        };
        connection.write_answer(
            status,
            &[],
            &mut message.as_bytes(),
            message.len() as u64,
            true,
            true,
        )?;
        connection.close();
        sending.join().unwrap();
        let mut answer = Vec::new();
        client.read_to_end(&mut answer)?;
        Ok(answer)
    }

    #[test]
    fn a_closed_connection_keeps_its_answer_while_the_peer_is_still_sending() {
        for _ in 0..5 {
            let answer = refuse_while_the_peer_sends().unwrap();
            let answer = String::from_utf8_lossy(&answer);
            assert!(answer.starts_with("HTTP/1.1 431 "), "{answer}");
            assert!(answer.ends_with("1024 bytes or 8 headers"), "{answer}");
        }
    }

    /// What clients read when the server answers them at once and hands their connections to a
    /// [`Closer`] while each is still sending its request body: a failed send or the answer.
    /// (Closing them at once instead, as the accept loop did, failed the send in 2 of 2 tries.)
    /// `clients` past [`Closer::HELD`] are closed at once and may see a failed send.
    fn refuse_through_the_closer(clients: usize) -> Vec<io::Result<Vec<u8>>> {
        // The server's own linger: the clients close as soon as they have read, and a loaded
        // machine must not end a drain before a client's body is through.
        let closer = Closer::start(Limits {
            linger: Limits::SERVER.linger,
            ..QUICK
        })
        .unwrap();
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let address = listener.local_addr().unwrap();
        let mut readers = Vec::new();
        for _ in 0..clients {
            let mut client = TcpStream::connect(address).unwrap();
            // The request's head is in the server's socket before the answer, as at a full
            // server; its body is still coming when the connection is handed over.
            client
                .write_all(b"POST / HTTP/1.1\r\nContent-Length: 262144\r\n\r\n")
                .unwrap();
            let mut sender = client.try_clone().unwrap();
            let sending = std::thread::spawn(move || {
                sender.write_all(&vec![b'a'; 1 << 18])?;
                sender.shutdown(std::net::Shutdown::Write)
            });
            let (mut server, _) = listener.accept().unwrap();
            server.peek(&mut [0u8; 1]).unwrap();
            server
                .write_all(b"HTTP/1.1 503 Service Unavailable\r\n\r\nbusy")
                .unwrap();
            closer.close(server);
            readers.push(std::thread::spawn(move || {
                // A client that sends its whole request before it reads (Python's requests
                // and http.client) reports a failed send, not the answer.
                sending.join().unwrap()?;
                let mut answer = Vec::new();
                client.read_to_end(&mut answer).map(|_| answer)
            }));
        }
        readers.into_iter().map(|r| r.join().unwrap()).collect()
    }

    #[test]
    fn the_closer_keeps_refused_answers_while_their_peers_are_still_sending() {
        for answer in refuse_through_the_closer(Closer::HELD / 2) {
            assert_eq!(
                String::from_utf8_lossy(&answer.unwrap()),
                "HTTP/1.1 503 Service Unavailable\r\n\r\nbusy"
            );
        }
        // A flood past what it holds: the rest are closed at once, and nothing waits on them.
        let answered = refuse_through_the_closer(Closer::HELD * 2)
            .into_iter()
            .filter(|answer| answer.is_ok())
            .count();
        assert!(answered >= Closer::HELD / 2, "{answered} answered");
    }

    #[test]
    fn a_body_that_ends_early_is_an_error_not_a_short_answer() {
        let (mut connection, _client) = pair();
        let err = connection
            .write_answer(200, &[], &mut &b"short"[..], 10, true, true)
            .unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::UnexpectedEof);
    }
}
