//! The HTTP the console speaks: one request per connection, `GET` and `HEAD`, and `POST` with a
//! JSON body of at most [`MAX_BODY_BYTES`] (the routes that write the alert log take it; every
//! other route answers 405).
//!
//! Hand-rolled on tokio, as the gateway's metrics endpoint is: the console answers a handful of
//! fixed paths and one Server-Sent Events stream, which HTTP/1.1 carries as a response that
//! never ends. Requests are read up to [`MAX_REQUEST_BYTES`] and [`REQUEST_TIMEOUT`]; every
//! response closes the connection and carries headers that keep the page to its own scripts
//! (a Content-Security-Policy with no inline script), so that even a string that slipped past
//! escaping could not run.
//!
//! A refusal is closed gracefully ([`respond_error`]): the console stops writing, then reads
//! and discards what the client still sends for a moment. Closing a socket with unread bytes
//! makes the kernel reset the connection, and a client that sees the reset may never read the
//! status it was sent (a 431 for a head too long is exactly such a case).

use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Longest request head read.
pub const MAX_REQUEST_BYTES: usize = 8 * 1024;
/// Longest request body read (`POST` only).
pub const MAX_BODY_BYTES: usize = 16 * 1024;
/// Time a client gets to send its request.
pub const REQUEST_TIMEOUT: Duration = Duration::from_secs(5);
/// Time a client gets to take one response write (a page that stops reading is dropped).
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(10);
/// After a refusal, how long and how much the console goes on reading before it closes.
const LINGER: Duration = Duration::from_secs(2);
const LINGER_BYTES: usize = 64 * 1024;

/// Headers on every response.
const COMMON_HEADERS: &str = "Cache-Control: no-store\r\n\
X-Content-Type-Options: nosniff\r\n\
X-Frame-Options: DENY\r\n\
Referrer-Policy: no-referrer\r\n\
Content-Security-Policy: default-src 'none'; script-src 'self'; style-src 'self'; \
connect-src 'self'; img-src 'self' data:; base-uri 'none'; form-action 'none'; \
frame-ancestors 'none'\r\n\
Connection: close\r\n";

/// A request the console will answer.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Request {
    /// `HEAD` asks for the headers only.
    pub head_only: bool,
    /// `POST`: the body is in `body`.
    pub post: bool,
    pub path: String,
    /// Query parameters in order, percent-decoded.
    pub query: Vec<(String, String)>,
    /// The `Host` header, if any.
    pub host: Option<String>,
    /// The `Origin` header, if any (browsers send it with every `POST`).
    pub origin: Option<String>,
    /// The `Content-Type` header, if any.
    pub content_type: Option<String>,
    /// `Content-Length` (0 when absent).
    pub content_length: usize,
    /// The body of a `POST`.
    pub body: Vec<u8>,
    /// The `Cookie` header, if any.
    pub cookie: Option<String>,
    /// Every other header, its name in lower case, in order (the head is bounded, so is this).
    pub headers: Vec<(String, String)>,
}

impl Request {
    /// The value of header `name` (lower case) among the others, if sent once; none if absent
    /// or sent twice (two values name two things: neither is taken).
    pub fn header(&self, name: &str) -> Option<&str> {
        let mut found = self.headers.iter().filter(|(k, _)| k == name);
        let first = found.next()?;
        found.next().is_none().then_some(first.1.as_str())
    }
}

/// A request refused before routing: the status to answer and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Refusal {
    pub status: u16,
    pub message: String,
    /// The methods a 405 names in its `Allow` header.
    pub allow: &'static str,
}

impl Refusal {
    pub fn new(status: u16, message: impl Into<String>) -> Refusal {
        Refusal {
            status,
            message: message.into(),
            allow: "GET, HEAD",
        }
    }

    /// A 405 for a route that takes only `allow`.
    pub fn method(allow: &'static str, message: impl Into<String>) -> Refusal {
        Refusal {
            status: 405,
            message: message.into(),
            allow,
        }
    }
}

/// Reads and parses one request head. `Ok(None)`: the client closed or was too slow, nothing
/// to answer.
pub async fn read_request(stream: &mut TcpStream) -> Result<Option<Request>, Refusal> {
    read_request_within(stream, REQUEST_TIMEOUT).await
}

/// [`read_request`] with another time limit.
pub async fn read_request_within(
    stream: &mut TcpStream,
    limit: Duration,
) -> Result<Option<Request>, Refusal> {
    let mut buf = Vec::with_capacity(1024);
    let read = async {
        let mut chunk = [0u8; 1024];
        loop {
            if let Some(end) = find_head_end(&buf) {
                return Ok(Some(end));
            }
            if buf.len() >= MAX_REQUEST_BYTES {
                return Err(Refusal::new(
                    431,
                    format!("request head longer than {MAX_REQUEST_BYTES} bytes"),
                ));
            }
            match stream.read(&mut chunk).await {
                Ok(0) | Err(_) => return Ok(None),
                Ok(n) => buf.extend_from_slice(&chunk[..n]),
            }
        }
    };
    let end = match tokio::time::timeout(limit, read).await {
        Err(_) => return Ok(None),
        Ok(r) => r?,
    };
    let Some(end) = end else { return Ok(None) };
    let mut req = parse_head(&buf[..end.min(MAX_REQUEST_BYTES)])?;
    if req.post {
        let mut body = buf.get(end + 4..).unwrap_or_default().to_vec();
        let want = req.content_length;
        let read = async {
            let mut chunk = [0u8; 4096];
            while body.len() < want {
                match stream.read(&mut chunk).await {
                    Ok(0) | Err(_) => return false,
                    Ok(n) => body.extend_from_slice(&chunk[..n]),
                }
            }
            true
        };
        match tokio::time::timeout(limit, read).await {
            Ok(true) => {}
            _ => {
                return Err(Refusal::new(
                    400,
                    format!("the body is shorter than its Content-Length ({want} bytes)"),
                ))
            }
        }
        body.truncate(want);
        req.body = body;
    }
    Ok(Some(req))
}

fn find_head_end(buf: &[u8]) -> Option<usize> {
    buf.windows(4).position(|w| w == b"\r\n\r\n")
}

/// Parses a request head (without the blank line that ends it).
pub fn parse_head(head: &[u8]) -> Result<Request, Refusal> {
    let text = std::str::from_utf8(head)
        .map_err(|_| Refusal::new(400, "the request head is not UTF-8"))?;
    let mut lines = text.split("\r\n");
    let line = lines.next().unwrap_or_default();
    let mut parts = line.split(' ');
    let (Some(method), Some(target), Some(version), None) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Err(Refusal::new(400, "malformed request line"));
    };
    if version != "HTTP/1.1" && version != "HTTP/1.0" {
        return Err(Refusal::new(
            505,
            format!("unsupported version {version:?}"),
        ));
    }
    let (head_only, post) = match method {
        "GET" => (false, false),
        "HEAD" => (true, false),
        "POST" => (false, true),
        _ => {
            return Err(Refusal::new(
                405,
                format!(
                    "method {method:?} not allowed: the console answers GET and HEAD, and POST on \
                     its alert-log routes"
                ),
            ))
        }
    };
    let mut host = None;
    let mut origin = None;
    let mut content_type = None;
    let mut content_length = 0;
    let mut cookie = None;
    let mut headers = Vec::new();
    for h in lines {
        let Some((name, value)) = h.split_once(':') else {
            return Err(Refusal::new(400, "malformed header line"));
        };
        let value = value.trim();
        if name.eq_ignore_ascii_case("host") {
            // Two Host headers name two hosts: taking either would let a foreign name pass
            // the loopback check beside a local one (RFC 9112 §3.2 asks for 400).
            if host.is_some() {
                return Err(Refusal::new(400, "more than one Host header"));
            }
            host = Some(value.to_owned());
        } else if name.eq_ignore_ascii_case("origin") {
            if origin.is_some() {
                return Err(Refusal::new(400, "more than one Origin header"));
            }
            origin = Some(value.to_owned());
        } else if name.eq_ignore_ascii_case("content-type") {
            content_type = Some(value.to_owned());
        } else if name.eq_ignore_ascii_case("content-length") {
            if !post && value != "0" {
                return Err(Refusal::new(
                    400,
                    "request bodies are accepted with POST only",
                ));
            }
            let n: usize = value.parse().map_err(|_| {
                Refusal::new(
                    400,
                    format!("Content-Length {value:?} is not a whole number"),
                )
            })?;
            if n > MAX_BODY_BYTES {
                return Err(Refusal::new(
                    413,
                    format!("request body of {n} bytes; at most {MAX_BODY_BYTES}"),
                ));
            }
            content_length = n;
        } else if name.eq_ignore_ascii_case("transfer-encoding") {
            return Err(Refusal::new(
                400,
                "Transfer-Encoding is not accepted: send a Content-Length",
            ));
        } else if name.eq_ignore_ascii_case("cookie") {
            if cookie.is_some() {
                return Err(Refusal::new(400, "more than one Cookie header"));
            }
            cookie = Some(value.to_owned());
        } else {
            headers.push((name.trim().to_ascii_lowercase(), value.to_owned()));
        }
    }
    if !target.starts_with('/') {
        return Err(Refusal::new(400, "the request target is not a path"));
    }
    let (path, query) = target.split_once('?').unwrap_or((target, ""));
    let mut params = Vec::new();
    for pair in query.split('&').filter(|p| !p.is_empty()) {
        let (k, v) = pair.split_once('=').unwrap_or((pair, ""));
        let k = percent_decode(k)?;
        let v = percent_decode(v)?;
        if params.iter().any(|(n, _): &(String, String)| *n == k) {
            return Err(Refusal::new(400, format!("parameter {k:?} given twice")));
        }
        params.push((k, v));
    }
    Ok(Request {
        head_only,
        post,
        path: percent_decode(path)?,
        query: params,
        host,
        origin,
        content_type,
        content_length,
        body: Vec::new(),
        cookie,
        headers,
    })
}

fn percent_decode(s: &str) -> Result<String, Refusal> {
    let bad = || Refusal::new(400, format!("bad percent-encoding in {s:?}"));
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        match b[i] {
            b'%' => {
                let hex = b.get(i + 1..i + 3).ok_or_else(bad)?;
                let hex = std::str::from_utf8(hex).map_err(|_| bad())?;
                out.push(u8::from_str_radix(hex, 16).map_err(|_| bad())?);
                i += 3;
            }
            b'+' => {
                out.push(b' ');
                i += 1;
            }
            c => {
                out.push(c);
                i += 1;
            }
        }
    }
    String::from_utf8(out).map_err(|_| bad())
}

/// Whether a `Host` header names this machine's loopback: what a page served from 127.0.0.1
/// sends. Anything else is a DNS-rebinding attempt (a hostile site's name resolved to
/// 127.0.0.1) or a request meant for someone else.
pub fn is_loopback_host(host: &str) -> bool {
    let name = if let Some(rest) = host.strip_prefix('[') {
        rest.split_once(']').map_or(rest, |(n, _)| n)
    } else {
        host.rsplit_once(':').map_or(host, |(n, _)| n)
    };
    name.eq_ignore_ascii_case("localhost")
        || name
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        400 => "Bad Request",
        401 => "Unauthorized",
        403 => "Forbidden",
        404 => "Not Found",
        405 => "Method Not Allowed",
        408 => "Request Timeout",
        413 => "Content Too Large",
        415 => "Unsupported Media Type",
        422 => "Unprocessable Content",
        431 => "Request Header Fields Too Large",
        500 => "Internal Server Error",
        501 => "Not Implemented",
        502 => "Bad Gateway",
        503 => "Service Unavailable",
        505 => "HTTP Version Not Supported",
        _ => "Error",
    }
}

/// Writes one whole response.
pub async fn respond(
    stream: &mut TcpStream,
    status: u16,
    content_type: &str,
    body: &[u8],
    head_only: bool,
) -> std::io::Result<()> {
    respond_allowing(stream, status, content_type, body, head_only, "GET, HEAD").await
}

/// [`respond`] with a `Set-Cookie` header.
pub async fn respond_setting_cookie(
    stream: &mut TcpStream,
    content_type: &str,
    body: &[u8],
    cookie: &str,
) -> std::io::Result<()> {
    // A cookie value is made here of a name, hex and fixed attributes: no line break.
    debug_assert!(!cookie.contains(['\r', '\n']));
    let extra = format!("Set-Cookie: {cookie}\r\n");
    respond_full(stream, 200, content_type, body, false, &extra).await
}

async fn respond_allowing(
    stream: &mut TcpStream,
    status: u16,
    content_type: &str,
    body: &[u8],
    head_only: bool,
    allow: &str,
) -> std::io::Result<()> {
    let allow = if status == 405 {
        format!("Allow: {allow}\r\n")
    } else {
        String::new()
    };
    respond_full(stream, status, content_type, body, head_only, &allow).await
}

async fn respond_full(
    stream: &mut TcpStream,
    status: u16,
    content_type: &str,
    body: &[u8],
    head_only: bool,
    extra: &str,
) -> std::io::Result<()> {
    let head = format!(
        "HTTP/1.1 {status} {}\r\nContent-Type: {content_type}\r\nContent-Length: {}\r\n{COMMON_HEADERS}{extra}\r\n",
        reason(status),
        body.len(),
    );
    let write = async {
        stream.write_all(head.as_bytes()).await?;
        if !head_only {
            stream.write_all(body).await?;
        }
        stream.flush().await
    };
    tokio::time::timeout(WRITE_TIMEOUT, write)
        .await
        .unwrap_or_else(|_| Err(std::io::ErrorKind::TimedOut.into()))
}

/// A response the browser saves as the file `name` rather than shows.
pub async fn respond_download(
    stream: &mut TcpStream,
    content_type: &str,
    name: &str,
    body: &[u8],
    head_only: bool,
) -> std::io::Result<()> {
    // Names are made of ids and numbers ([A-Za-z0-9_-.]): nothing to quote.
    let head = format!(
        "HTTP/1.1 200 OK\r\nContent-Type: {content_type}\r\nContent-Length: {}\r\nContent-Disposition: attachment; filename=\"{name}\"\r\n{COMMON_HEADERS}\r\n",
        body.len(),
    );
    let write = async {
        stream.write_all(head.as_bytes()).await?;
        if !head_only {
            stream.write_all(body).await?;
        }
        stream.flush().await
    };
    tokio::time::timeout(WRITE_TIMEOUT, write)
        .await
        .unwrap_or_else(|_| Err(std::io::ErrorKind::TimedOut.into()))
}

/// A plain-text error response, then a graceful close: the client reads the status even if
/// the console did not read all it sent.
pub async fn respond_error(stream: &mut TcpStream, r: &Refusal) -> std::io::Result<()> {
    let body = format!("{}\n", r.message);
    respond_allowing(
        stream,
        r.status,
        "text/plain; charset=utf-8",
        body.as_bytes(),
        false,
        r.allow,
    )
    .await?;
    linger(stream).await;
    Ok(())
}

/// Ends the response (FIN), then discards what the client still sends, for at most [`LINGER`]
/// and [`LINGER_BYTES`], so that closing does not reset the connection under the response.
async fn linger(stream: &mut TcpStream) {
    if stream.shutdown().await.is_err() {
        return;
    }
    let drain = async {
        let mut sink = [0u8; 4096];
        let mut read = 0;
        while read < LINGER_BYTES {
            match stream.read(&mut sink).await {
                Ok(0) | Err(_) => return,
                Ok(n) => read += n,
            }
        }
    };
    let _ = tokio::time::timeout(LINGER, drain).await;
}

/// Starts a Server-Sent Events response; the body follows as events until the connection ends.
pub async fn start_events(stream: &mut TcpStream) -> std::io::Result<()> {
    let head = format!(
        "HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\n{COMMON_HEADERS}\r\nretry: 2000\n\n"
    );
    write_timed(stream, head.as_bytes()).await
}

/// One event: `event: <name>` and its data on one line (JSON has no raw newline).
pub async fn send_event(stream: &mut TcpStream, name: &str, data: &str) -> std::io::Result<()> {
    debug_assert!(!data.contains('\n'));
    let text = format!("event: {name}\ndata: {data}\n\n");
    write_timed(stream, text.as_bytes()).await
}

async fn write_timed(stream: &mut TcpStream, bytes: &[u8]) -> std::io::Result<()> {
    tokio::time::timeout(WRITE_TIMEOUT, stream.write_all(bytes))
        .await
        .unwrap_or_else(|_| Err(std::io::ErrorKind::TimedOut.into()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_get_with_a_query() {
        let r = parse_head(
            b"GET /api/history?building=hq&sensor=acc-01&from_ns=5&note=a%20b+c HTTP/1.1\r\nHost: 127.0.0.1:9760\r\nAccept: */*",
        )
        .unwrap();
        assert!(!r.head_only);
        assert_eq!(r.path, "/api/history");
        assert_eq!(r.host.as_deref(), Some("127.0.0.1:9760"));
        assert_eq!(
            r.query,
            [
                ("building".into(), "hq".into()),
                ("sensor".into(), "acc-01".into()),
                ("from_ns".into(), "5".into()),
                ("note".into(), "a b c".into())
            ]
        );
    }

    #[test]
    fn what_is_refused_and_why() {
        let status = |h: &[u8]| parse_head(h).unwrap_err().status;
        assert_eq!(status(b"DELETE / HTTP/1.1"), 405);
        assert_eq!(status(b"PUT / HTTP/1.1"), 405);
        assert_eq!(
            status(b"POST /api/alerts/ack HTTP/1.1\r\nContent-Length: 16385"),
            413
        );
        assert_eq!(
            status(b"POST /api/alerts/ack HTTP/1.1\r\nContent-Length: x"),
            400
        );
        assert_eq!(
            status(b"POST / HTTP/1.1\r\nOrigin: a\r\nOrigin: b"),
            400,
            "two origins"
        );
        let post = parse_head(
            b"POST /api/alerts/ack HTTP/1.1\r\nHost: 127.0.0.1\r\nOrigin: http://127.0.0.1\r\nContent-Type: application/json\r\nContent-Length: 12",
        )
        .unwrap();
        assert!(post.post);
        assert_eq!(post.content_length, 12);
        assert_eq!(post.origin.as_deref(), Some("http://127.0.0.1"));
        assert_eq!(status(b"GET / HTTP/2\r\nHost: x"), 505);
        assert_eq!(status(b"GET /"), 400);
        assert_eq!(status(b"GET  / HTTP/1.1"), 400);
        assert_eq!(status(b"GET http://evil/ HTTP/1.1"), 400);
        assert_eq!(status(b"GET / HTTP/1.1\r\nContent-Length: 5"), 400);
        assert_eq!(status(b"GET / HTTP/1.1\r\nTransfer-Encoding: chunked"), 400);
        assert_eq!(status(b"GET / HTTP/1.1\r\nno colon"), 400);
        assert_eq!(status(b"GET /?a=1&a=2 HTTP/1.1"), 400);
        assert_eq!(status(b"GET /?a=%zz HTTP/1.1"), 400);
        assert_eq!(status(b"GET /?a=%ff HTTP/1.1"), 400, "not UTF-8");
        assert_eq!(status(b"GET /?a=% HTTP/1.1"), 400);
        assert_eq!(status(&[b'G', b'E', b'T', b' ', 0xff, b' ']), 400);
        assert_eq!(
            status(b"GET / HTTP/1.1\r\nHost: evil.example\r\nHost: 127.0.0.1"),
            400,
            "two hosts"
        );
        assert!(parse_head(b"HEAD / HTTP/1.0").unwrap().head_only);
    }

    #[test]
    fn loopback_hosts() {
        for ok in [
            "127.0.0.1:9760",
            "localhost:1",
            "LOCALHOST",
            "[::1]:9760",
            "127.8.9.1",
            "[::1]",
        ] {
            assert!(is_loopback_host(ok), "{ok}");
        }
        for bad in [
            "evil.example:9760",
            "10.0.0.1:9760",
            "[fe80::1]:1",
            "",
            "localhost.evil",
        ] {
            assert!(!is_loopback_host(bad), "{bad}");
        }
    }
}
