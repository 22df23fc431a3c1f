//! Who may talk to the server: the checks every request passes before it is routed.
//!
//! Why this file exists: the server listens on loopback without a login, so the attacker to keep
//! out is not another machine but a web page open in the user's own browser. Such a page can send
//! "simple" cross-site requests (a `text/plain` POST needs no CORS preflight, so it reaches the
//! handler even though the page cannot read the answer), and through DNS rebinding it can make its
//! own host name resolve to 127.0.0.1 and then read answers as if it were same-origin. So:
//! - `Host` must name a loopback address (`127.0.0.1`, `localhost`, `[::1]` …) with the server's
//!   own port: a rebinding page's requests carry the page's host name;
//! - an `Origin` header, when a browser sends one, must be a loopback origin (403 otherwise, and
//!   `Origin: null` from sandboxed frames and `file://` pages is refused too);
//! - a POST must declare `Content-Type: application/json`, which no simple request can, so a
//!   browser would have to ask first with a preflight that this server never grants;
//! - with a bearer token configured (for users who tunnel the port), every request must carry
//!   `Authorization: Bearer TOKEN` (401 otherwise); the token then replaces the Host check, since
//!   a tunnel's far end names its own host and port, and a page cannot know the token.
//!
//! The checks are pure functions of the request's method and headers, so they are tested here
//! without a socket.

use std::fmt;

/// What a request must show to be served.
#[derive(Clone)]
pub(crate) struct Access {
    /// The port the server is bound to (the one a same-machine `Host` names).
    port: u16,
    /// The bearer token, when one is required.
    token: Option<String>,
}

impl fmt::Debug for Access {
    // The token stays out of logs and panic messages.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Access")
            .field("port", &self.port)
            .field("token", &self.token.as_ref().map(|_| "<set>"))
            .finish()
    }
}

/// A request that is not served, and how to answer it.
#[derive(Debug, PartialEq, Eq)]
pub(crate) struct Refusal {
    /// HTTP status: 400 (no Host), 401 (token), 403 (Host or Origin), 415 (Content-Type).
    pub status: u16,
    /// The message of the JSON error body.
    pub message: String,
}

impl Refusal {
    fn new(status: u16, message: impl Into<String>) -> Self {
        Self {
            status,
            message: message.into(),
        }
    }
}

/// The parts of a request the checks read.
pub(crate) struct RequestHead<'a> {
    /// Whether the method is POST (the one method with a body here).
    pub post: bool,
    /// The `Host` header.
    pub host: Option<&'a str>,
    /// The `Origin` header.
    pub origin: Option<&'a str>,
    /// The `Content-Type` header.
    pub content_type: Option<&'a str>,
    /// The `Authorization` header.
    pub authorization: Option<&'a str>,
}

impl Access {
    /// Requests to a server bound to `port`, with an optional bearer token.
    pub(crate) fn new(port: u16, token: Option<String>) -> Self {
        Self { port, token }
    }

    /// Passes a request, or says why not. The token is checked first, so a client without it
    /// learns nothing else about the server.
    pub(crate) fn check(&self, head: &RequestHead<'_>) -> Result<(), Refusal> {
        match &self.token {
            Some(token) => check_token(token, head.authorization)?,
            None => self.check_host(head.host)?,
        }
        check_origin(head.origin)?;
        if head.post {
            check_content_type(head.content_type)?;
        }
        Ok(())
    }

    fn check_host(&self, host: Option<&str>) -> Result<(), Refusal> {
        let Some(host) = host.map(str::trim).filter(|h| !h.is_empty()) else {
            return Err(Refusal::new(
                400,
                "the request has no Host header (HTTP/1.1 requires one)",
            ));
        };
        let refused = || {
            Refusal::new(
                403,
                format!(
                    "Host `{}` is not this server: it answers only requests addressed to a \
                     loopback address with its port, such as 127.0.0.1:{} (a web page that \
                     rebinds its own name to 127.0.0.1 is refused this way); to reach it through \
                     a tunnel, start it with a bearer token (--serve-token)",
                    shorten(host),
                    self.port
                ),
            )
        };
        let (name, port) = split_host_port(host).ok_or_else(refused)?;
        // Browsers omit the default port.
        let port_matches = match port {
            Some(p) => p == self.port,
            None => self.port == 80,
        };
        if port_matches && is_loopback_name(name) {
            Ok(())
        } else {
            Err(refused())
        }
    }
}

fn check_token(token: &str, authorization: Option<&str>) -> Result<(), Refusal> {
    let given = authorization
        .map(str::trim)
        .and_then(|value| {
            let (scheme, rest) = value.split_once(' ')?;
            scheme.eq_ignore_ascii_case("bearer").then(|| rest.trim())
        })
        .ok_or_else(|| {
            Refusal::new(
                401,
                "this server requires a bearer token: send `Authorization: Bearer TOKEN` \
                 (`vlem query --connect` reads it from --token or VLEM_SERVE_TOKEN)",
            )
        })?;
    if constant_time_eq(given.as_bytes(), token.as_bytes()) {
        Ok(())
    } else {
        Err(Refusal::new(401, "the bearer token is not this server's"))
    }
}

fn check_origin(origin: Option<&str>) -> Result<(), Refusal> {
    let Some(origin) = origin.map(str::trim) else {
        // Same-origin navigations and non-browser clients send none.
        return Ok(());
    };
    let loopback = origin
        .strip_prefix("http://")
        .or_else(|| origin.strip_prefix("https://"))
        .and_then(split_host_port)
        .is_some_and(|(name, _)| is_loopback_name(name));
    if loopback {
        Ok(())
    } else {
        Err(Refusal::new(
            403,
            format!(
                "requests from the web page at Origin `{}` are refused: the server answers \
                 programs on this machine and pages served from loopback only",
                shorten(origin)
            ),
        ))
    }
}

fn check_content_type(content_type: Option<&str>) -> Result<(), Refusal> {
    let essence = content_type
        .and_then(|value| value.split(';').next())
        .map(str::trim);
    if essence.is_some_and(|e| e.eq_ignore_ascii_case("application/json")) {
        Ok(())
    } else {
        Err(Refusal::new(
            415,
            format!(
                "POST bodies must be sent as `Content-Type: application/json` (got {}); with \
                 curl: -H 'Content-Type: application/json'",
                content_type.map_or_else(|| "none".to_owned(), |c| format!("`{}`", shorten(c)))
            ),
        ))
    }
}

/// `name:port`, `[v6]:port`, `name` or `[v6]` → the name (brackets removed) and the port.
/// `None` for anything else (a port that is not a number, an unclosed bracket, a path).
fn split_host_port(host: &str) -> Option<(&str, Option<u16>)> {
    if host.contains(['/', '@', ' ']) {
        return None;
    }
    let (name, port) = if let Some(rest) = host.strip_prefix('[') {
        let (name, after) = rest.split_once(']')?;
        match after {
            "" => (name, None),
            _ => (name, Some(after.strip_prefix(':')?)),
        }
    } else {
        match host.split_once(':') {
            Some((name, port)) => (name, Some(port)),
            None => (host, None),
        }
    };
    let port = match port {
        Some(p) => Some(p.parse::<u16>().ok()?),
        None => None,
    };
    Some((name, port))
}

/// `localhost`, `*.localhost` (RFC 6761 keeps both on loopback), or a loopback IP literal.
fn is_loopback_name(name: &str) -> bool {
    let name = name.trim_end_matches('.');
    if name.eq_ignore_ascii_case("localhost")
        || name
            .to_ascii_lowercase()
            .strip_suffix(".localhost")
            .is_some_and(|label| !label.is_empty())
    {
        return true;
    }
    name.parse::<std::net::IpAddr>()
        .is_ok_and(|ip| ip.is_loopback())
}

/// Compares in time that depends on the lengths only, so a wrong token's answer time says
/// nothing about how much of it was right.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// A header value as quoted in an error message: at most 80 characters.
fn shorten(text: &str) -> String {
    const MAX: usize = 80;
    match text.char_indices().nth(MAX) {
        Some((cut, _)) => format!("{}…", &text[..cut]),
        None => text.to_owned(),
    }
}

/// Checks a bearer token given by the user: it must fit into a header value unchanged.
///
/// # Errors
/// A message naming what is wrong with it (never the token itself).
pub(crate) fn validate_token(token: &str) -> Result<(), String> {
    if token.is_empty() {
        return Err("the bearer token is empty".into());
    }
    if token.len() < 16 {
        return Err(format!(
            "the bearer token has {} characters; use at least 16 (for example `openssl rand -hex 16`)",
            token.len()
        ));
    }
    if !token.bytes().all(|b| b.is_ascii_graphic()) {
        return Err(
            "the bearer token must be printable ASCII without spaces (it travels in a header)"
                .into(),
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn head<'a>(host: Option<&'a str>) -> RequestHead<'a> {
        RequestHead {
            post: false,
            host,
            origin: None,
            content_type: None,
            authorization: None,
        }
    }

    fn status(access: &Access, head: &RequestHead<'_>) -> u16 {
        access.check(head).err().map_or(200, |r| r.status)
    }

    #[test]
    fn only_loopback_hosts_with_the_servers_port_pass() {
        let access = Access::new(8765, None);
        for host in [
            "127.0.0.1:8765",
            "localhost:8765",
            "LOCALHOST:8765",
            "localhost.:8765",
            "vlem.localhost:8765",
            "[::1]:8765",
            "127.1.2.3:8765",
        ] {
            assert_eq!(status(&access, &head(Some(host))), 200, "{host}");
        }
        for host in [
            "attacker.example:8765",
            "attacker.example",
            "127.0.0.1:8766",
            "127.0.0.1",
            "localhost",
            "localhost.attacker.example:8765",
            "10.0.0.1:8765",
            "[::1",
            "[::1]8765",
            "127.0.0.1:port",
            "user@127.0.0.1:8765",
            ".localhost:8765",
        ] {
            assert_eq!(status(&access, &head(Some(host))), 403, "{host}");
        }
        assert_eq!(status(&access, &head(None)), 400);
        assert_eq!(status(&access, &head(Some("  "))), 400);
        // On port 80 a browser leaves the port out.
        assert_eq!(
            status(&Access::new(80, None), &head(Some("localhost"))),
            200
        );
        let message = access
            .check(&head(Some("attacker.example:8765")))
            .unwrap_err()
            .message;
        assert!(
            message.contains("attacker.example") && message.contains("127.0.0.1:8765"),
            "{message}"
        );
    }

    #[test]
    fn cross_site_origins_are_refused() {
        let access = Access::new(8765, None);
        let with_origin = |origin| RequestHead {
            origin: Some(origin),
            ..head(Some("127.0.0.1:8765"))
        };
        for origin in [
            "http://127.0.0.1:8765",
            "http://localhost:3000",
            "https://[::1]:8443",
            "http://localhost",
        ] {
            assert_eq!(status(&access, &with_origin(origin)), 200, "{origin}");
        }
        for origin in [
            "https://attacker.example",
            "http://attacker.example:8765",
            "null",
            "file://",
            "http://127.0.0.1.attacker.example",
            "",
        ] {
            assert_eq!(status(&access, &with_origin(origin)), 403, "{origin}");
        }
    }

    #[test]
    fn posts_must_be_declared_json() {
        let access = Access::new(8765, None);
        let post = |content_type| RequestHead {
            post: true,
            content_type,
            ..head(Some("127.0.0.1:8765"))
        };
        for ok in [
            "application/json",
            "application/json; charset=utf-8",
            "Application/JSON",
        ] {
            assert_eq!(status(&access, &post(Some(ok))), 200, "{ok}");
        }
        for simple in [
            "text/plain",
            "application/x-www-form-urlencoded",
            "multipart/form-data; boundary=x",
            "application/jsonx",
        ] {
            assert_eq!(status(&access, &post(Some(simple))), 415, "{simple}");
        }
        let missing = access.check(&post(None)).unwrap_err();
        assert_eq!(missing.status, 415);
        assert!(missing.message.contains("got none"), "{}", missing.message);
        // GETs carry no body and need no Content-Type.
        assert_eq!(status(&access, &head(Some("127.0.0.1:8765"))), 200);
    }

    #[test]
    fn a_token_is_required_when_set_and_replaces_the_host_check() {
        let token = "0123456789abcdef0123";
        let access = Access::new(8765, Some(token.into()));
        let with = |authorization, host| RequestHead {
            authorization,
            ..head(host)
        };
        let bearer = format!("Bearer {token}");
        let lower = format!("bearer {token}");
        assert_eq!(status(&access, &with(Some(&bearer), None)), 200);
        assert_eq!(status(&access, &with(Some(&lower), None)), 200);
        // Through a tunnel the Host names the tunnel's end.
        assert_eq!(
            status(&access, &with(Some(&bearer), Some("robot.example:9000"))),
            200
        );
        for wrong in [
            None,
            Some("Bearer 0123456789abcdef0124"),
            Some("Bearer "),
            Some("Basic dXNlcjpwYXNz"),
            Some(token),
        ] {
            assert_eq!(
                status(&access, &with(wrong, Some("127.0.0.1:8765"))),
                401,
                "{wrong:?}"
            );
        }
        // The Origin check still applies.
        let cross = RequestHead {
            origin: Some("https://attacker.example"),
            ..with(Some(&bearer), Some("127.0.0.1:8765"))
        };
        assert_eq!(status(&access, &cross), 403);
        assert!(!format!("{access:?}").contains(token));
    }

    #[test]
    fn tokens_are_validated_without_being_echoed() {
        assert!(validate_token("0123456789abcdef").is_ok());
        assert!(validate_token("").is_err());
        let short = validate_token("secret").unwrap_err();
        assert!(short.contains("at least 16") && !short.contains("secret"));
        let spaced = validate_token("0123456789 abcdef").unwrap_err();
        assert!(spaced.contains("printable ASCII"));
        assert!(validate_token("0123456789abcdef\n").is_err());
    }

    #[test]
    fn constant_time_comparison_compares() {
        assert!(constant_time_eq(b"abc", b"abc"));
        assert!(!constant_time_eq(b"abc", b"abd"));
        assert!(!constant_time_eq(b"abc", b"abcd"));
        assert!(constant_time_eq(b"", b""));
    }

    #[test]
    fn long_header_values_are_shortened_in_messages() {
        let long = "a".repeat(10_000);
        let message = Access::new(1, None)
            .check(&head(Some(&long)))
            .unwrap_err()
            .message;
        assert!(message.len() < 600, "{}", message.len());
    }
}
