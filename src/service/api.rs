//! The HTTP API, versioned under `/api/v1`, plus `/metrics` and the web page at `/`.
//!
//! Errors are JSON: `{"error": {"code": "...", "message": "..."}}` with a 4xx/5xx status. When the
//! daemon has a token, every route needs `Authorization: Bearer <token>` or the session cookie a
//! browser gets by signing in with the token (`POST /api/v1/session`, see [`super::session`]);
//! only the page itself (`/`, `/web/...`) and `/api/v1/session` are open.

use std::convert::Infallible;
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant};

use axum::extract::rejection::JsonRejection;
use axum::extract::{DefaultBodyLimit, Path, Request, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use futures_util::{Stream, StreamExt};
use serde_json::json;
use tokio_util::sync::CancellationToken;

use super::console;
use super::jobs::{JobError, Jobs, ReprocessRequest, StartRequest};
use super::metrics::Metrics;
use super::rig::{error_chain, RigError, RigHandle};
use super::session::{self, Sessions};
use super::store::{valid_id, StoreError};
use crate::config::RigConfig;

/// Largest request body accepted, bytes.
pub const MAX_BODY: usize = 16 * 1024;

/// What the handlers share.
#[derive(Debug, Clone)]
pub struct AppState {
    /// The configuration in force (replaced on reload).
    pub config: Arc<RwLock<Arc<RigConfig>>>,
    /// The device thread.
    pub rig: RigHandle,
    /// Scan jobs.
    pub jobs: Jobs,
    /// Counters.
    pub metrics: Arc<Metrics>,
    /// Bearer token required on every request, if set.
    pub token: Option<Arc<str>>,
    /// Cancelled at shutdown: ends event streams.
    pub shutdown: CancellationToken,
    /// When the daemon started.
    pub started: Instant,
    /// The live camera frames every MJPEG viewer shares.
    pub camera: Arc<super::camera::LiveCamera>,
    /// Browsers signed in with the token (the console's cookie sessions).
    pub sessions: Arc<Sessions>,
    /// Held while a sign-in is checked, so that wrong tokens are tried at most one a second.
    pub sign_in_gate: Arc<tokio::sync::Mutex<()>>,
}

impl AppState {
    /// The configuration in force.
    pub fn app_config(&self) -> Arc<RigConfig> {
        self.config()
    }

    fn config(&self) -> Arc<RigConfig> {
        self.config.read().map(|c| c.clone()).unwrap_or_else(|p| p.into_inner().clone())
    }
}

/// A JSON error response.
#[derive(Debug)]
pub struct ApiError {
    status: StatusCode,
    code: &'static str,
    message: String,
}

impl ApiError {
    /// An error answer with `status`, a machine-readable `code` and a message in words.
    pub fn new(status: StatusCode, code: &'static str, message: impl Into<String>) -> Self {
        ApiError { status, code, message: message.into() }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        (self.status, Json(json!({"error": {"code": self.code, "message": self.message}}))).into_response()
    }
}

impl From<JobError> for ApiError {
    fn from(e: JobError) -> Self {
        let msg = error_chain(&e);
        match e {
            JobError::Busy(_) => ApiError::new(StatusCode::CONFLICT, "busy", msg),
            JobError::Invalid { .. } => ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, "invalid_request", msg),
            JobError::WrongState { .. } => ApiError::new(StatusCode::CONFLICT, "wrong_state", msg),
            JobError::StoredConfig { .. } => ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, "stored_config", msg),
            JobError::Store(StoreError::NotFound(_)) => ApiError::new(StatusCode::NOT_FOUND, "not_found", msg),
            JobError::Store(e) if e.is_disk_full() => ApiError::new(StatusCode::INSUFFICIENT_STORAGE, "disk_full", msg),
            JobError::Store(_) => ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "store", msg),
        }
    }
}

impl From<StoreError> for ApiError {
    fn from(e: StoreError) -> Self {
        JobError::Store(e).into()
    }
}

impl From<JsonRejection> for ApiError {
    fn from(e: JsonRejection) -> Self {
        let code = if e.status() == StatusCode::PAYLOAD_TOO_LARGE { "too_large" } else { "bad_request" };
        ApiError::new(e.status(), code, e.body_text())
    }
}

/// The router over `state`.
pub fn router(state: AppState) -> Router {
    let api = Router::new()
        .route("/status", get(status))
        .route("/devices", get(devices))
        .route("/scans", get(list_scans).post(start_scan))
        .route("/scans/{id}", get(get_scan).delete(console::delete_scan))
        .route("/scans/{id}/pause", post(pause_scan))
        .route("/scans/{id}/resume", post(resume_scan))
        .route("/scans/{id}/cancel", post(cancel_scan))
        .route("/scans/{id}/reprocess", post(reprocess_scan))
        .route("/methods", get(list_methods))
        .route("/session", get(session_state).post(sign_in).delete(sign_out))
        .route("/scans/{id}/files/{*path}", get(scan_file))
        .route("/scans/{id}/live.ply", get(live_model))
        .route("/events", get(events))
        .route("/preview", get(preview))
        // The console (issue 16): live camera, manual control, scan management.
        .route("/camera.mjpg", get(console::camera_mjpg))
        .route("/camera", get(console::camera_info))
        .route("/control", get(console::control_state))
        .route("/control/turntable", post(console::control_turntable))
        .route("/control/light", post(console::control_light))
        .route("/control/laser", post(console::control_laser))
        .route("/control/projector", post(console::control_projector))
        .route("/devices/{name}/reconnect", post(console::reconnect_device))
        .route("/scans/{id}/archive.zip", get(console::archive))
        .route("/scans/{id}/thumbnail.jpg", get(console::thumbnail))
        .route("/scans/{id}/model.ply", get(console::display_model));
    Router::new()
        .nest("/api/v1", api)
        .route("/metrics", get(metrics))
        .route("/", get(page))
        .route("/web/{*path}", get(web_file))
        .fallback(|| async { ApiError::new(StatusCode::NOT_FOUND, "not_found", "no such route") })
        .layer(axum::middleware::from_fn_with_state(state.clone(), guard))
        .layer(DefaultBodyLimit::max(MAX_BODY))
        .layer(axum::middleware::from_fn(json_errors))
        .with_state(state)
}

/// Turns every error answer that is not JSON yet (extractor rejections such as a path that is
/// not UTF-8, 405 Method Not Allowed) into the API's JSON error shape.
async fn json_errors(req: Request, next: Next) -> Response {
    let res = next.run(req).await;
    let status = res.status();
    let is_json = res
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"));
    if !(status.is_client_error() || status.is_server_error()) || is_json {
        return res;
    }
    let code = match status {
        StatusCode::BAD_REQUEST => "bad_request",
        StatusCode::NOT_FOUND => "not_found",
        StatusCode::METHOD_NOT_ALLOWED => "method_not_allowed",
        StatusCode::PAYLOAD_TOO_LARGE => "too_large",
        StatusCode::UNSUPPORTED_MEDIA_TYPE => "unsupported_media_type",
        _ if status.is_client_error() => "bad_request",
        _ => "internal",
    };
    let (parts, body) = res.into_parts();
    let text = axum::body::to_bytes(body, MAX_BODY).await.unwrap_or_default();
    let mut message = String::from_utf8_lossy(&text).trim().to_owned();
    if message.is_empty() {
        message = status.canonical_reason().unwrap_or("error").to_ascii_lowercase();
    }
    let mut out = ApiError::new(status, code, message).into_response();
    if let Some(allow) = parts.headers.get(header::ALLOW) {
        out.headers_mut().insert(header::ALLOW, allow.clone());
    }
    out
}

/// Counts requests and checks the bearer token.
async fn guard(State(state): State<AppState>, req: Request, next: Next) -> Response {
    state.metrics.http_requests.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    // A body announced larger than any route accepts is refused before a byte of it is read.
    let announced = req.headers().get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()).map(str::parse::<u64>);
    match announced {
        Some(Ok(n)) if n > MAX_BODY as u64 => {
            let mut res = ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                "too_large",
                format!("the request body ({n} bytes) is larger than {MAX_BODY} bytes"),
            )
            .into_response();
            res.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
            return res;
        }
        Some(Err(_)) => {
            return ApiError::new(StatusCode::BAD_REQUEST, "bad_request", "Content-Length is not a number")
                .into_response();
        }
        _ => {}
    }
    let path = req.uri().path();
    let open = path == "/" || path.starts_with("/web/") || path == "/api/v1/session";
    if let (Some(token), false) = (&state.token, open) {
        if !bearer_is(req.headers(), token) {
            if !session::cookie(req.headers()).is_some_and(|id| state.sessions.valid(id)) {
                return ApiError::new(
                    StatusCode::UNAUTHORIZED,
                    "unauthorized",
                    "a valid bearer token (or a console session: sign in on the page) is required",
                )
                .into_response();
            }
            // A cookie is sent by the browser on its own; a change made with it must come from
            // the daemon's own page (SameSite=Strict already keeps other sites' requests out).
            let safe = matches!(*req.method(), axum::http::Method::GET | axum::http::Method::HEAD);
            if !safe && !session::same_origin(req.headers()) {
                return cross_origin().into_response();
            }
        }
    }
    next.run(req).await
}

/// Whether the request carries `Authorization: Bearer <token>`.
fn bearer_is(headers: &axum::http::HeaderMap, token: &str) -> bool {
    let given =
        headers.get(header::AUTHORIZATION).and_then(|v| v.to_str().ok()).and_then(|v| v.strip_prefix("Bearer "));
    given.is_some_and(|g| constant_time_eq(g.as_bytes(), token.as_bytes()))
}

fn cross_origin() -> ApiError {
    ApiError::new(
        StatusCode::FORBIDDEN,
        "cross_origin",
        "a console session may only be used from the daemon's own page",
    )
}

/// `GET /api/v1/session`: whether this daemon needs a sign-in and whether the caller has one.
async fn session_state(State(s): State<AppState>, headers: axum::http::HeaderMap) -> Json<serde_json::Value> {
    let authenticated = match &s.token {
        None => true,
        Some(t) => bearer_is(&headers, t) || session::cookie(&headers).is_some_and(|id| s.sessions.valid(id)),
    };
    Json(json!({"required": s.token.is_some(), "authenticated": authenticated}))
}

/// The body of `POST /api/v1/session`.
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct SignIn {
    /// The daemon's bearer token (surrounding white space is ignored, as in token files).
    token: String,
}

/// `POST /api/v1/session {"token": "..."}`: sign a browser in. The right token answers with the
/// session cookie; a wrong one answers 401 after a second (one attempt at a time).
async fn sign_in(
    State(s): State<AppState>,
    headers: axum::http::HeaderMap,
    body: Result<Json<SignIn>, JsonRejection>,
) -> Result<Response, ApiError> {
    let Json(body) = body?;
    let Some(token) = &s.token else {
        return Ok(Json(json!({"required": false, "authenticated": true})).into_response());
    };
    if !session::same_origin(&headers) {
        return Err(cross_origin());
    }
    let _one_at_a_time = s.sign_in_gate.lock().await;
    if !constant_time_eq(body.token.trim().as_bytes(), token.as_bytes()) {
        tokio::time::sleep(Duration::from_secs(1)).await;
        return Err(ApiError::new(StatusCode::UNAUTHORIZED, "wrong_token", "that is not this daemon's access token"));
    }
    let id = s.sessions.create().map_err(|e| {
        ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", format!("cannot make a session id: {e}"))
    })?;
    tracing::info!(sessions = s.sessions.len(), "console signed in");
    Ok(([(header::SET_COOKIE, session::set_cookie(&id))], Json(json!({"required": true, "authenticated": true})))
        .into_response())
}

/// `DELETE /api/v1/session`: sign out (ends the caller's session and clears its cookie).
async fn sign_out(State(s): State<AppState>, headers: axum::http::HeaderMap) -> Response {
    if let Some(id) = session::cookie(&headers) {
        s.sessions.end(id);
    }
    let authenticated = s.token.as_deref().is_none_or(|t| bearer_is(&headers, t));
    (
        [(header::SET_COOKIE, session::clear_cookie())],
        Json(json!({"required": s.token.is_some(), "authenticated": authenticated})),
    )
        .into_response()
}

/// Whether `given` equals `secret`, in a time that depends only on `secret`'s length (never on
/// where the first difference is, nor on `given`'s length).
pub fn constant_time_eq(given: &[u8], secret: &[u8]) -> bool {
    let mut diff = u8::from(given.len() != secret.len());
    for (i, s) in secret.iter().enumerate() {
        let g = given.get(i).copied().unwrap_or(!s);
        diff |= g ^ s;
    }
    std::hint::black_box(diff) == 0
}

async fn status(State(s): State<AppState>) -> Json<serde_json::Value> {
    let config = s.config();
    Json(json!({
        "version": env!("CARGO_PKG_VERSION"),
        "rig": config.rig.name,
        "uptime_s": s.started.elapsed().as_secs_f64(),
        "devices": s.rig.status(),
        "running": s.jobs.running(),
        "progress": s.jobs.progress(),
        "defaults": {
            "method": config.reconstruction.method,
            "resolution": config.reconstruction.resolution,
            "positions": config.scan.positions,
            "lights": config.scan.lights,
        },
    }))
}

async fn devices(State(s): State<AppState>) -> Json<serde_json::Value> {
    Json(json!({ "devices": s.rig.status() }))
}

async fn list_scans(State(s): State<AppState>) -> Result<Json<serde_json::Value>, ApiError> {
    let store = s.jobs.store();
    let scans: Vec<serde_json::Value> = store.list()?.iter().map(|m| console::scan_entry(store, m)).collect();
    Ok(Json(json!({ "scans": scans })))
}

async fn start_scan(
    State(s): State<AppState>,
    body: Result<Json<StartRequest>, JsonRejection>,
) -> Result<(StatusCode, Json<serde_json::Value>), ApiError> {
    let Json(req) = body?;
    let meta = s.jobs.start(&s.config(), req)?;
    Ok((StatusCode::ACCEPTED, Json(json!(meta))))
}

fn check_id(id: &str) -> Result<(), ApiError> {
    if valid_id(id) {
        Ok(())
    } else {
        Err(ApiError::new(StatusCode::BAD_REQUEST, "bad_request", "malformed scan id"))
    }
}

async fn get_scan(State(s): State<AppState>, Path(id): Path<String>) -> Result<Json<serde_json::Value>, ApiError> {
    check_id(&id)?;
    let meta = s.jobs.store().get(&id)?;
    let dir = s.jobs.store().dir(&id);
    let report: Option<serde_json::Value> =
        std::fs::read(dir.join("report.json")).ok().and_then(|b| serde_json::from_slice(&b).ok());
    let frames = std::fs::read_dir(dir.join("frames"))
        .map(|d| d.flatten().filter(|e| e.file_name().to_string_lossy().ends_with(".png")).count())
        .unwrap_or(0);
    let entry = console::scan_entry(s.jobs.store(), &meta);
    let replication = s.jobs.replication().and_then(|q| q.status(&id));
    Ok(Json(json!({ "scan": entry, "frames": frames, "report": report, "replication": replication })))
}

async fn pause_scan(State(s): State<AppState>, Path(id): Path<String>) -> Result<Json<serde_json::Value>, ApiError> {
    check_id(&id)?;
    s.jobs.pause(&id)?;
    Ok(Json(json!({ "id": id, "requested": "pause" })))
}

async fn resume_scan(
    State(s): State<AppState>,
    Path(id): Path<String>,
) -> Result<(StatusCode, Json<serde_json::Value>), ApiError> {
    check_id(&id)?;
    let meta = s.jobs.resume(&id)?;
    Ok((StatusCode::ACCEPTED, Json(json!(meta))))
}

async fn reprocess_scan(
    State(s): State<AppState>,
    Path(id): Path<String>,
    body: Result<Json<ReprocessRequest>, JsonRejection>,
) -> Result<(StatusCode, Json<serde_json::Value>), ApiError> {
    check_id(&id)?;
    let Json(req) = body?;
    let meta = s.jobs.reprocess(&id, req)?;
    Ok((StatusCode::ACCEPTED, Json(json!(meta))))
}

/// Every method with whether this rig can run it and, if not, what is missing.
async fn list_methods(State(s): State<AppState>) -> Json<serde_json::Value> {
    let config = s.config();
    Json(json!({ "default": config.reconstruction.method, "methods": super::jobs::methods(&config) }))
}

async fn cancel_scan(State(s): State<AppState>, Path(id): Path<String>) -> Result<Json<serde_json::Value>, ApiError> {
    check_id(&id)?;
    s.jobs.cancel(&id)?;
    Ok(Json(json!({ "id": id, "requested": "cancel" })))
}

/// Serves `model.ply|stl|obj`, `voxels.ply`, `cloud.ply`, `report.json`, `meta.json`, `rig.toml`,
/// `frames/pos_NNN*.png|json` and `frames/prepare.json`.
async fn scan_file(State(s): State<AppState>, Path((id, path)): Path<(String, String)>) -> Result<Response, ApiError> {
    check_id(&id)?;
    let allowed = match path.split_once('/') {
        None => matches!(
            path.as_str(),
            "model.ply"
                | "model.stl"
                | "model.obj"
                | "voxels.ply"
                | "cloud.ply"
                | "report.json"
                | "meta.json"
                | "rig.toml"
        ),
        Some(("frames", "prepare.json")) => true,
        Some(("frames", name)) => {
            name.starts_with("pos_")
                && (name.ends_with(".png") || name.ends_with(".json"))
                && name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'.')
                && !name.contains("..")
        }
        Some(_) => false,
    };
    if !allowed {
        return Err(ApiError::new(StatusCode::NOT_FOUND, "not_found", format!("no file `{path}` in a scan")));
    }
    s.jobs.store().get(&id)?;
    let file = s.jobs.store().dir(&id).join(&path);
    // Streamed in 64 KiB chunks: memory per download is bounded whatever the file's size.
    let missing = || ApiError::new(StatusCode::NOT_FOUND, "not_found", format!("scan {id} has no {path} (yet)"));
    let f = tokio::fs::File::open(&file).await.map_err(|_| missing())?;
    let len = f.metadata().await.map_err(|_| missing())?.len();
    let body = axum::body::Body::from_stream(tokio_util::io::ReaderStream::with_capacity(f, 64 * 1024));
    let mime = match path.rsplit('.').next() {
        Some("png") => "image/png",
        Some("json") => "application/json",
        Some("obj" | "toml") => "text/plain; charset=utf-8",
        Some("stl") => "model/stl",
        _ => "application/octet-stream",
    };
    Ok((
        [(header::CONTENT_TYPE, HeaderValue::from_static(mime)), (header::CONTENT_LENGTH, HeaderValue::from(len))],
        body,
    )
        .into_response())
}

/// The latest live estimate of scan `id` as binary PLY (see [`crate::service::jobs::LiveModel`]).
async fn live_model(State(s): State<AppState>, Path(id): Path<String>) -> Result<Response, ApiError> {
    s.jobs.store().get(&id)?;
    let model = s
        .jobs
        .live_model(&id)
        .ok_or_else(|| ApiError::new(StatusCode::NOT_FOUND, "not_found", format!("scan {id} has no live estimate")))?;
    let version = HeaderValue::from(model.version);
    Ok((
        [
            (header::CONTENT_TYPE, HeaderValue::from_static("application/octet-stream")),
            (header::HeaderName::from_static("x-model-version"), version),
            (header::CACHE_CONTROL, HeaderValue::from_static("no-store")),
        ],
        model.ply,
    )
        .into_response())
}

/// Server-sent events: `progress` (the snapshot, first at once, then on every change) and `model`
/// (a new live estimate: scan id, version, position, point count).
async fn events(State(s): State<AppState>) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    let rx = s.jobs.subscribe();
    let first = futures_util::stream::once({
        let p = s.jobs.progress();
        async move { Ok(Event::default().event("progress").json_data(&p).unwrap_or_default()) }
    });
    let updates = futures_util::stream::unfold(rx, |mut rx| async move {
        rx.changed().await.ok()?;
        let p = rx.borrow_and_update().clone();
        Some((Ok(Event::default().event("progress").json_data(&p).unwrap_or_default()), rx))
    });
    // Only the newest estimate matters: a slow client skips versions, never queues them.
    let models = futures_util::stream::unfold(s.jobs.subscribe_live(), |mut rx| async move {
        loop {
            rx.changed().await.ok()?;
            let m = rx.borrow_and_update().clone();
            if let Some(m) = m {
                return Some((Ok(Event::default().event("model").json_data(&m).unwrap_or_default()), rx));
            }
        }
    });
    let stream = futures_util::stream::select(
        futures_util::stream::select(first.chain(updates), models),
        console::device_events(&s),
    )
    .take_until(s.shutdown.clone().cancelled_owned());
    Sse::new(stream).keep_alive(KeepAlive::new().interval(Duration::from_secs(10)))
}

async fn preview(State(s): State<AppState>) -> Result<Response, ApiError> {
    // While a scan runs the device thread is busy: serve its latest stored frame instead.
    if let Some(id) = s.jobs.running() {
        let dir = s.jobs.store().dir(&id).join("frames");
        let latest = std::fs::read_dir(&dir).ok().and_then(|d| {
            d.flatten()
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|n| n.starts_with("pos_") && n.ends_with(".png"))
                .max()
        });
        return match latest {
            Some(name) => {
                let bytes = tokio::fs::read(dir.join(name))
                    .await
                    .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "io", e.to_string()))?;
                Ok(([(header::CONTENT_TYPE, "image/png")], bytes).into_response())
            }
            None => Err(ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "busy", "no frame captured yet")),
        };
    }
    let answer = tokio::time::timeout(Duration::from_secs(10), s.rig.preview()).await;
    match answer.as_ref().map(|r| r.as_ref().map_err(RigError::inner)) {
        Ok(Ok(png)) => Ok(([(header::CONTENT_TYPE, "image/png")], png.clone()).into_response()),
        Ok(Err(RigError::Busy)) => Err(ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "busy", "the rig is busy")),
        Ok(Err(e @ RigError::NotConnected)) => {
            Err(ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "disconnected", error_chain(e)))
        }
        Ok(Err(e)) => Err(ApiError::new(StatusCode::BAD_GATEWAY, "device", error_chain(e))),
        Err(_) => Err(ApiError::new(StatusCode::GATEWAY_TIMEOUT, "timeout", "no preview frame in 10 s")),
    }
}

async fn metrics(State(s): State<AppState>) -> Response {
    let body = s.metrics.render(s.jobs.running().is_some());
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], body).into_response()
}

async fn page() -> Response {
    ([(header::CONTENT_TYPE, "text/html; charset=utf-8")], include_str!("../../web/index.html")).into_response()
}

/// A file of the web console (`web/`, embedded at build time); 404 for anything not in the list.
async fn web_file(Path(path): Path<String>) -> Result<Response, ApiError> {
    let file = super::web::lookup(&path)
        .ok_or_else(|| ApiError::new(StatusCode::NOT_FOUND, "not_found", format!("no web file `{path}`")))?;
    Ok(([(header::CONTENT_TYPE, file.content_type), (header::CACHE_CONTROL, "no-cache")], file.bytes).into_response())
}

#[cfg(test)]
mod tests {
    use super::constant_time_eq;

    #[test]
    fn token_comparison_is_exact_whatever_the_lengths() {
        assert!(constant_time_eq(b"s3cret", b"s3cret"));
        for given in [&b""[..], b"s3cre", b"s3cret!", b"s3creT", b"\xff\xff\xff\xff\xff\xff"] {
            assert!(!constant_time_eq(given, b"s3cret"), "{given:?}");
        }
    }
}
