//! The rig file: TOML schema ([`schema`]), loading with file:line errors, and [`RigConfig::validate`],
//! which reports every problem at once.

pub mod replication;
pub mod schema;
pub mod structured_light;
pub mod vocab;

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
    /// The `[projector] procam` file could not be used (the message names the rig file, the line of
    /// `projector.procam` and the procam file; the source is the calibration layer's error).
    #[error("{0}")]
    Procam(Box<dyn std::error::Error + Send + Sync>),
    /// The calibration file named by `[rig] calibration` could not be read or does not fit the rig.
    #[error("{path}:{line}: `rig.calibration`: cannot use the calibration file")]
    Calibration {
        /// The rig file.
        path: PathBuf,
        /// 1-based line of the `calibration` key.
        line: usize,
        /// What is wrong with the calibration file (the calibration layer's error).
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
}

/// Read, parse and check the values of a rig file (this layer only: the device checks and the
/// calibration file are composed on top by [`crate::rigfile::load`]).
pub fn load(path: &Path) -> Result<RigConfig, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read { path: path.to_owned(), source })?;
    parse(&text, path)
}

/// Parse rig-file text and check its values; `path` is used in messages.
pub fn parse(text: &str, path: &Path) -> Result<RigConfig, ConfigError> {
    parse_with(text, path, |_| Vec::new())
}

/// Parse rig-file text and check its values plus the problems `more` finds (a higher layer's, e.g.
/// the drivers' checks of their settings), all reported at once with their lines: every unknown key
/// and misspelled section first, then the values.
pub fn parse_with(
    text: &str,
    path: &Path,
    more: impl FnOnce(&RigConfig) -> Vec<Problem>,
) -> Result<RigConfig, ConfigError> {
    let (config, mut problems) = deserialize_all(text, path)?;
    let mut values = config.validate();
    values.extend(more(&config));
    locate(text, &mut values);
    problems.extend(values);
    if !problems.is_empty() {
        return Err(ConfigError::Invalid { path: path.to_owned(), problems });
    }
    Ok(config)
}

/// The 1-based line of `key` (dotted path) in rig-file `text`, if it is there.
pub fn line_of(text: &str, key: &str) -> Option<usize> {
    let mut p = [Problem { key: key.into(), line: None, message: String::new() }];
    locate(text, &mut p);
    p[0].line
}

/// Deserialize the rig file, reporting every unknown key and misspelled section at once: each
/// unknown key found is recorded with its line and commented out (line numbers stay the same),
/// and the file is parsed again, up to [`MAX_UNKNOWN`] times. A misspelled section header takes
/// its whole section with it, so the missing section it leaves is reported too, after it.
fn deserialize_all(text: &str, path: &Path) -> Result<(RigConfig, Vec<Problem>), ConfigError> {
    let mut working: Vec<String> = text.split('\n').map(str::to_owned).collect();
    let mut problems: Vec<Problem> = Vec::new();
    // Unknown top-level keys and sections first: the parser reads sections in name order and may
    // stop at a missing field of a section a misspelled header leaves behind before it gets to them.
    let known = top_level_fields();
    if let (Ok(doc), false) = (toml_edit::Document::parse(text), known.is_empty()) {
        for (key, _) in doc.as_table().iter() {
            if known.iter().any(|k| k == key) {
                continue;
            }
            let Some(span) = doc.as_table().get_key_value(key).and_then(|(k, _)| k.span()) else { continue };
            let line = line_col(text, span.start).0;
            let message = format!("unknown section or key `{key}`, expected one of {}", known.join(", "));
            // Its own lines, and every `[key.sub]` section under it.
            let mut cut = Vec::new();
            if let Some((first, last, _)) = find_unknown(&working, line, key) {
                cut.push((first, last));
            }
            for (i, l) in working.iter().enumerate() {
                let t = l.trim();
                if t.starts_with('[') && t.trim_start_matches('[').starts_with(&format!("{key}.")) {
                    let end =
                        (i + 1..working.len()).find(|&j| working[j].trim().starts_with('[')).unwrap_or(working.len());
                    cut.push((i, end - 1));
                }
            }
            for (first, last) in cut {
                for l in &mut working[first..=last] {
                    if !l.starts_with('#') {
                        l.insert(0, '#');
                    }
                }
            }
            problems.push(Problem { key: key.to_owned(), line: Some(line), message });
        }
    }
    // Then unknown keys inside each section, section by section, so that a missing field in one
    // section does not hide an unknown key in another.
    for name in &known {
        section_unknowns(&mut working, name, &mut problems);
    }
    for _ in 0..=MAX_UNKNOWN {
        let joined = working.join("\n");
        let e = match toml::from_str::<RigConfig>(&joined) {
            // With the unknown keys left out, the values are checked too.
            Ok(config) => return Ok((config, problems)),
            Err(e) => e,
        };
        let (line, column) = e.span().map(|s| line_col(&joined, s.start)).unwrap_or((1, 1));
        let message = e.message().trim().to_owned();
        let unknown =
            message.strip_prefix("unknown field `").and_then(|m| m.split_once('`')).map(|(field, _)| field.to_owned());
        if let Some((first, last, key)) = unknown.as_deref().and_then(|f| find_unknown(&working, line, f)) {
            problems.push(Problem { key, line: Some(first + 1), message });
            for l in &mut working[first..=last] {
                l.insert(0, '#');
            }
            continue;
        }
        if problems.is_empty() {
            return Err(ConfigError::Parse { path: path.to_owned(), line, column, message });
        }
        // What the earlier problems left (a missing section, a syntax error): reported after them.
        let key = section_of(&working, line.saturating_sub(1)).unwrap_or_default();
        problems.push(Problem { key, line: Some(line), message: format!("{message} (column {column})") });
        return Err(ConfigError::Invalid { path: path.to_owned(), problems });
    }
    Err(ConfigError::Invalid { path: path.to_owned(), problems })
}

/// Deserialize section `name` of the (partly commented-out) file on its own and record each of its
/// unknown keys (commenting it out and going on). Other errors are left for the whole-file parse.
fn section_unknowns(working: &mut [String], name: &str, problems: &mut Vec<Problem>) {
    fn probe<T: serde::de::DeserializeOwned>(v: toml::Value) -> Option<String> {
        let e = T::deserialize(v).err()?;
        let m = e.message().trim().to_owned();
        m.starts_with("unknown field `").then_some(m)
    }
    for _ in 0..MAX_UNKNOWN {
        let Ok(table) = toml::from_str::<toml::Table>(&working.join("\n")) else { return };
        let Some(v) = table.get(name).cloned() else { return };
        let message = match name {
            "rig" => probe::<RigSection>(v),
            "turntable" => probe::<TurntableConfig>(v),
            "lights" => probe::<LightsConfig>(v),
            "camera" => probe::<CameraConfig>(v),
            "projector" => probe::<ProjectorConfig>(v),
            "depth_camera" => probe::<DepthCameraConfig>(v),
            "controller" => probe::<ControllerConfig>(v),
            "sim" => probe::<SimConfig>(v),
            "scan" => probe::<ScanPlan>(v),
            "reconstruction" => probe::<ReconstructionConfig>(v),
            _ => None,
        };
        let Some(message) = message else { return };
        let Some(field) = message.strip_prefix("unknown field `").and_then(|m| m.split_once('`')).map(|(f, _)| f)
        else {
            return;
        };
        // The first live line in this section (or its subsections) that is the key or a header for it.
        let in_section = |i: usize| {
            section_of(working, i).is_some_and(|s| {
                let s = s.trim_start_matches('[').trim();
                s == name || s.starts_with(&format!("{name}."))
            })
        };
        let hit = (0..working.len())
            .filter(|&i| !working[i].trim_start().starts_with('#') && in_section(i))
            .find_map(|i| find_unknown(working, i + 1, field).filter(|(first, _, _)| *first == i));
        let Some((first, last, key)) = hit else { return };
        let key = if key.starts_with(name) { key } else { format!("{name}.{key}") };
        problems.push(Problem { key, line: Some(first + 1), message });
        for l in &mut working[first..=last] {
            l.insert(0, '#');
        }
    }
}

/// The top-level keys of a rig file, as the parser itself lists them for an unknown one (so the
/// list cannot drift from the schema).
fn top_level_fields() -> Vec<String> {
    let Err(e) = toml::from_str::<RigConfig>("unknown_key_probe = 1") else { return Vec::new() };
    let message = e.message().to_owned();
    let Some((_, list)) = message.split_once("expected one of ") else { return Vec::new() };
    list.split(',').map(|f| f.trim().trim_matches('`').to_owned()).filter(|f| !f.is_empty()).collect()
}

/// How many unknown keys one report names at most.
pub const MAX_UNKNOWN: usize = 64;

/// The lines (0-based, inclusive) to comment out for the unknown `field` the parser reported at
/// 1-based `line`, and its dotted key: the key's line (and the lines its value continues on), or
/// a whole section when `field` is a misspelled section header. The parser points at the key
/// itself, or at the start of a section that is read as a whole (sections tagged by `kind`).
fn find_unknown(lines: &[String], line: usize, field: &str) -> Option<(usize, usize, String)> {
    let start = line.checked_sub(1)?;
    let is_key = |l: &str| {
        let t = l.trim_start();
        let rest = t.strip_prefix(field).or_else(|| t.strip_prefix(&format!("\"{field}\"")));
        rest.is_some_and(|r| {
            let r = r.trim_start();
            r.starts_with('=') || r.starts_with('.')
        })
    };
    let header = |l: &str| {
        let t = l.trim();
        (t.starts_with('[') && !t.starts_with("#")).then(|| t.trim_matches(|c| c == '[' || c == ']').trim().to_owned())
    };
    // A header naming `field`: the whole section (up to the next header) goes.
    if let Some(name) = lines.get(start).and_then(|l| header(l)) {
        if name == field || name.ends_with(&format!(".{field}")) {
            let end = (start + 1..lines.len()).find(|&i| header(&lines[i]).is_some()).map_or(lines.len(), |i| i) - 1;
            return Some((start, end, name));
        }
    }
    // Otherwise the key, at that line or further down in the same section.
    let mut i = start;
    while i < lines.len() {
        if i > start && header(&lines[i]).is_some() {
            break;
        }
        if !lines[i].trim_start().starts_with('#') && is_key(&lines[i]) {
            let end = value_end(lines, i);
            let key = match section_of(lines, i) {
                Some(s) if !s.is_empty() => format!("{s}.{field}"),
                _ => field.to_owned(),
            };
            return Some((i, end, key));
        }
        i += 1;
    }
    None
}

/// The last line of the value that starts on line `i`: brackets and braces opened there are
/// closed (multi-line arrays and inline tables), or it is the same line.
fn value_end(lines: &[String], i: usize) -> usize {
    let mut depth: i64 = 0;
    let mut in_str = false;
    for (k, l) in lines.iter().enumerate().skip(i) {
        for c in l.chars() {
            match c {
                '"' => in_str = !in_str,
                '#' if !in_str => break,
                '[' | '{' if !in_str => depth += 1,
                ']' | '}' if !in_str => depth -= 1,
                _ => {}
            }
        }
        if depth <= 0 {
            return k;
        }
    }
    lines.len() - 1
}

/// The name of the section (table header) line `i` (0-based) is in.
fn section_of(lines: &[String], i: usize) -> Option<String> {
    lines[..=i.min(lines.len().saturating_sub(1))].iter().rev().find_map(|l| {
        let t = l.trim();
        t.starts_with('[').then(|| t.trim_matches(|c| c == '[' || c == ']').trim().to_owned())
    })
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

const MIB: u64 = 1024 * 1024;

/// What a scan with this rig file holds in memory at its peak, estimated from the grid and the
/// frames (an upper bound of the big buffers; small ones are ignored). Bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MemoryEstimate {
    /// Voxels of the grid over the working volume.
    pub voxels: u64,
    /// The method's per-voxel buffers, bytes.
    pub grid_bytes: u64,
    /// Frames and their per-pixel buffers kept for the reconstruction, bytes.
    pub frame_bytes: u64,
}

impl MemoryEstimate {
    /// Grid plus frames, bytes.
    pub fn total(&self) -> u64 {
        self.grid_bytes.saturating_add(self.frame_bytes)
    }
}

impl RigConfig {
    /// Estimate the memory of a scan: the grid's voxels times the bytes the method keeps per voxel
    /// (space carving 12 B: measured peak RSS of `scanrig scan` on the simulated rig grows by
    /// 11.7 B a voxel from resolution 128 to 256; shadow carving 44 B (its peak RSS at 512^3 on the
    /// shipped rig, 512 x 512 x 431 voxels, was 4,909 MiB, 42.9 B a voxel over the frames: the
    /// per-position carving keeps candidate and blocker state per voxel on top of the grid); photo
    /// methods and depth fusion 20 B (colours or TSDF value and weight on top); structured light 28 B
    /// (free-space labels, distances, components, TSDF); laser 96 B (the same, and its cloud meshing
    /// and handle removal on a solid full of voxel-scale holes at fine grids: at 512^3 its RSS had
    /// reached 11.9 GB, 89 B a voxel, when the scan was stopped unfinished)),
    /// plus every frame kept: camera pixels x (RGB + mask + a u32 summed-area table) = 8 B a pixel,
    /// per position (and per shadow light for shadow carving).
    pub fn memory_estimate(&self) -> MemoryEstimate {
        let r = &self.reconstruction;
        let grid = crate::geometry::VoxelGrid::from_resolution(&r.bbox(), r.resolution);
        let voxels = grid.dims.iter().fold(1u64, |a, &d| a.saturating_mul(d as u64));
        let per_voxel = match r.method {
            Method::SpaceCarving => 12,
            Method::ShadowCarving => 44,
            Method::VoxelColoring | Method::SpaceCarvingPhoto => 20,
            Method::DepthFusion => 20,
            Method::StructuredLight => 28,
            Method::Laser => 96,
        };
        let (w, h) = match &self.camera {
            CameraConfig::Sim(c) => (c.width, c.height),
            CameraConfig::V4l2(c) | CameraConfig::Uvc(c) => (c.width, c.height),
            CameraConfig::Genicam(c) => (c.width, c.height),
        };
        let lightings = 1 + if r.method == Method::ShadowCarving { self.scan.shadow_lights.len() as u64 } else { 0 };
        let frames = u64::from(self.scan.positions).saturating_mul(lightings);
        let frame_bytes = frames.saturating_mul(u64::from(w) * u64::from(h) * 8);
        MemoryEstimate { voxels, grid_bytes: voxels.saturating_mul(per_voxel), frame_bytes }
    }

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
        match vocab::PortSpec::parse(&c.port) {
            Ok(vocab::PortSpec::Emulator(name)) => {
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
            }
            CameraConfig::Genicam(c) => {
                check_camera(&mut bad, "camera", c.width, c.height, &c.calibration);
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
            }
            Some(ProjectorConfig::Window(p)) => {
                if let Some(cal) = &p.calibration {
                    check_camera(&mut bad, "projector", p.width, p.height, cal);
                }
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
        if plan.lights.len() > 64 {
            bad("scan.lights", format!("at most 64 entries (one per light switched on), got {}", plan.lights.len()));
        } else {
            for (i, &l) in plan.lights.iter().enumerate() {
                if l >= light_count {
                    bad(
                        &format!("scan.lights.{i}"),
                        format!("light {l} is not one of the rig's lights: the rig has {light_count} light(s)"),
                    );
                }
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
        } else if r.bbox().is_valid() {
            let m = self.memory_estimate();
            let budget = r.memory_budget_mb.saturating_mul(MIB);
            if m.total() > budget {
                bad(
                    "reconstruction.resolution",
                    format!(
                        "resolution {} needs about {} MB (grid {} MB for {} voxels, frames {} MB), above the memory \
                         budget of {} MB (`reconstruction.memory_budget_mb`): lower the resolution or raise the budget",
                        r.resolution,
                        m.total() / MIB,
                        m.grid_bytes / MIB,
                        m.voxels,
                        m.frame_bytes / MIB,
                        r.memory_budget_mb
                    ),
                );
            }
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
        let e = r.mesh.max_error_voxels;
        if !(e.is_finite() && (0.0..=8.0).contains(&e)) {
            bad("reconstruction.mesh.max_error_voxels", format!("must be in [0, 8] voxels, got {e}"));
        }
        let p = &r.photo;
        if let Some(t) = p.threshold.filter(|t| !(t.is_finite() && *t > 0.0 && *t <= 255.0)) {
            bad("reconstruction.photo.threshold", format!("must be in (0, 255] levels, got {t}"));
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
        if let Some(r) = &self.replication {
            out.extend(r.validate());
        }
        out
    }
}

#[cfg(test)]
mod tests;
