//! The rig file: TOML schema ([`schema`]), loading with file:line errors, and [`RigConfig::validate`],
//! which reports every problem at once.

pub mod schema;
pub mod structured_light;

use std::fmt;
use std::path::{Path, PathBuf};

pub use schema::*;

use crate::geometry::Vector3;

/// One problem found in a rig file.
#[derive(Debug, Clone, PartialEq)]
pub struct Problem {
    /// Dotted key path, e.g. `reconstruction.resolution`.
    pub key: String,
    /// 1-based line of the key in the file, when it is there.
    pub line: Option<usize>,
    /// What is wrong.
    pub message: String,
}

impl fmt::Display for Problem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.line {
            Some(l) => write!(f, "line {l}: `{}`: {}", self.key, self.message),
            None => write!(f, "`{}`: {}", self.key, self.message),
        }
    }
}

/// Why a rig file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("{path}: cannot read rig file")]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: std::io::Error,
    },
    /// The file is not valid TOML or does not fit the schema.
    #[error("{path}:{line}:{column}: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
        /// 1-based column.
        column: usize,
        /// The parser's message.
        message: String,
    },
    /// The file parsed but its values do not make a working rig.
    #[error("{path}: {} problem(s):\n{}", problems.len(), problems.iter().map(|p| format!("  {}:{p}", path.display())).collect::<Vec<_>>().join("\n"))]
    Invalid {
        /// The file.
        path: PathBuf,
        /// Every problem found.
        problems: Vec<Problem>,
    },
    /// The `[projector] procam` file could not be used.
    #[error(transparent)]
    Procam(Box<ProcamConfigError>),
    /// The calibration file named by `[rig] calibration` could not be read or does not fit the rig.
    #[error("{path}:{line}: `rig.calibration`: cannot use the calibration file")]
    Calibration {
        /// The rig file.
        path: PathBuf,
        /// 1-based line of the `calibration` key.
        line: usize,
        /// What is wrong with the calibration file.
        #[source]
        source: crate::calibration::file::CalibrationFileError,
    },
}

/// The `[projector] procam` file of an fbdev projector could not be read or does not fit the rig.
#[derive(Debug, thiserror::Error)]
#[error("{}:{line}: `projector.procam`: cannot use {}", path.display(), file.display())]
pub struct ProcamConfigError {
    /// The rig file.
    pub path: PathBuf,
    /// 1-based line of the `procam` key.
    pub line: usize,
    /// The procam file.
    pub file: PathBuf,
    /// Why.
    #[source]
    pub source: crate::calibration::procam_file::ProcamFileError,
}

/// Read, parse and validate a rig file.
pub fn load(path: &Path) -> Result<RigConfig, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read { path: path.to_owned(), source })?;
    parse(&text, path)
}

/// Parse and validate rig-file text; `path` is used in messages and to find the calibration file of
/// `[rig] calibration` (relative to the rig file's directory), which is then applied.
pub fn parse(text: &str, path: &Path) -> Result<RigConfig, ConfigError> {
    let mut config: RigConfig = toml::from_str(text).map_err(|e| {
        let (line, column) = e.span().map(|s| line_col(text, s.start)).unwrap_or((1, 1));
        ConfigError::Parse { path: path.to_owned(), line, column, message: e.message().trim().to_owned() }
    })?;
    let mut problems = config.validate();
    if !problems.is_empty() {
        locate(text, &mut problems);
        return Err(ConfigError::Invalid { path: path.to_owned(), problems });
    }
    if let Some(rel) = config.rig.calibration.clone() {
        let file = path.parent().map_or(rel.clone(), |d| d.join(&rel));
        crate::calibration::file::apply_to_rig(&file, &mut config).map_err(|source| {
            let mut p = [Problem { key: "rig.calibration".into(), line: None, message: String::new() }];
            locate(text, &mut p);
            ConfigError::Calibration { path: path.to_owned(), line: p[0].line.unwrap_or(1), source }
        })?;
    }
    if let Some(ProjectorConfig::Fbdev(p)) = &config.projector {
        if let Some(rel) = p.procam.clone() {
            let file = path.parent().map_or(rel.clone(), |d| d.join(&rel));
            crate::calibration::procam_cloud::apply_procam_to_rig(&file, &mut config).map_err(|source| {
                let mut pr = [Problem { key: "projector.procam".into(), line: None, message: String::new() }];
                locate(text, &mut pr);
                ConfigError::Procam(Box::new(ProcamConfigError {
                    path: path.to_owned(),
                    line: pr[0].line.unwrap_or(1),
                    file,
                    source,
                }))
            })?;
        }
    }
    Ok(config)
}

fn line_col(text: &str, offset: usize) -> (usize, usize) {
    let before = &text[..offset.min(text.len())];
    let line = before.bytes().filter(|&b| b == b'\n').count() + 1;
    let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
    (line, column)
}

/// Fill in the line of each problem's key from the document's spans (the deepest part of the key
/// path that exists in the file).
fn locate(text: &str, problems: &mut [Problem]) {
    let Ok(doc) = toml_edit::Document::parse(text) else { return };
    for p in problems.iter_mut() {
        let parts: Vec<&str> = p.key.split('.').collect();
        p.line = key_span(doc.as_table(), &parts).map(|s| line_col(text, s.start).0);
    }
}

fn key_span(table: &dyn toml_edit::TableLike, parts: &[&str]) -> Option<std::ops::Range<usize>> {
    let (first, rest) = parts.split_first()?;
    let (key, item) = table.get_key_value(first)?;
    let here = key.span().or_else(|| item.span());
    let deeper = match (item, rest.first()) {
        (_, None) => None,
        (toml_edit::Item::ArrayOfTables(a), Some(i)) => {
            let t = a.get(i.parse().ok()?)?;
            key_span(t, &rest[1..]).or_else(|| t.span())
        }
        (toml_edit::Item::Value(toml_edit::Value::Array(a)), Some(i)) => a.get(i.parse().ok()?)?.span(),
        (item, Some(_)) => item.as_table_like().and_then(|t| key_span(t, rest)),
    };
    deeper.or(here)
}

impl RigConfig {
    /// Checks of `[controller]` and of the devices that use it.
    fn validate_controller(&self, bad: &mut dyn FnMut(&str, String)) {
        let serial_turntable = matches!(self.turntable, TurntableConfig::Serial(_));
        let serial_lights = self.lights.as_ref().is_some_and(|l| l.kind == LightsKind::Serial);
        let Some(c) = &self.controller else {
            if serial_turntable {
                bad("turntable.kind", "kind = \"serial\" needs a `[controller]` section".into());
            }
            if serial_lights {
                bad("lights.kind", "kind = \"serial\" needs a `[controller]` section".into());
            }
            return;
        };
        if !serial_turntable && !serial_lights {
            bad("controller", "no device has kind = \"serial\", so this section is unused".into());
        }
        match crate::devices::serial::PortSpec::parse(&c.port) {
            Ok(crate::devices::serial::PortSpec::Emulator(name)) => {
                if name != c.dialect.name() {
                    bad(
                        "controller.port",
                        format!("`emulator:{name}` must name the dialect `{}` (emulator:scanrig, emulator:horus or emulator:fabscan)", c.dialect.name()),
                    );
                }
            }
            Ok(_) => {}
            Err(e) => bad("controller.port", e.to_string()),
        }
        if !(300..=4_000_000).contains(&c.baud) {
            bad("controller.baud", format!("must be between 300 and 4000000, got {}", c.baud));
        }
        match c.steps_per_turn {
            Some(0) => bad("controller.steps_per_turn", "must be at least 1".into()),
            None if c.dialect != SerialDialect::Scanrig => bad(
                "controller.steps_per_turn",
                format!(
                    "the {} dialect cannot ask the board; set it (a wrong value mirrors or stretches scans)",
                    c.dialect.name()
                ),
            ),
            _ => {}
        }
        if c.lasers > 255 || (c.dialect == SerialDialect::Fabscan && c.lasers > 2) {
            bad("controller.lasers", "too many lasers for this dialect (FabScan: 2, others: 255)".into());
        }
        if !(c.speed_deg_per_s.is_finite() && c.speed_deg_per_s > 0.0) {
            bad("controller.speed_deg_per_s", "must be a positive number".into());
        }
        if c.reply_timeout_ms == 0 || c.reply_timeout_ms > 60_000 {
            bad("controller.reply_timeout_ms", "must be between 1 and 60000".into());
        }
        if c.retries > 20 {
            bad("controller.retries", "must be at most 20".into());
        }
        if c.handshake_attempts == 0 || c.handshake_attempts > 20 {
            bad("controller.handshake_attempts", "must be between 1 and 20".into());
        }
        if c.boot_ms > 30_000 {
            bad("controller.boot_ms", "must be at most 30000".into());
        }
        if c.reconnect_max_ms == 0 || c.reconnect_max_ms > 600_000 {
            bad("controller.reconnect_max_ms", "must be between 1 and 600000".into());
        }
        if let Some(lights) = &self.lights {
            if serial_lights && lights.lasers.len() > c.lasers as usize && c.dialect != SerialDialect::Scanrig {
                bad(
                    "lights.laser",
                    format!("{} lasers configured but the board has {}", lights.lasers.len(), c.lasers),
                );
            }
        }
        let e = &c.emulator;
        if !(e.speed_deg_per_s.is_finite() && e.speed_deg_per_s > 0.0) {
            bad("controller.emulator.speed_deg_per_s", "must be a positive number".into());
        }
        if e.steps_per_turn == Some(0) {
            bad("controller.emulator.steps_per_turn", "must be at least 1".into());
        }
        if e.lights > 255 || e.boot_ms > 30_000 {
            bad("controller.emulator", "lights must be at most 255 and boot_ms at most 30000".into());
        }
    }

    /// Every problem with the values of this rig (ranges, consistency between sections), at once.
    pub fn validate(&self) -> Vec<Problem> {
        let mut out = Vec::new();
        let mut bad = |key: &str, message: String| out.push(Problem { key: key.to_owned(), line: None, message });

        match &self.turntable {
            TurntableConfig::Sim(t) => {
                if t.steps_per_turn == 0 {
                    bad("turntable.steps_per_turn", "must be at least 1".into());
                }
                if !(t.speed_deg_per_s.is_finite() && t.speed_deg_per_s > 0.0) {
                    bad("turntable.speed_deg_per_s", format!("must be a positive number, got {}", t.speed_deg_per_s));
                }
            }
            TurntableConfig::Serial(_) => {}
        }
        self.validate_controller(&mut bad);

        let light_count = self.lights.as_ref().map_or(0, |l| l.lights.len());
        if let Some(lights) = &self.lights {
            for (i, l) in lights.lights.iter().enumerate() {
                if !l.position_m.iter().all(|v| v.is_finite()) {
                    bad(&format!("lights.light.{i}.position_m"), "must be finite".into());
                }
                if !(l.intensity.is_finite() && l.intensity >= 0.0) {
                    bad(&format!("lights.light.{i}.intensity"), "must be a non-negative number".into());
                }
            }
            for (i, l) in lights.lasers.iter().enumerate() {
                let n = l.plane_normal;
                if !(n.iter().all(|v| v.is_finite()) && n.iter().map(|v| v * v).sum::<f64>() > 1e-18) {
                    bad(&format!("lights.laser.{i}.plane_normal"), "must be a finite, non-zero vector".into());
                }
            }
        }

        let check_camera =
            |bad: &mut dyn FnMut(&str, String), section: &str, w: u32, h: u32, cal: &CameraCalibration| {
                if w == 0 || h == 0 || w > 16384 || h > 16384 {
                    bad(&format!("{section}.width"), format!("image size {w}x{h} is not between 1 and 16384 pixels"));
                }
                let k = &cal.intrinsics;
                if !(k.fx.is_finite() && k.fx > 0.0 && k.fy.is_finite() && k.fy > 0.0) {
                    bad(&format!("{section}.calibration.intrinsics.fx"), "focal lengths must be positive".into());
                }
                if ![k.cx, k.cy, k.skew].iter().chain(k.distortion().iter()).all(|v| v.is_finite()) {
                    bad(&format!("{section}.calibration.intrinsics"), "values must be finite".into());
                }
                match &cal.pose {
                    PoseConfig::LookAt { eye_m, target_m, up } => {
                        let e = Vector3::from(*eye_m);
                        let t = Vector3::from(*target_m);
                        let u = Vector3::from(*up);
                        if !(e.iter().chain(t.iter()).chain(u.iter()).all(|v| v.is_finite())) {
                            bad(&format!("{section}.calibration.pose"), "values must be finite".into());
                        } else if (t - e).norm() < 1e-9 || (t - e).normalize().cross(&u).norm() < 1e-6 {
                            bad(
                                &format!("{section}.calibration.pose.target_m"),
                                "target must differ from eye and the view must not be parallel to `up`".into(),
                            );
                        }
                    }
                    PoseConfig::Matrix { rotation, translation_m } => {
                        let r = crate::geometry::Matrix3::from_fn(|i, j| rotation[i][j]);
                        let err = (r * r.transpose() - crate::geometry::Matrix3::identity()).norm();
                        if !(err < 1e-6 && (r.determinant() - 1.0).abs() < 1e-6) {
                            bad(&format!("{section}.calibration.pose.rotation"), "is not a rotation matrix".into());
                        }
                        if !translation_m.iter().all(|v| v.is_finite()) {
                            bad(&format!("{section}.calibration.pose.translation_m"), "must be finite".into());
                        }
                    }
                }
            };

        let mut uses_sim = matches!(self.turntable, TurntableConfig::Sim(_));
        match &self.camera {
            CameraConfig::Sim(c) => {
                uses_sim = true;
                check_camera(&mut bad, "camera", c.width, c.height, &c.calibration);
                if c.buffer_depth == 0 || c.buffer_depth > 32 {
                    bad("camera.buffer_depth", "must be between 1 and 32".into());
                }
                if !(c.noise_sigma.is_finite() && c.noise_sigma >= 0.0) {
                    bad("camera.noise_sigma", "must be a non-negative number".into());
                }
            }
            CameraConfig::V4l2(c) | CameraConfig::Uvc(c) => {
                check_camera(&mut bad, "camera", c.width, c.height, &c.calibration);
                crate::devices::hardware::validate_camera(&self.camera, c, &mut bad);
            }
        }
        match &self.projector {
            Some(ProjectorConfig::Sim(p)) => {
                uses_sim = true;
                check_camera(&mut bad, "projector", p.width, p.height, &p.calibration);
                if !(p.gamma.is_finite() && (0.2..=5.0).contains(&p.gamma)) {
                    bad("projector.gamma", "must be between 0.2 and 5".into());
                }
                if !(p.black_level.is_finite() && (0.0..1.0).contains(&p.black_level)) {
                    bad("projector.black_level", "must be in 0..1".into());
                }
            }
            Some(ProjectorConfig::Fbdev(p)) => {
                if let Some(cal) = &p.calibration {
                    check_camera(&mut bad, "projector", p.width, p.height, cal);
                    if p.procam.is_some() {
                        bad("projector.procam", "give either `procam` or `[projector.calibration]`, not both".into());
                    }
                }
                crate::devices::hardware::validate_fbdev(p, &mut bad);
            }
            None => {}
        }
        match &self.depth_camera {
            Some(DepthCameraConfig::Sim(d)) => {
                uses_sim = true;
                check_camera(&mut bad, "depth_camera", d.width, d.height, &d.calibration);
            }
            Some(DepthCameraConfig::Freenect(d)) => {
                check_camera(
                    &mut bad,
                    "depth_camera",
                    FreenectDepthConfig::WIDTH,
                    FreenectDepthConfig::HEIGHT,
                    &d.calibration,
                );
                crate::devices::hardware::validate_freenect(d, &mut bad);
            }
            None => {}
        }
        if self.lights.as_ref().is_some_and(|l| l.kind == LightsKind::Sim) {
            uses_sim = true;
        }
        match &self.sim {
            None if uses_sim => bad("sim", "a `[sim]` section is needed when a device has kind = \"sim\"".into()),
            Some(s) => {
                if !crate::sim::SCENE_NAMES.contains(&s.scene.as_str()) {
                    bad(
                        "sim.scene",
                        format!("unknown scene `{}`; known: {}", s.scene, crate::sim::SCENE_NAMES.join(", ")),
                    );
                }
                if !(s.scale.is_finite() && s.scale > 0.0) {
                    bad("sim.scale", "must be a positive number".into());
                }
                if !(s.ambient.is_finite() && (0.0..=1.0).contains(&s.ambient)) {
                    bad("sim.ambient", "must be between 0 and 1".into());
                }
            }
            None => {}
        }

        let plan = &self.scan;
        if plan.positions == 0 || plan.positions > 100_000 {
            bad("scan.positions", format!("must be between 1 and 100000, got {}", plan.positions));
        }
        if !plan.start_deg.is_finite() {
            bad("scan.start_deg", "must be finite".into());
        }
        for (i, &l) in plan.lights.iter().enumerate() {
            if l >= light_count {
                bad(
                    &format!("scan.lights.{i}"),
                    format!("light {l} does not exist: the rig has {light_count} light(s)"),
                );
            }
        }
        for (i, &l) in plan.shadow_lights.iter().enumerate() {
            if l >= light_count {
                bad(
                    &format!("scan.shadow_lights.{i}"),
                    format!("light {l} does not exist: the rig has {light_count} light(s)"),
                );
            } else if plan.shadow_lights[..i].contains(&l) {
                bad(&format!("scan.shadow_lights.{i}"), format!("light {l} is named twice"));
            }
        }
        if self.reconstruction.method == Method::ShadowCarving && plan.shadow_lights.is_empty() {
            bad("scan.shadow_lights", "method \"shadow-carving\" needs at least one light here".into());
        }
        if self.reconstruction.method == Method::DepthFusion {
            if self.depth_camera.is_none() {
                bad("depth_camera", "method \"depth-fusion\" needs a [depth_camera]".into());
            }
            let t = self.reconstruction.depth_fusion.truncation_voxels;
            if !(t.is_finite() && t > 0.0) {
                bad("reconstruction.depth_fusion.truncation_voxels", "must be a positive number of voxels".into());
            }
        }
        if self.reconstruction.method == Method::Laser {
            let lasers = self.lights.as_ref().map_or(0, |l| l.lasers.len());
            for (key, message) in self.reconstruction.laser.problems(lasers) {
                bad(&key, message);
            }
        }
        structured_light::validate(self, &mut bad);
        if plan.capture_timeout_ms == 0 {
            bad("scan.capture_timeout_ms", "must be at least 1".into());
        }
        if plan.move_timeout_ms == 0 {
            bad("scan.move_timeout_ms", "must be at least 1".into());
        }

        let r = &self.reconstruction;
        if !r.bbox().is_valid() {
            bad("reconstruction.bbox_max_m", "the working volume must be finite with max > min on every axis".into());
        }
        if r.resolution < 2 || r.resolution > 4096 {
            bad("reconstruction.resolution", format!("must be between 2 and 4096 voxels, got {}", r.resolution));
        }
        let s = &r.silhouette;
        if !(s.threshold.is_finite() && (0.0..1.0).contains(&s.threshold)) {
            bad("reconstruction.silhouette.threshold", format!("must be in [0, 1), got {}", s.threshold));
        }
        if s.dilate_px > 64 || s.erode_px > 64 {
            bad("reconstruction.silhouette.dilate_px", "disc radii above 64 pixels are not supported".into());
        }
        if r.mesh.smooth_radius > crate::pipeline::MeshParams::MAX_SMOOTH_RADIUS {
            bad(
                "reconstruction.mesh.smooth_radius",
                format!("must be at most {} voxels", crate::pipeline::MeshParams::MAX_SMOOTH_RADIUS),
            );
        }
        let p = &r.photo;
        if !(p.threshold.is_finite() && p.threshold > 0.0 && p.threshold <= 255.0) {
            bad("reconstruction.photo.threshold", format!("must be in (0, 255] levels, got {}", p.threshold));
        }
        if p.min_ncc.is_some_and(|n| !(-1.0..=1.0).contains(&n)) {
            bad("reconstruction.photo.min_ncc", "must be in [-1, 1]".into());
        }
        if p.min_views < 2 {
            bad("reconstruction.photo.min_views", format!("must be at least 2, got {}", p.min_views));
        }
        if !(-1.0..=1.0).contains(&p.min_cos) {
            bad("reconstruction.photo.min_cos", format!("must be in [-1, 1], got {}", p.min_cos));
        }
        if !(p.arc_deg.is_finite() && p.arc_deg > 0.0 && p.arc_deg < 180.0) {
            bad("reconstruction.photo.arc_deg", format!("must be in (0, 180) degrees, got {}", p.arc_deg));
        }
        out
    }
}

#[cfg(test)]
mod tests;
