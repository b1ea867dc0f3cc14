//! Console sign-in: a browser gives the daemon's bearer token once (`POST /api/v1/session`) and
//! then carries a session cookie, because the page's live parts cannot send an `Authorization`
//! header (`EventSource` for `/api/v1/events`, `<img>` for `/api/v1/camera.mjpg`).
//!
//! The cookie holds a random 256-bit session id, never the token: `HttpOnly` (scripts cannot read
//! it), `SameSite=Strict` (another site's page cannot make the browser send it) and `Path=/`.
//! Sessions live in the daemon's memory: at most [`MAX_SESSIONS`], the oldest dropped first, each
//! valid for [`LIFETIME`]; a restart or a changed token signs every browser out. A request that is
//! authorised by the cookie and changes something must also come from the daemon's own page
//! (its `Origin`, when the browser sends one, is the daemon's own `Host`).

use std::collections::VecDeque;
use std::io::Read;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use axum::http::{header, HeaderMap};

/// Name of the session cookie.
pub const COOKIE: &str = "scanrig_session";
/// Most sessions kept at once; signing in beyond that signs the oldest session out.
pub const MAX_SESSIONS: usize = 64;
/// How long a session is valid after sign-in (30 days).
pub const LIFETIME: Duration = Duration::from_secs(30 * 24 * 3600);
/// Bytes of randomness in a session id (hex-encoded in the cookie: twice as many characters).
const ID_BYTES: usize = 32;

/// The signed-in browsers.
#[derive(Debug, Default)]
pub struct Sessions {
    live: Mutex<VecDeque<(String, Instant)>>,
}

impl Sessions {
    /// An empty set.
    pub fn new() -> Sessions {
        Sessions::default()
    }

    /// A new session id (from the kernel's random source), remembered until it expires, is
    /// ended, or is pushed out by [`MAX_SESSIONS`] newer ones.
    pub fn create(&self) -> std::io::Result<String> {
        let mut bytes = [0u8; ID_BYTES];
        std::fs::File::open("/dev/urandom")?.read_exact(&mut bytes)?;
        let id: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
        let mut live = self.lock();
        live.retain(|(_, at)| at.elapsed() < LIFETIME);
        while live.len() >= MAX_SESSIONS {
            live.pop_front();
        }
        live.push_back((id.clone(), Instant::now()));
        Ok(id)
    }

    /// Whether `id` is a live session. Every stored id is compared in full, in constant time.
    pub fn valid(&self, id: &str) -> bool {
        let live = self.lock();
        let mut found = false;
        for (known, at) in live.iter() {
            found |= super::api::constant_time_eq(id.as_bytes(), known.as_bytes()) && at.elapsed() < LIFETIME;
        }
        found
    }

    /// End the session `id` (sign out); unknown ids are ignored.
    pub fn end(&self, id: &str) {
        self.lock().retain(|(known, _)| known != id);
    }

    /// How many sessions are live.
    pub fn len(&self) -> usize {
        self.lock().iter().filter(|(_, at)| at.elapsed() < LIFETIME).count()
    }

    /// Whether no session is live.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, VecDeque<(String, Instant)>> {
        self.live.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// The session id the request's `Cookie` headers carry, if any.
pub fn cookie(headers: &HeaderMap) -> Option<&str> {
    headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(';'))
        .filter_map(|pair| pair.trim().split_once('='))
        .find(|(name, _)| *name == COOKIE)
        .map(|(_, value)| value.trim())
}

/// The `Set-Cookie` value that stores session `id` in the browser.
pub fn set_cookie(id: &str) -> String {
    format!("{COOKIE}={id}; Path=/; HttpOnly; SameSite=Strict; Max-Age={}", LIFETIME.as_secs())
}

/// The `Set-Cookie` value that removes the session cookie from the browser.
pub fn clear_cookie() -> String {
    format!("{COOKIE}=; Path=/; HttpOnly; SameSite=Strict; Max-Age=0")
}

/// Whether a request comes from the daemon's own page as far as the browser says: its `Origin`
/// (sent by browsers on every cross-origin request and on same-origin POSTs) names the `Host` it
/// was sent to, and `Sec-Fetch-Site`, where sent, is not `cross-site`. A request with neither
/// header (a non-browser client) passes: the cookie is then the only credential, and only a
/// browser that signed in holds it.
pub fn same_origin(headers: &HeaderMap) -> bool {
    let text = |name: header::HeaderName| headers.get(name).and_then(|v| v.to_str().ok());
    if text(header::HeaderName::from_static("sec-fetch-site")).is_some_and(|s| s == "cross-site") {
        return false;
    }
    match text(header::ORIGIN) {
        None => true,
        Some(origin) => {
            let host = text(header::HOST).unwrap_or("");
            let rest = origin.strip_prefix("http://").or_else(|| origin.strip_prefix("https://"));
            !host.is_empty() && rest == Some(host)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use axum::http::HeaderValue;

    #[test]
    fn sessions_are_random_bounded_and_end_on_sign_out() {
        let s = Sessions::new();
        let a = s.create().expect("random");
        let b = s.create().expect("random");
        assert_eq!(a.len(), 2 * ID_BYTES);
        assert_ne!(a, b);
        assert!(s.valid(&a) && s.valid(&b));
        assert!(!s.valid(&a[..10]));
        assert!(!s.valid(""));
        s.end(&a);
        assert!(!s.valid(&a) && s.valid(&b));
        for _ in 0..MAX_SESSIONS {
            s.create().expect("random");
        }
        assert_eq!(s.len(), MAX_SESSIONS);
        assert!(!s.valid(&b), "the oldest session is pushed out");
    }

    #[test]
    fn the_cookie_is_found_among_others_and_origins_are_checked() {
        let mut h = HeaderMap::new();
        h.append(header::COOKIE, HeaderValue::from_static("theme=dark; scanrig_session=abc123 ; x=1"));
        assert_eq!(cookie(&h), Some("abc123"));
        let mut h = HeaderMap::new();
        h.append(header::COOKIE, HeaderValue::from_static("scanrig_sessionX=no"));
        assert_eq!(cookie(&h), None);

        let mut h = HeaderMap::new();
        h.insert(header::HOST, HeaderValue::from_static("rig.local:8080"));
        assert!(same_origin(&h), "no Origin: not a browser's cross-site request");
        h.insert(header::ORIGIN, HeaderValue::from_static("http://rig.local:8080"));
        assert!(same_origin(&h));
        h.insert(header::ORIGIN, HeaderValue::from_static("http://evil.example"));
        assert!(!same_origin(&h));
        h.insert(header::ORIGIN, HeaderValue::from_static("http://rig.local:8080.evil.example"));
        assert!(!same_origin(&h));
        h.insert(header::ORIGIN, HeaderValue::from_static("null"));
        assert!(!same_origin(&h));
        let mut h = HeaderMap::new();
        h.insert(header::HOST, HeaderValue::from_static("rig.local:8080"));
        h.insert("sec-fetch-site", HeaderValue::from_static("cross-site"));
        assert!(!same_origin(&h));
        assert!(set_cookie("x").contains("HttpOnly") && set_cookie("x").contains("SameSite=Strict"));
    }
}
