//! The console's API routes (issue 16): live camera, manual control, device reconnection, scan
//! deletion, archives, thumbnails and display models. Mounted by [`super::api::router`].

use std::convert::Infallible;
use std::time::{Duration, Instant};

use axum::body::{Body, Bytes};
use axum::extract::rejection::{JsonRejection, QueryRejection};
use axum::extract::{Path, Query, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::sse::Event;
use axum::response::{IntoResponse, Response};
use axum::Json;
use futures_util::Stream;
use serde::Deserialize;
use serde_json::json;

use super::api::{ApiError, AppState};
use super::camera::{frame_period, mjpeg_part, KEEPALIVE};
use super::control::{ControlCommand, ControlError, ProjectorShow, TestPattern};
use super::rig::{error_chain, RigError};
use super::store::{valid_id, ScanMeta, ScanStore};
use crate::config::CameraConfig;
use crate::pipeline::display;

/// Outputs a scan directory may hold, in the order `outputs` lists them.
pub const OUTPUTS: [&str; 5] = ["model.stl", "model.ply", "model.obj", "cloud.ply", "voxels.ply"];

/// Largest faces of a display mesh when the request names none.
pub const DEFAULT_MAX_FACES: usize = 200_000;
/// Largest points of a display cloud when the request names none.
pub const DEFAULT_MAX_POINTS: usize = 300_000;
/// Widest thumbnail, pixels.
pub const THUMBNAIL_WIDTH: u32 = 240;

fn bad(field: &str, problem: impl std::fmt::Display) -> ApiError {
    ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, "invalid_request", format!("{field}: {problem}"))
}

fn check_id(id: &str) -> Result<(), ApiError> {
    if valid_id(id) {
        Ok(())
    } else {
        Err(ApiError::new(StatusCode::BAD_REQUEST, "bad_request", "malformed scan id"))
    }
}

fn internal(what: &str, e: &dyn std::error::Error) -> ApiError {
    ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", format!("{what}: {}", error_chain(e)))
}

/// Refuse while a scan owns the hardware (a reprocess needs none and does not count).
fn refuse_while_scanning(s: &AppState) -> Result<(), ApiError> {
    match s.jobs.scanning() {
        Some(id) => Err(ApiError::new(
            StatusCode::CONFLICT,
            "scan_running",
            format!("scan {id} is running and owns the rig; try again when it has finished"),
        )),
        None => Ok(()),
    }
}

impl From<RigError> for ApiError {
    fn from(e: RigError) -> Self {
        let msg = error_chain(&e);
        match e.inner() {
            RigError::Busy => ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "busy", msg),
            RigError::NotConnected => ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "disconnected", msg),
            RigError::Stopped => ApiError::new(StatusCode::SERVICE_UNAVAILABLE, "stopped", msg),
            RigError::UnknownDevice(_) => ApiError::new(StatusCode::NOT_FOUND, "not_found", msg),
            RigError::Control(ControlError::NoDevice(_)) => ApiError::new(StatusCode::NOT_FOUND, "no_device", msg),
            RigError::Control(ControlError::NoSuchIndex { .. }) => bad("index", msg),
            RigError::Control(ControlError::BadAngle(_)) => bad("turn_deg", msg),
            _ => ApiError::new(StatusCode::BAD_GATEWAY, "device", msg),
        }
    }
}

// ---- live camera -------------------------------------------------------------------------------

/// `?fps=N` of the MJPEG stream.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MjpegQuery {
    /// Frames per second wanted (default 5, at most 15).
    pub fps: Option<f64>,
}

/// `GET /api/v1/camera.mjpg`: see [`super::camera`].
pub async fn camera_mjpg(
    State(s): State<AppState>,
    query: Result<Query<MjpegQuery>, QueryRejection>,
) -> Result<Response, ApiError> {
    let Query(q) = query.map_err(|e| bad("query", e.body_text()))?;
    let period = frame_period(q.fps).ok_or_else(|| bad("fps", "must be a positive number of frames per second"))?;
    struct Viewer {
        s: AppState,
        period: Duration,
        next: tokio::time::Instant,
        last_seq: Option<u64>,
        last_sent: Instant,
    }
    let viewer =
        Viewer { s: s.clone(), period, next: tokio::time::Instant::now(), last_seq: None, last_sent: Instant::now() };
    let stream = futures_util::stream::unfold(viewer, |mut v| async move {
        loop {
            tokio::time::sleep_until(v.next).await;
            v.next = tokio::time::Instant::now() + v.period;
            if v.s.jobs.scanning().is_some() {
                // Paused: the scan owns the camera. Keep the connection open with the last frame.
                if v.last_sent.elapsed() >= KEEPALIVE {
                    if let Some(f) = v.s.camera.last() {
                        v.last_sent = Instant::now();
                        return Some((Ok::<Bytes, Infallible>(mjpeg_part(&f)), v));
                    }
                }
                v.next = tokio::time::Instant::now() + Duration::from_millis(250);
                continue;
            }
            match v.s.camera.frame(v.period).await {
                Ok(f) if Some(f.sequence) != v.last_seq || v.last_sent.elapsed() >= KEEPALIVE => {
                    v.last_seq = Some(f.sequence);
                    v.last_sent = Instant::now();
                    return Some((Ok(mjpeg_part(&f)), v));
                }
                Ok(_) => {}
                Err(e) => {
                    tracing::debug!(error = %error_chain(&e), "no live frame");
                    v.next = tokio::time::Instant::now() + Duration::from_secs(1);
                }
            }
        }
    });
    let stream = futures_util::StreamExt::take_until(stream, s.shutdown.clone().cancelled_owned());
    Ok((
        [
            (header::CONTENT_TYPE, HeaderValue::from_static("multipart/x-mixed-replace; boundary=frame")),
            (header::CACHE_CONTROL, HeaderValue::from_static("no-store")),
        ],
        Body::from_stream(stream),
    )
        .into_response())
}

/// `GET /api/v1/camera`: size, whether the stream is paused, exposure and gain where the rig
/// file sets them (the drivers lock them there for a scan).
pub async fn camera_info(State(s): State<AppState>) -> Json<serde_json::Value> {
    let config = s.app_config();
    let (w, h) = s.rig.camera_size().map_or(config.camera.size(), |c| (c.width, c.height));
    let (exposure_us, gain_db, gain_units): (Option<f64>, Option<f64>, Option<i64>) = match &config.camera {
        CameraConfig::Sim(_) => (None, None, None),
        CameraConfig::V4l2(c) | CameraConfig::Uvc(c) => (c.controls.exposure_us.map(f64::from), None, c.controls.gain),
        CameraConfig::Genicam(c) => (c.exposure_us, c.gain, None),
    };
    let kind = s.rig.status().into_iter().find(|d| d.name == "camera").map(|d| d.kind);
    Json(json!({
        "streaming_paused": s.jobs.scanning().is_some(),
        "width": w,
        "height": h,
        "exposure_us": exposure_us,
        "gain_db": gain_db,
        "gain_device_units": gain_units,
        "kind": kind,
    }))
}

// ---- manual control ----------------------------------------------------------------------------

/// `GET /api/v1/control`.
pub async fn control_state(State(s): State<AppState>) -> Json<serde_json::Value> {
    Json(json!(s.rig.control_state()))
}

/// Body of `POST /control/turntable`: exactly one of the two.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TurntableBody {
    /// Degrees to turn by, relative.
    pub turn_deg: Option<f64>,
    /// Home the table.
    pub home: Option<bool>,
}

/// Body of `POST /control/light` and `/control/laser`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SwitchBody {
    /// Index, 0-based.
    pub index: usize,
    /// On or off.
    pub on: bool,
}

/// Body of `POST /control/projector`: exactly one of the three.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProjectorBody {
    /// A test pattern: `checker`, `gray`, `white`, `black`.
    pub pattern: Option<TestPattern>,
    /// A solid colour, `[r, g, b]`, 0-255.
    pub colour: Option<[u8; 3]>,
    /// Blank the projector.
    pub blank: Option<bool>,
}

fn json_body<T>(body: Result<Json<T>, JsonRejection>) -> Result<T, ApiError> {
    match body {
        Ok(Json(b)) => Ok(b),
        Err(e) if e.status() == StatusCode::UNPROCESSABLE_ENTITY => {
            Err(ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, "invalid_request", e.body_text()))
        }
        Err(e) => Err(e.into()),
    }
}

async fn run_control(s: &AppState, cmd: ControlCommand) -> Result<super::control::ControlState, ApiError> {
    refuse_while_scanning(s)?;
    let answer = tokio::time::timeout(Duration::from_secs(60), s.rig.control(cmd)).await;
    match answer {
        Ok(r) => Ok(r?),
        Err(_) => {
            Err(ApiError::new(StatusCode::GATEWAY_TIMEOUT, "timeout", "the device thread did not answer in 60 s"))
        }
    }
}

/// `POST /api/v1/control/turntable`.
pub async fn control_turntable(
    State(s): State<AppState>,
    body: Result<Json<TurntableBody>, JsonRejection>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let b = json_body(body)?;
    let cmd = match (b.turn_deg, b.home) {
        (Some(d), None) => ControlCommand::Turn { degrees: d },
        (None, Some(true)) => ControlCommand::Home,
        (None, Some(false)) => return Err(bad("home", "only `true` means something")),
        (None, None) => return Err(bad("turn_deg", "give `turn_deg` (degrees) or `home: true`")),
        (Some(_), Some(_)) => return Err(bad("turn_deg", "give `turn_deg` or `home`, not both")),
    };
    let state = run_control(&s, cmd).await?;
    Ok(Json(json!({ "angle_deg": state.angle_deg })))
}

/// `POST /api/v1/control/light`.
pub async fn control_light(
    State(s): State<AppState>,
    body: Result<Json<SwitchBody>, JsonRejection>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let b = json_body(body)?;
    Ok(Json(json!(run_control(&s, ControlCommand::Light { index: b.index, on: b.on }).await?)))
}

/// `POST /api/v1/control/laser`.
pub async fn control_laser(
    State(s): State<AppState>,
    body: Result<Json<SwitchBody>, JsonRejection>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let b = json_body(body)?;
    Ok(Json(json!(run_control(&s, ControlCommand::Laser { index: b.index, on: b.on }).await?)))
}

/// `POST /api/v1/control/projector`.
pub async fn control_projector(
    State(s): State<AppState>,
    body: Result<Json<ProjectorBody>, JsonRejection>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let b = json_body(body)?;
    let show = match (b.pattern, b.colour, b.blank) {
        (Some(p), None, None) => ProjectorShow::Pattern(p),
        (None, Some(c), None) => ProjectorShow::Colour(c),
        (None, None, Some(true)) => ProjectorShow::Blank,
        (None, None, Some(false)) => return Err(bad("blank", "only `true` means something")),
        (None, None, None) => return Err(bad("pattern", "give one of `pattern`, `colour` or `blank`")),
        _ => return Err(bad("pattern", "give only one of `pattern`, `colour` or `blank`")),
    };
    Ok(Json(json!(run_control(&s, ControlCommand::Projector(show)).await?)))
}

/// `POST /api/v1/devices/{name}/reconnect`: 202 once the attempt is made.
pub async fn reconnect_device(
    State(s): State<AppState>,
    Path(name): Path<String>,
) -> Result<(StatusCode, Json<serde_json::Value>), ApiError> {
    if !s.rig.status().iter().any(|d| d.name == name) {
        return Err(RigError::UnknownDevice(name).into());
    }
    refuse_while_scanning(&s)?;
    tokio::time::timeout(Duration::from_secs(60), s.rig.reconnect(&name)).await.map_err(|_| {
        ApiError::new(StatusCode::GATEWAY_TIMEOUT, "timeout", "the device thread did not answer in 60 s")
    })??;
    Ok((StatusCode::ACCEPTED, Json(json!({ "device": name, "requested": "reconnect", "devices": s.rig.status() }))))
}

/// The SSE `devices` events: the `/devices` array each time a device's status changes.
pub fn device_events(s: &AppState) -> impl Stream<Item = Result<Event, Infallible>> + Send + 'static {
    let rx = s.rig.subscribe_devices();
    let rig = s.rig.clone();
    futures_util::stream::unfold((rx, rig, None::<serde_json::Value>), |(mut rx, rig, mut last)| async move {
        loop {
            rx.changed().await.ok()?;
            let now = json!(rig.status());
            if last.as_ref() != Some(&now) {
                let event = Event::default().event("devices").json_data(&now).unwrap_or_default();
                last = Some(now);
                return Some((Ok(event), (rx, rig, last)));
            }
        }
    })
}

// ---- scans -------------------------------------------------------------------------------------

/// A scan's list entry: its `meta.json` plus `created` (RFC 3339), `report` (summary figures of a
/// finished scan, else null) and `outputs` (the model files it has).
pub fn scan_entry(store: &ScanStore, meta: &ScanMeta) -> serde_json::Value {
    let dir = store.dir(&meta.id);
    let mut v = json!(meta);
    v["created"] = json!(super::store::rfc3339(meta.created_unix));
    v["updated"] = json!(super::store::rfc3339(meta.updated_unix));
    let report: Option<serde_json::Value> =
        std::fs::read(dir.join("report.json")).ok().and_then(|b| serde_json::from_slice(&b).ok());
    v["report"] = report.as_ref().map_or(serde_json::Value::Null, report_summary);
    v["outputs"] = json!(OUTPUTS.iter().filter(|f| dir.join(f).is_file()).collect::<Vec<_>>());
    v
}

/// The figures of `report.json` a list shows.
pub fn report_summary(r: &serde_json::Value) -> serde_json::Value {
    let mut v = json!({
        "views": r["views"],
        "volume_m3": r["volume_m3"],
        "mesh_triangles": r["mesh_triangles"],
        "occupied_voxels": r["occupied_voxels"],
        "reprojection_iou_mean": r["reprojection_iou_mean"],
        "total_s": r["timings_s"]["total"],
        "after_last_frame_s": r["timings_s"]["after_last_frame_s"],
    });
    if let Some(bb) = r["bbox_m"].as_array() {
        if let (Some(lo), Some(hi)) = (bb.first().and_then(|x| x.as_array()), bb.get(1).and_then(|x| x.as_array())) {
            let size: Vec<f64> =
                lo.iter().zip(hi).map(|(a, b)| (b.as_f64().unwrap_or(0.0) - a.as_f64().unwrap_or(0.0)) * 1e3).collect();
            v["bbox_mm"] = json!(size);
        }
    }
    if r["ground_truth"].is_object() {
        v["iou"] = r["ground_truth"]["iou"].clone();
        v["chamfer_rel"] = r["ground_truth"]["chamfer_rel"].clone();
    }
    v
}

/// `DELETE /api/v1/scans/{id}`: 204; 409 while it runs.
pub async fn delete_scan(State(s): State<AppState>, Path(id): Path<String>) -> Result<StatusCode, ApiError> {
    check_id(&id)?;
    let jobs = s.jobs.clone();
    tokio::task::spawn_blocking(move || jobs.delete(&id))
        .await
        .map_err(|_| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", "delete task failed"))??;
    Ok(StatusCode::NO_CONTENT)
}

/// `GET /api/v1/scans/{id}/archive.zip`: the scan directory as a stored zip, streamed.
pub async fn archive(State(s): State<AppState>, Path(id): Path<String>) -> Result<Response, ApiError> {
    check_id(&id)?;
    s.jobs.store().get(&id)?;
    let dir = s.jobs.store().dir(&id);
    let (tx, rx) = tokio::sync::mpsc::channel::<Result<Bytes, std::io::Error>>(4);
    let scan = id.clone();
    tokio::task::spawn_blocking(move || {
        let sink = ChannelWriter { tx: tx.clone() };
        if let Err(e) = super::archive::write_dir_zip(&dir, sink) {
            tracing::warn!(scan = %scan, error = %error_chain(&e), "archive cut short");
            let _ = tx.blocking_send(Err(std::io::Error::other(e.to_string())));
        }
    });
    let body = Body::from_stream(futures_util::stream::unfold(rx, |mut rx| async move {
        let item = rx.recv().await?;
        Some((item, rx))
    }));
    let disposition = format!("attachment; filename=\"{id}.zip\"");
    Ok((
        [
            (header::CONTENT_TYPE, HeaderValue::from_static("application/zip")),
            (
                header::CONTENT_DISPOSITION,
                HeaderValue::from_str(&disposition).unwrap_or(HeaderValue::from_static("attachment")),
            ),
        ],
        body,
    )
        .into_response())
}

/// A `Write` that hands its bytes to the response body, waiting while the client is behind.
struct ChannelWriter {
    tx: tokio::sync::mpsc::Sender<Result<Bytes, std::io::Error>>,
}

impl std::io::Write for ChannelWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.tx
            .blocking_send(Ok(Bytes::copy_from_slice(buf)))
            .map_err(|_| std::io::Error::new(std::io::ErrorKind::BrokenPipe, "the client went away"))?;
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// `GET /api/v1/scans/{id}/thumbnail.jpg`: the first stored view, at most 240 px wide.
pub async fn thumbnail(State(s): State<AppState>, Path(id): Path<String>) -> Result<Response, ApiError> {
    check_id(&id)?;
    s.jobs.store().get(&id)?;
    let frames = s.jobs.store().dir(&id).join("frames");
    let first = std::fs::read_dir(&frames).ok().and_then(|d| {
        d.flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|n| n.starts_with("pos_") && n.ends_with(".png") && !crate::atomic::is_atomic_temp(n))
            .min()
    });
    let Some(name) = first else {
        return Err(ApiError::new(StatusCode::NOT_FOUND, "not_found", format!("scan {id} has no stored view yet")));
    };
    let path = frames.join(&name);
    let jpeg = tokio::task::spawn_blocking(move || -> Result<Vec<u8>, ApiError> {
        let img = image::open(&path).map_err(|e| internal(&format!("cannot read {name}"), &e))?.to_rgb8();
        let img = if img.width() > THUMBNAIL_WIDTH {
            let h = (u64::from(img.height()) * u64::from(THUMBNAIL_WIDTH) / u64::from(img.width())).max(1) as u32;
            image::imageops::thumbnail(&img, THUMBNAIL_WIDTH, h)
        } else {
            img
        };
        super::camera::encode_jpeg(&img, 85).map_err(|e| internal("cannot encode the thumbnail", &e))
    })
    .await
    .map_err(|_| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", "thumbnail task failed"))??;
    Ok(([(header::CONTENT_TYPE, "image/jpeg")], jpeg).into_response())
}

/// The model a display request asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ModelKind {
    /// The mesh (`model.ply`).
    Mesh,
    /// The point cloud (`cloud.ply`).
    Cloud,
    /// The occupied voxels' centres (`voxels.ply`).
    Voxels,
}

/// Query of `model.ply`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelQuery {
    /// Which model (default `mesh`).
    pub kind: Option<ModelKind>,
    /// Most faces of a mesh.
    pub max_faces: Option<usize>,
    /// Most points of a cloud or of the voxel centres.
    pub max_points: Option<usize>,
}

/// `GET /api/v1/scans/{id}/model.ply?kind=mesh|cloud|voxels&max_faces=N&max_points=N`: binary PLY
/// for display (see [`crate::pipeline::display`]).
pub async fn display_model(
    State(s): State<AppState>,
    Path(id): Path<String>,
    query: Result<Query<ModelQuery>, QueryRejection>,
) -> Result<Response, ApiError> {
    check_id(&id)?;
    let Query(q) = query.map_err(|e| bad("query", e.body_text()))?;
    s.jobs.store().get(&id)?;
    let kind = q.kind.unwrap_or(ModelKind::Mesh);
    let file = match kind {
        ModelKind::Mesh => "model.ply",
        ModelKind::Cloud => "cloud.ply",
        ModelKind::Voxels => "voxels.ply",
    };
    let path = s.jobs.store().dir(&id).join(file);
    let bytes = tokio::fs::read(&path)
        .await
        .map_err(|_| ApiError::new(StatusCode::NOT_FOUND, "not_found", format!("scan {id} has no {file}")))?;
    let max_faces = q.max_faces.unwrap_or(DEFAULT_MAX_FACES);
    let max_points = q.max_points.unwrap_or(DEFAULT_MAX_POINTS);
    let out = tokio::task::spawn_blocking(move || -> Result<Vec<u8>, ApiError> {
        let model = display::read_ply(&bytes).map_err(|e| internal(&format!("cannot read {file}"), &e))?;
        Ok(match kind {
            ModelKind::Mesh => crate::pipeline::export::ply_mesh_bytes(&display::decimate_mesh(&model, max_faces)),
            _ => {
                let (p, c) = display::subsample_points(&model.vertices, model.colors.as_ref(), max_points);
                crate::pipeline::export::ply_points_bytes(&p, c.as_ref())
            }
        })
    })
    .await
    .map_err(|_| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", "model task failed"))??;
    Ok(([(header::CONTENT_TYPE, "application/octet-stream")], out).into_response())
}
