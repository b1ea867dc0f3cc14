//! A small blocking HTTP/1.1 client for the daemon's API (used by the `scanrig` CLI and tests):
//! one request per connection, `Content-Length` and chunked bodies, and a Server-Sent Events reader.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream, ToSocketAddrs};
use std::time::Duration;

/// Why a request failed.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The daemon address does not resolve.
    #[error("cannot resolve {0}")]
    Resolve(String),
    /// Connecting, sending or receiving failed.
    #[error("I/O with the daemon at {addr}")]
    Io {
        /// The daemon.
        addr: SocketAddr,
        /// The error.
        #[source]
        source: std::io::Error,
    },
    /// The daemon answered something that is not HTTP.
    #[error("malformed HTTP response: {0}")]
    Malformed(&'static str),
    /// The daemon answered with an error.
    #[error("{status} {code}: {message}")]
    Api {
        /// HTTP status.
        status: u16,
        /// The error code from the JSON body.
        code: String,
        /// The message from the JSON body.
        message: String,
    },
    /// A JSON body could not be parsed.
    #[error("malformed JSON from the daemon")]
    Json(#[source] serde_json::Error),
}

/// An HTTP response.
#[derive(Debug, Clone)]
pub struct Response {
    /// Status code.
    pub status: u16,
    /// Headers, names lower-cased.
    pub headers: Vec<(String, String)>,
    /// The body.
    pub body: Vec<u8>,
}

impl Response {
    /// The body as JSON.
    pub fn json(&self) -> Result<serde_json::Value, ClientError> {
        serde_json::from_slice(&self.body).map_err(ClientError::Json)
    }
    /// A header's value.
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
    }
}

/// A client for one daemon.
#[derive(Debug, Clone)]
pub struct Client {
    addr: SocketAddr,
    host: String,
    token: Option<String>,
    timeout: Duration,
}

impl Client {
    /// A client for the daemon at `addr` (`host:port`), with an optional bearer token.
    pub fn new(addr: &str, token: Option<String>) -> Result<Client, ClientError> {
        let sock = addr
            .to_socket_addrs()
            .map_err(|_| ClientError::Resolve(addr.to_owned()))?
            .next()
            .ok_or_else(|| ClientError::Resolve(addr.to_owned()))?;
        Ok(Client { addr: sock, host: addr.to_owned(), token, timeout: Duration::from_secs(30) })
    }

    /// Set the connect/read timeout.
    pub fn with_timeout(mut self, timeout: Duration) -> Client {
        self.timeout = timeout;
        self
    }

    fn io(&self) -> impl Fn(std::io::Error) -> ClientError + '_ {
        move |source| ClientError::Io { addr: self.addr, source }
    }

    fn send(&self, method: &str, path: &str, body: Option<&[u8]>, accept: &str) -> Result<TcpStream, ClientError> {
        let mut stream = TcpStream::connect_timeout(&self.addr, self.timeout).map_err(self.io())?;
        stream.set_read_timeout(Some(self.timeout)).map_err(self.io())?;
        stream.set_write_timeout(Some(self.timeout)).map_err(self.io())?;
        let mut head =
            format!("{method} {path} HTTP/1.1\r\nHost: {}\r\nConnection: close\r\nAccept: {accept}\r\n", self.host);
        if let Some(t) = &self.token {
            head.push_str(&format!("Authorization: Bearer {t}\r\n"));
        }
        if let Some(b) = body {
            head.push_str(&format!("Content-Type: application/json\r\nContent-Length: {}\r\n", b.len()));
        }
        head.push_str("\r\n");
        stream.write_all(head.as_bytes()).map_err(self.io())?;
        if let Some(b) = body {
            stream.write_all(b).map_err(self.io())?;
        }
        Ok(stream)
    }

    /// Send a raw request and return the response whatever its status.
    pub fn raw(&self, method: &str, path: &str, body: Option<&[u8]>) -> Result<Response, ClientError> {
        let stream = self.send(method, path, body, "*/*")?;
        let mut reader = BufReader::new(stream);
        let (status, headers) = read_head(&mut reader).map_err(|e| e.with_addr(self.addr))?;
        let chunked = headers.iter().any(|(k, v)| k == "transfer-encoding" && v.contains("chunked"));
        let mut body = Vec::new();
        if chunked {
            ChunkedReader::new(reader).read_to_end(&mut body).map_err(self.io())?;
        } else if let Some(len) =
            headers.iter().find(|(k, _)| k == "content-length").and_then(|(_, v)| v.parse::<u64>().ok())
        {
            reader.take(len).read_to_end(&mut body).map_err(self.io())?;
        } else {
            reader.read_to_end(&mut body).map_err(self.io())?;
        }
        Ok(Response { status, headers, body })
    }

    /// Send a request; a non-2xx status becomes [`ClientError::Api`].
    pub fn request(&self, method: &str, path: &str, body: Option<&[u8]>) -> Result<Response, ClientError> {
        let r = self.raw(method, path, body)?;
        if (200..300).contains(&r.status) {
            return Ok(r);
        }
        let (code, message) = match r.json() {
            Ok(v) => (
                v["error"]["code"].as_str().unwrap_or("unknown").to_owned(),
                v["error"]["message"].as_str().unwrap_or("").to_owned(),
            ),
            Err(_) => ("unknown".to_owned(), String::from_utf8_lossy(&r.body).into_owned()),
        };
        Err(ClientError::Api { status: r.status, code, message })
    }

    /// GET a JSON document.
    pub fn get_json(&self, path: &str) -> Result<serde_json::Value, ClientError> {
        self.request("GET", path, None)?.json()
    }

    /// POST a JSON body and return the JSON answer.
    pub fn post_json(&self, path: &str, body: &serde_json::Value) -> Result<serde_json::Value, ClientError> {
        let bytes = serde_json::to_vec(body).map_err(ClientError::Json)?;
        self.request("POST", path, Some(&bytes))?.json()
    }

    /// Follow the progress event stream, calling `on_event` with each `progress` event's JSON data
    /// until it returns `false` or the stream ends.
    pub fn watch(&self, mut on_event: impl FnMut(&serde_json::Value) -> bool) -> Result<(), ClientError> {
        self.watch_events(|name, v| name != "progress" || on_event(v))
    }

    /// Follow the event stream, calling `on_event` with each event's name (`progress`, `model`, ...)
    /// and JSON data until it returns `false` or the stream ends.
    pub fn watch_events(&self, mut on_event: impl FnMut(&str, &serde_json::Value) -> bool) -> Result<(), ClientError> {
        let stream = self.send("GET", "/api/v1/events", None, "text/event-stream")?;
        let mut reader = BufReader::new(stream);
        let (status, headers) = read_head(&mut reader).map_err(|e| e.with_addr(self.addr))?;
        if status != 200 {
            return Err(ClientError::Api {
                status,
                code: "events".into(),
                message: "cannot open the event stream".into(),
            });
        }
        let chunked = headers.iter().any(|(k, v)| k == "transfer-encoding" && v.contains("chunked"));
        let body: Box<dyn Read> = if chunked { Box::new(ChunkedReader::new(reader)) } else { Box::new(reader) };
        let mut lines = BufReader::new(body);
        let mut data = String::new();
        let mut name = String::new();
        let mut line = String::new();
        loop {
            line.clear();
            if lines.read_line(&mut line).map_err(self.io())? == 0 {
                return Ok(());
            }
            let l = line.trim_end_matches(['\r', '\n']);
            if let Some(d) = l.strip_prefix("data:") {
                data.push_str(d.trim_start());
            } else if let Some(n) = l.strip_prefix("event:") {
                n.trim_start().clone_into(&mut name);
            } else if l.is_empty() && !data.is_empty() {
                let v: serde_json::Value = serde_json::from_str(&data).map_err(ClientError::Json)?;
                data.clear();
                // An event without a name is a `message` (the SSE default).
                let event = if name.is_empty() { "message" } else { name.as_str() };
                let more = on_event(event, &v);
                name.clear();
                if !more {
                    return Ok(());
                }
            }
        }
    }
}

/// Download scan `id`'s results (`model.ply`, `model.stl`, `model.obj`, `voxels.ply`,
/// `report.json`, `meta.json`) into `out`, each written atomically. Returns the names written.
pub fn fetch_results(client: &Client, id: &str, out: &std::path::Path) -> Result<Vec<&'static str>, FetchError> {
    std::fs::create_dir_all(out).map_err(|source| FetchError::Write { path: out.to_owned(), source })?;
    let mut written = Vec::new();
    for name in ["report.json", "meta.json", "model.ply", "model.stl", "model.obj", "voxels.ply"] {
        let r = client.request("GET", &format!("/api/v1/scans/{id}/files/{name}"), None).map_err(FetchError::Client)?;
        let path = out.join(name);
        crate::atomic::write_atomic(&path, &r.body).map_err(FetchError::WriteFile)?;
        written.push(name);
    }
    Ok(written)
}

/// Why fetching results failed.
#[derive(Debug, thiserror::Error)]
pub enum FetchError {
    /// The request failed.
    #[error("download failed")]
    Client(#[source] ClientError),
    /// The output directory cannot be created.
    #[error("cannot create {path}")]
    Write {
        /// The directory.
        path: std::path::PathBuf,
        /// The error.
        #[source]
        source: std::io::Error,
    },
    /// A file cannot be written.
    #[error("cannot write a result file")]
    WriteFile(#[source] crate::atomic::AtomicWriteError),
}

enum HeadError {
    Io(std::io::Error),
    Malformed(&'static str),
}

impl HeadError {
    fn with_addr(self, addr: SocketAddr) -> ClientError {
        match self {
            HeadError::Io(source) => ClientError::Io { addr, source },
            HeadError::Malformed(m) => ClientError::Malformed(m),
        }
    }
}

fn read_head(r: &mut impl BufRead) -> Result<(u16, Vec<(String, String)>), HeadError> {
    let mut line = String::new();
    r.read_line(&mut line).map_err(HeadError::Io)?;
    let status = line
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse::<u16>().ok())
        .ok_or(HeadError::Malformed("no status line"))?;
    let mut headers = Vec::new();
    loop {
        line.clear();
        if r.read_line(&mut line).map_err(HeadError::Io)? == 0 {
            return Err(HeadError::Malformed("headers cut short"));
        }
        let l = line.trim_end_matches(['\r', '\n']);
        if l.is_empty() {
            return Ok((status, headers));
        }
        let (k, v) = l.split_once(':').ok_or(HeadError::Malformed("header without a colon"))?;
        headers.push((k.trim().to_ascii_lowercase(), v.trim().to_owned()));
        if headers.len() > 100 {
            return Err(HeadError::Malformed("too many headers"));
        }
    }
}

/// Decodes a `Transfer-Encoding: chunked` body.
struct ChunkedReader<R> {
    inner: R,
    left: u64,
    done: bool,
}

impl<R: BufRead> ChunkedReader<R> {
    fn new(inner: R) -> Self {
        ChunkedReader { inner, left: 0, done: false }
    }
}

impl<R: BufRead> Read for ChunkedReader<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        if self.done || buf.is_empty() {
            return Ok(0);
        }
        if self.left == 0 {
            let mut line = String::new();
            if self.inner.read_line(&mut line)? == 0 {
                self.done = true;
                return Ok(0);
            }
            if line.trim().is_empty() {
                // The CRLF that ends the previous chunk.
                line.clear();
                if self.inner.read_line(&mut line)? == 0 {
                    self.done = true;
                    return Ok(0);
                }
            }
            let size = line.trim().split(';').next().unwrap_or("");
            self.left = u64::from_str_radix(size, 16)
                .map_err(|_| std::io::Error::new(std::io::ErrorKind::InvalidData, "bad chunk size"))?;
            if self.left == 0 {
                self.done = true;
                return Ok(0);
            }
        }
        let want = buf.len().min(usize::try_from(self.left).unwrap_or(usize::MAX));
        let n = self.inner.read(&mut buf[..want])?;
        if n == 0 {
            return Err(std::io::Error::new(std::io::ErrorKind::UnexpectedEof, "chunk cut short"));
        }
        self.left -= n as u64;
        Ok(n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chunked_bodies_are_decoded() {
        let raw = b"5\r\nhello\r\n7;ext=1\r\n, world\r\n0\r\n\r\n";
        let mut out = String::new();
        ChunkedReader::new(&raw[..]).read_to_string(&mut out).expect("read");
        assert_eq!(out, "hello, world");
    }

    #[test]
    fn a_bad_chunk_size_is_an_error_not_a_panic() {
        let raw = b"zz\r\nhello\r\n";
        let mut out = Vec::new();
        assert!(ChunkedReader::new(&raw[..]).read_to_end(&mut out).is_err());
    }

    #[test]
    fn heads_are_parsed_and_garbage_rejected() {
        let mut ok = &b"HTTP/1.1 404 Not Found\r\nContent-Length: 2\r\nX-A: b\r\n\r\n{}"[..];
        let (status, headers) = read_head(&mut ok).ok().expect("head");
        assert_eq!(status, 404);
        assert_eq!(headers[0], ("content-length".to_owned(), "2".to_owned()));
        let mut bad = &b"garbage\r\n\r\n"[..];
        assert!(read_head(&mut bad).is_err());
    }
}
