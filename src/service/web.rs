//! The web console's static files (`web/` in the repository), embedded in the binary at build
//! time and served under `/web/{path}`: the page's scripts and style sheet and the vendored
//! three.js r187 (`web/vendor/three/`, see its README). Only the paths listed here exist, so no
//! request path can reach anything else on disk.

/// One embedded file: its path under `web/`, its content type and its bytes.
#[derive(Debug, Clone, Copy)]
pub struct WebFile {
    /// Path under `web/`, `/`-separated, no leading slash.
    pub path: &'static str,
    /// The `Content-Type` it is served with.
    pub content_type: &'static str,
    /// The file's bytes.
    pub bytes: &'static [u8],
}

const JS: &str = "text/javascript; charset=utf-8";

macro_rules! web_files {
    ($($path:literal => $mime:expr),* $(,)?) => {
        &[$(WebFile { path: $path, content_type: $mime, bytes: include_bytes!(concat!("../../web/", $path)) }),*]
    };
}

/// Every file served under `/web/`.
pub const FILES: &[WebFile] = web_files![
    "index.html" => "text/html; charset=utf-8",
    "style.css" => "text/css; charset=utf-8",
    "app.js" => JS,
    "viewer.js" => JS,
    "words.js" => JS,
    "vendor/three/build/three.module.js" => JS,
    "vendor/three/build/three.core.js" => JS,
    "vendor/three/examples/jsm/controls/OrbitControls.js" => JS,
    "vendor/three/examples/jsm/loaders/PLYLoader.js" => JS,
    "vendor/three/LICENSE" => "text/plain; charset=utf-8",
    "vendor/three/README.md" => "text/plain; charset=utf-8",
];

/// The embedded file at `path` (relative to `web/`), if there is one.
pub fn lookup(path: &str) -> Option<&'static WebFile> {
    FILES.iter().find(|f| f.path == path)
}

#[cfg(test)]
mod tests {
    use super::lookup;

    #[test]
    fn only_listed_files_are_found() {
        let three = lookup("vendor/three/build/three.module.js").expect("three.js");
        assert!(three.content_type.starts_with("text/javascript"));
        assert!(three.bytes.len() > 100_000);
        for bad in ["", "/app.js", "../Cargo.toml", "vendor/../app.js", "vendor/three/", "APP.JS", "app.js/"] {
            assert!(lookup(bad).is_none(), "{bad}");
        }
    }
}
