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
    #[error("the daemon refused: {message} (HTTP {status}, {code})")]
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
    /// A downloaded file could not be written.
    #[error("cannot write {path}")]
    Write {
        /// The file.
        path: std::path::PathBuf,
        /// The error.
        #[source]
        source: std::io::Error,
    },
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

/// An open streamed response: status, headers (names lower-cased) and a reader of the body.
pub type OpenStream = (u16, Vec<(String, String)>, Box<dyn BufRead + Send>);

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

    /// DELETE `path`; a non-2xx status becomes [`ClientError::Api`].
    pub fn delete(&self, path: &str) -> Result<(), ClientError> {
        self.request("DELETE", path, None).map(|_| ())
    }

    /// GET `path` and stream its body into the file `dest` (through `dest` + `.part`, renamed when
    /// complete, so a cut download leaves no file that looks whole). Returns the bytes written.
    pub fn download(&self, path: &str, dest: &std::path::Path) -> Result<u64, ClientError> {
        let stream = self.send("GET", path, None, "*/*")?;
        let mut reader = BufReader::new(stream);
        let (status, headers) = read_head(&mut reader).map_err(|e| e.with_addr(self.addr))?;
        let chunked = headers.iter().any(|(k, v)| k == "transfer-encoding" && v.contains("chunked"));
        let mut body: Box<dyn Read> = if chunked { Box::new(ChunkedReader::new(reader)) } else { Box::new(reader) };
        if !(200..300).contains(&status) {
            let mut text = Vec::new();
            body.take(64 * 1024).read_to_end(&mut text).map_err(self.io())?;
            let r = Response { status, headers, body: text };
            let (code, message) = match r.json() {
                Ok(v) => (
                    v["error"]["code"].as_str().unwrap_or("unknown").to_owned(),
                    v["error"]["message"].as_str().unwrap_or("").to_owned(),
                ),
                Err(_) => ("unknown".to_owned(), String::from_utf8_lossy(&r.body).into_owned()),
            };
            return Err(ClientError::Api { status, code, message });
        }
        let length = headers.iter().find(|(k, _)| k == "content-length").and_then(|(_, v)| v.parse::<u64>().ok());
        if let Some(n) = length.filter(|_| !chunked) {
            body = Box::new(body.take(n));
        }
        let mut part = dest.as_os_str().to_owned();
        part.push(".part");
        let part = std::path::PathBuf::from(part);
        let write_err = |source| ClientError::Write { path: part.clone(), source };
        let mut file = std::fs::File::create(&part).map_err(write_err)?;
        let n = std::io::copy(&mut body, &mut file).map_err(self.io())?;
        if length.is_some_and(|want| !chunked && want != n) {
            let _ = std::fs::remove_file(&part);
            return Err(ClientError::Malformed("the body ended before its Content-Length"));
        }
        file.sync_all().map_err(write_err)?;
        std::fs::rename(&part, dest).map_err(|source| ClientError::Write { path: dest.to_owned(), source })?;
        Ok(n)
    }

    /// GET `path` and return the status, the headers and a reader of the (de-chunked) body as it
    /// arrives, for streams (`camera.mjpg`, `events`).
    pub fn open_stream(&self, path: &str) -> Result<OpenStream, ClientError> {
        let stream = self.send("GET", path, None, "*/*")?;
        let mut reader = BufReader::new(stream);
        let (status, headers) = read_head(&mut reader).map_err(|e| e.with_addr(self.addr))?;
        let chunked = headers.iter().any(|(k, v)| k == "transfer-encoding" && v.contains("chunked"));
        let body: Box<dyn BufRead + Send> =
            if chunked { Box::new(BufReader::new(ChunkedReader::new(reader))) } else { Box::new(reader) };
        Ok((status, headers, body))
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
    /// until it returns `false` or the stream ends (other events are skipped).
    pub fn watch(&self, mut on_event: impl FnMut(&serde_json::Value) -> bool) -> Result<(), ClientError> {
        self.watch_events(|name, v| name != "progress" || on_event(v))
    }

    /// Follow the event stream, calling `on_event` with each event's name (`progress`, `model`,
    /// `devices`...; `message` when it has none) and JSON data until it returns `false` or the
    /// stream ends.
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
            } else if let Some(e) = l.strip_prefix("event:") {
                e.trim().clone_into(&mut name);
            } else if l.is_empty() && !data.is_empty() {
                let v: serde_json::Value = serde_json::from_str(&data).map_err(ClientError::Json)?;
                data.clear();
                let event = if name.is_empty() { "message" } else { name.as_str() };
                if !on_event(event, &v) {
                    return Ok(());
                }
                name.clear();
            } else if l.is_empty() {
                name.clear();
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

/// Download scan `id`'s whole directory as `archive.zip` into `dest`, then, with `unpack`, write
/// every file of it under `out` (frames in `out/frames/`). Returns the files unpacked.
pub fn fetch_archive(
    client: &Client,
    id: &str,
    dest: &std::path::Path,
    unpack: Option<&std::path::Path>,
) -> Result<Vec<String>, FetchError> {
    client.download(&format!("/api/v1/scans/{id}/archive.zip"), dest).map_err(FetchError::Client)?;
    let Some(out) = unpack else { return Ok(Vec::new()) };
    let bytes = std::fs::read(dest).map_err(|source| FetchError::Write { path: dest.to_owned(), source })?;
    let entries =
        stored_zip_entries(&bytes).map_err(|problem| FetchError::Archive { path: dest.to_owned(), problem })?;
    let mut names = Vec::new();
    for (name, data) in entries {
        let safe = !name.is_empty()
            && !name.starts_with('/')
            && name.split('/').all(|c| !c.is_empty() && c != "." && c != "..");
        if !safe {
            return Err(FetchError::Archive {
                path: dest.to_owned(),
                problem: format!("entry `{name}` leaves the directory"),
            });
        }
        let path = out.join(&name);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(|source| FetchError::Write { path: parent.to_owned(), source })?;
        }
        crate::atomic::write_atomic(&path, data).map_err(FetchError::WriteFile)?;
        names.push(name);
    }
    Ok(names)
}

/// The entries of a zip file of stored (uncompressed) entries, as the daemon's archive writes it,
/// each checked against its CRC-32. The problem, in words, on anything else.
pub fn stored_zip_entries(zip: &[u8]) -> Result<Vec<(String, &[u8])>, String> {
    let u16_at = |i: usize| zip.get(i..i + 2).map(|b| u16::from_le_bytes([b[0], b[1]]) as usize);
    let u32_at = |i: usize| zip.get(i..i + 4).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize);
    let eocd = (0..zip.len().saturating_sub(21))
        .rev()
        .find(|&i| u32_at(i) == Some(0x0605_4b50))
        .ok_or("no end of central directory record")?;
    let count = u16_at(eocd + 10).ok_or("truncated end record")?;
    let mut at = u32_at(eocd + 16).ok_or("truncated end record")?;
    let mut out = Vec::with_capacity(count);
    for n in 0..count {
        let bad = |what: &str| format!("central directory entry {n}: {what}");
        if u32_at(at) != Some(0x0201_4b50) {
            return Err(bad("bad signature"));
        }
        let method = u16_at(at + 10).ok_or_else(|| bad("truncated"))?;
        let crc = u32_at(at + 16).ok_or_else(|| bad("truncated"))? as u32;
        let size = u32_at(at + 20).ok_or_else(|| bad("truncated"))?;
        let name_len = u16_at(at + 28).ok_or_else(|| bad("truncated"))?;
        let extra = u16_at(at + 30).ok_or_else(|| bad("truncated"))?;
        let comment = u16_at(at + 32).ok_or_else(|| bad("truncated"))?;
        let local = u32_at(at + 42).ok_or_else(|| bad("truncated"))?;
        let name = zip.get(at + 46..at + 46 + name_len).ok_or_else(|| bad("truncated name"))?;
        let name = String::from_utf8_lossy(name).into_owned();
        if method != 0 {
            return Err(format!("{name}: compression method {method} (only stored entries are read)"));
        }
        let local_name = u16_at(local + 26).ok_or_else(|| bad("truncated local header"))?;
        let local_extra = u16_at(local + 28).ok_or_else(|| bad("truncated local header"))?;
        let start = local + 30 + local_name + local_extra;
        let data = zip.get(start..start + size).ok_or_else(|| format!("{name}: data cut short"))?;
        if crc32fast::hash(data) != crc {
            return Err(format!("{name}: CRC-32 mismatch"));
        }
        out.push((name, data));
        at += 46 + name_len + extra + comment;
    }
    Ok(out)
}

/// One part of a `multipart/x-mixed-replace` stream (as `camera.mjpg` sends it).
#[derive(Debug, Clone)]
pub struct MultipartPart {
    /// The part's headers, names lower-cased.
    pub headers: Vec<(String, String)>,
    /// Its body (`Content-Length` bytes).
    pub body: Vec<u8>,
}

/// Read the next part of a multipart stream with boundary `boundary` (without the leading `--`):
/// skips to the boundary line, reads the part's headers and its `Content-Length` bytes. `None` at
/// the end of the stream.
pub fn read_multipart_part(r: &mut dyn BufRead, boundary: &str) -> std::io::Result<Option<MultipartPart>> {
    let invalid = |m: &str| std::io::Error::new(std::io::ErrorKind::InvalidData, m.to_owned());
    let marker = format!("--{boundary}");
    let mut line = String::new();
    loop {
        line.clear();
        if r.read_line(&mut line)? == 0 {
            return Ok(None);
        }
        if line.trim_end() == marker {
            break;
        }
    }
    let mut headers = Vec::new();
    loop {
        line.clear();
        if r.read_line(&mut line)? == 0 {
            return Err(invalid("part headers cut short"));
        }
        let l = line.trim_end_matches(['\r', '\n']);
        if l.is_empty() {
            break;
        }
        let (k, v) = l.split_once(':').ok_or_else(|| invalid("part header without a colon"))?;
        headers.push((k.trim().to_ascii_lowercase(), v.trim().to_owned()));
        if headers.len() > 50 {
            return Err(invalid("too many part headers"));
        }
    }
    let len = headers
        .iter()
        .find(|(k, _)| k == "content-length")
        .and_then(|(_, v)| v.parse::<usize>().ok())
        .ok_or_else(|| invalid("part without a Content-Length"))?;
    let mut body = vec![0; len];
    r.read_exact(&mut body)?;
    Ok(Some(MultipartPart { headers, body }))
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
    /// The downloaded archive cannot be unpacked.
    #[error("{path}: {problem}")]
    Archive {
        /// The archive.
        path: std::path::PathBuf,
        /// What is wrong.
        problem: String,
    },
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
