//! The bearer token's policy, shared by `scanrigd` and the `scanrig` CLI: a token comes from a
//! file that only its owner can read, or from an environment variable, never from the command
//! line (where `ps` shows it); an empty or whitespace-only token is refused.

use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};

/// Why a token could not be used.
#[derive(Debug, thiserror::Error)]
pub enum TokenError {
    /// The file could not be read.
    #[error("cannot read the token file {path}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The error.
        #[source]
        source: std::io::Error,
    },
    /// The file may be read by other users.
    #[error("the token file {path} is readable by its group or others (mode {mode:03o}); run `chmod 600 {path}`")]
    Permissions {
        /// The file.
        path: PathBuf,
        /// Its permission bits.
        mode: u32,
    },
    /// The token is empty or only whitespace.
    #[error("the token in {from} is empty")]
    Empty {
        /// The file or environment variable.
        from: String,
    },
}

/// Read the token in `path`: the file must not be group- or world-readable, and the token (the
/// file's text without surrounding whitespace) must not be empty.
pub fn from_file(path: &Path) -> Result<String, TokenError> {
    let read = |source| TokenError::Read { path: path.to_owned(), source };
    let meta = std::fs::metadata(path).map_err(read)?;
    let mode = meta.permissions().mode() & 0o777;
    if mode & 0o044 != 0 {
        return Err(TokenError::Permissions { path: path.to_owned(), mode });
    }
    let text = std::fs::read_to_string(path).map_err(read)?;
    checked(text.trim(), &path.display().to_string())
}

/// The token in environment variable `var`, if it is set; an empty or whitespace value is refused.
pub fn from_env(var: &str) -> Result<Option<String>, TokenError> {
    match std::env::var(var) {
        Ok(v) => checked(v.trim(), var).map(Some),
        Err(_) => Ok(None),
    }
}

fn checked(token: &str, from: &str) -> Result<String, TokenError> {
    if token.is_empty() {
        Err(TokenError::Empty { from: from.to_owned() })
    } else {
        Ok(token.to_owned())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn empty_and_readable_token_files_are_refused() {
        let dir = tempfile::tempdir().expect("tempdir");
        let f = dir.path().join("t");
        for (text, mode, ok) in [
            ("tok\n", 0o600, true),
            (" \n\t", 0o600, false),
            ("", 0o400, false),
            ("tok", 0o640, false),
            ("tok", 0o604, false),
        ] {
            std::fs::write(&f, text).expect("write");
            std::fs::set_permissions(&f, std::fs::Permissions::from_mode(mode)).expect("chmod");
            assert_eq!(from_file(&f).is_ok(), ok, "{text:?} {mode:o}");
        }
    }
}
