//! Where the tests find the real data sets: `../shared/data/NAME` beside the checkout (relative to
//! `CARGO_MANIFEST_DIR`), or `$SCANRIG_SHARED_DATA/NAME` when that variable is set. A missing data
//! set skips the test with a message on a developer machine and FAILS it when `CI` is set (CI has the
//! data beside the checkout; a skipped data-set test there would hide a broken setup).

use std::path::{Path, PathBuf};

/// The data set `name`, or `None` (after printing why) when it is absent outside CI.
///
/// # Panics
/// When the data set is absent and the environment variable `CI` is set.
pub fn dataset(name: &str) -> Option<PathBuf> {
    let root = match std::env::var_os("SCANRIG_SHARED_DATA") {
        Some(d) => PathBuf::from(d),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data"),
    };
    let dir = root.join(name);
    if dir.is_dir() {
        return Some(dir);
    }
    if std::env::var_os("CI").is_some_and(|v| !v.is_empty()) {
        panic!("data set {} is missing (CI is set, so this fails instead of skipping)", dir.display());
    }
    println!("skipped: data set {} is absent", dir.display());
    None
}
