//! The HTTP/1.1 server under the API: hyper connections with a header-read timeout, an idle
//! timeout and a bounded shutdown, so that half-sent requests or silent clients can neither hold
//! a connection for ever nor delay SIGTERM (and with it the parking of the rig).
//!
//! - A request head must arrive within [`Limits::header_read`] of its first byte, else the
//!   connection is closed.
//! - A connection on which nothing is read or written for [`Limits::idle`] is closed (event
//!   streams send a keep-alive comment every 10 s, so they stay open).
//! - At shutdown, idle connections close at once and busy ones get [`Limits::shutdown_grace`] to
//!   finish their response; then they are dropped.
//! - hyper answers some malformed requests itself (400, 414 URI too long, 431 headers too large)
//!   with an empty body; [`JsonErrors`] rewrites those answers to the API's JSON error shape.

use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio_util::sync::CancellationToken;

/// The server's timeouts and sizes.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    /// Longest time from a request's first byte to the end of its head.
    pub header_read: Duration,
    /// Longest time a connection may see no byte read or written.
    pub idle: Duration,
    /// How long busy connections may go on after shutdown starts.
    pub shutdown_grace: Duration,
    /// Largest request head (request line and headers), bytes; hyper answers 431 above it.
    pub max_head: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            header_read: Duration::from_secs(5),
            idle: Duration::from_secs(60),
            shutdown_grace: Duration::from_secs(2),
            max_head: 64 * 1024,
        }
    }
}

/// Serve `router` on `listener` until `shutdown` is cancelled, then close every connection within
/// [`Limits::shutdown_grace`].
pub async fn serve(
    listener: TcpListener,
    router: axum::Router,
    shutdown: CancellationToken,
    limits: Limits,
) -> io::Result<()> {
    let mut conns = tokio::task::JoinSet::new();
    loop {
        tokio::select! {
            _ = shutdown.cancelled() => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => {
                    let _ = stream.set_nodelay(true);
                    conns.spawn(connection(stream, router.clone(), shutdown.clone(), limits));
                }
                Err(e) => {
                    // Out of descriptors or a connection reset before accept: keep serving.
                    tracing::warn!(error = %e, "accept failed");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            },
            Some(_) = conns.join_next(), if !conns.is_empty() => {}
        }
    }
    drop(listener);
    while conns.join_next().await.is_some() {}
    Ok(())
}

async fn connection(stream: TcpStream, router: axum::Router, shutdown: CancellationToken, limits: Limits) {
    let base = Instant::now();
    let activity = Arc::new(AtomicU64::new(0));
    let io = TokioIo::new(JsonErrors::new(stream, activity.clone(), base));
    let service = hyper_util::service::TowerToHyperService::new(router);
    let mut builder = hyper::server::conn::http1::Builder::new();
    builder.timer(TokioTimer::new()).header_read_timeout(limits.header_read).max_buf_size(limits.max_head.max(8192));
    let conn = builder.serve_connection(io, service);
    tokio::pin!(conn);
    let mut grace_until: Option<tokio::time::Instant> = None;
    loop {
        let last = base + Duration::from_millis(activity.load(Ordering::Relaxed));
        let idle_at = tokio::time::Instant::from_std(last + limits.idle);
        let stop_at = grace_until.map_or(idle_at, |g| g.min(idle_at));
        tokio::select! {
            result = conn.as_mut() => {
                if let Err(e) = result {
                    tracing::debug!(error = %e, "connection ended with an error");
                }
                return;
            }
            _ = shutdown.cancelled(), if grace_until.is_none() => {
                conn.as_mut().graceful_shutdown();
                grace_until = Some(tokio::time::Instant::now() + limits.shutdown_grace);
            }
            _ = tokio::time::sleep_until(stop_at) => {
                let now = tokio::time::Instant::now();
                let last = base + Duration::from_millis(activity.load(Ordering::Relaxed));
                if grace_until.is_some_and(|g| now >= g) {
                    tracing::debug!("closing a connection still busy after the shutdown grace");
                    return;
                }
                if now.into_std() >= last + limits.idle {
                    tracing::debug!("closing an idle connection");
                    return;
                }
            }
        }
    }
}

/// The connection's socket: records activity for the idle timeout and replaces hyper's own
/// empty-bodied error answers by JSON ones.
struct JsonErrors<S> {
    inner: S,
    activity: Arc<AtomicU64>,
    base: Instant,
    /// A replacement being written: the bytes, how many are written, how many hyper gave.
    replacement: Option<(Vec<u8>, usize, usize)>,
}

impl<S> JsonErrors<S> {
    fn new(inner: S, activity: Arc<AtomicU64>, base: Instant) -> Self {
        JsonErrors { inner, activity, base, replacement: None }
    }

    fn touch(&self) {
        let ms = u64::try_from(self.base.elapsed().as_millis()).unwrap_or(u64::MAX);
        self.activity.store(ms, Ordering::Relaxed);
    }
}

/// If `buf` is exactly a response head with status >= 400 and `content-length: 0` (the API itself
/// never sends one: its errors carry a JSON body), the same answer with a JSON body.
pub fn json_error_for_bare_head(buf: &[u8]) -> Option<Vec<u8>> {
    let head = std::str::from_utf8(buf).ok()?;
    let rest = head.strip_prefix("HTTP/1.")?;
    if !head.ends_with("\r\n\r\n") || head.matches("\r\n\r\n").count() != 1 {
        return None;
    }
    let status_line = rest.split("\r\n").next()?;
    let mut parts = status_line.splitn(3, ' ');
    let _version = parts.next()?;
    let code: u16 = parts.next()?.parse().ok()?;
    let reason = parts.next().unwrap_or("error");
    if code < 400 || !head.to_ascii_lowercase().contains("\r\ncontent-length: 0\r\n") {
        return None;
    }
    let name = match code {
        400 => "bad_request",
        408 => "timeout",
        413 => "too_large",
        414 => "uri_too_long",
        431 => "headers_too_large",
        505 => "http_version",
        _ => "http_error",
    };
    let message = match code {
        414 => "the request target is too long".to_owned(),
        431 => "the request headers are too large".to_owned(),
        _ => reason.to_ascii_lowercase(),
    };
    let body = serde_json::json!({"error": {"code": name, "message": message}}).to_string();
    Some(
        format!(
            "HTTP/1.1 {code} {reason}\r\ncontent-type: application/json\r\ncontent-length: {}\r\nconnection: close\r\n\r\n{body}",
            body.len()
        )
        .into_bytes(),
    )
}

impl<S: AsyncRead + Unpin> AsyncRead for JsonErrors<S> {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        let before = buf.filled().len();
        let r = Pin::new(&mut self.inner).poll_read(cx, buf);
        if matches!(r, Poll::Ready(Ok(()))) && buf.filled().len() > before {
            self.touch();
        }
        r
    }
}

impl<S: AsyncWrite + Unpin> AsyncWrite for JsonErrors<S> {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        if self.replacement.is_none() {
            if let Some(bytes) = json_error_for_bare_head(buf) {
                self.replacement = Some((bytes, 0, buf.len()));
            }
        }
        let this = &mut *self;
        if let Some((bytes, written, claimed)) = &mut this.replacement {
            while *written < bytes.len() {
                match Pin::new(&mut this.inner).poll_write(cx, &bytes[*written..]) {
                    Poll::Ready(Ok(0)) => return Poll::Ready(Err(io::ErrorKind::WriteZero.into())),
                    Poll::Ready(Ok(n)) => *written += n,
                    Poll::Ready(Err(e)) => return Poll::Ready(Err(e)),
                    Poll::Pending => return Poll::Pending,
                }
            }
            let n = *claimed;
            this.replacement = None;
            this.touch();
            return Poll::Ready(Ok(n));
        }
        let r = Pin::new(&mut this.inner).poll_write(cx, buf);
        if matches!(r, Poll::Ready(Ok(n)) if n > 0) {
            this.touch();
        }
        r
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }

    fn is_write_vectored(&self) -> bool {
        // hyper then hands a whole response head to one poll_write, which the rewrite needs.
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_bare_error_heads_are_rewritten() {
        let bare = b"HTTP/1.1 431 Request Header Fields Too Large\r\ncontent-length: 0\r\ndate: x\r\n\r\n";
        let out = String::from_utf8(json_error_for_bare_head(bare).expect("rewritten")).expect("utf8");
        assert!(out.starts_with("HTTP/1.1 431 "), "{out}");
        let body = out.split("\r\n\r\n").nth(1).expect("body");
        let v: serde_json::Value = serde_json::from_str(body).expect("json");
        assert_eq!(v["error"]["code"], "headers_too_large");
        assert!(json_error_for_bare_head(b"HTTP/1.1 200 OK\r\ncontent-length: 0\r\n\r\n").is_none());
        assert!(json_error_for_bare_head(b"HTTP/1.1 404 Not Found\r\ncontent-length: 12\r\n\r\n").is_none());
        assert!(json_error_for_bare_head(b"HTTP/1.1 400 Bad Request\r\ncontent-length: 0\r\n\r\nxx").is_none());
    }
}
