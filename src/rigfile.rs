//! Loading a rig file: the layers compose here, one level above them. The rig file's schema and
//! values are the config layer's ([`crate::config::parse_with`]); the drivers check their own
//! settings ([`crate::devices::hardware::check`]), reported with the config's problems, all at once
//! with their lines; then the calibration file of `[rig] calibration` and an fbdev projector's
//! `procam` file (both relative to the rig file's directory) are applied by the calibration layer.

use std::path::{Path, PathBuf};

use crate::config::{self, ConfigError, ProjectorConfig, RigConfig};

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

/// Read a rig file, check it (values and device settings) and apply its calibration file.
pub fn load(path: &Path) -> Result<RigConfig, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read { path: path.to_owned(), source })?;
    parse(&text, path)
}

/// [`load`] on rig-file text; `path` names it in messages and locates the calibration file.
pub fn parse(text: &str, path: &Path) -> Result<RigConfig, ConfigError> {
    let mut config = config::parse_with(text, path, crate::devices::hardware::check)?;
    if let Some(rel) = config.rig.calibration.clone() {
        let file = path.parent().map_or(rel.clone(), |d| d.join(&rel));
        crate::calibration::file::apply_to_rig(&file, &mut config).map_err(|source| ConfigError::Calibration {
            path: path.to_owned(),
            line: config::line_of(text, "rig.calibration").unwrap_or(1),
            source: Box::new(source),
        })?;
    }
    if let Some(ProjectorConfig::Fbdev(p)) = &config.projector {
        if let Some(rel) = p.procam.clone() {
            let file = path.parent().map_or(rel.clone(), |d| d.join(&rel));
            crate::calibration::procam_cloud::apply_procam_to_rig(&file, &mut config).map_err(|source| {
                let line = config::line_of(text, "projector.procam").unwrap_or(1);
                ConfigError::Procam(Box::new(ProcamConfigError { path: path.to_owned(), line, file, source }))
            })?;
        }
    }
    Ok(config)
}
