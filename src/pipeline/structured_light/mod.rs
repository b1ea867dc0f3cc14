//! Structured light with binary / Gray-code stripes: pattern generation for a projector and
//! per-pixel decoding of a captured sequence into projector columns and rows.
//!
//! - [`patterns`]: the sequence (column pairs MSB first, row pairs, white, black) for any
//!   projector resolution.
//! - [`decode`](mod@decode): the row-wise, rayon-parallel decoder with black/white thresholds.
//! - [`phase`]: N-step phase shift with Gray-code or multi-frequency unwrapping (sub-pixel).
//! - [`debruijn`]: one-shot De Bruijn colour stripes; [`stripe`]: a single sweeping stripe.
//! - [`gamma`]: projector-camera response (black/white levels, gamma) and its compensation.
//! - [`codes`]: one interface over every coding, decoding to [`ProjectorCoords`].
//! - [`coords`]: continuous per-pixel projector coordinates, the input of triangulation.
//! - [`subpixel`]: stripe-edge interpolation of a decoded map into sub-pixel coordinates.
//! - [`triangulate`](mod@triangulate): camera ray against projector column plane or ray, with
//!   distortion, into a range image with normals, colours and outlier removal.
//! - [`capture`]: loading a captured sequence from a directory, with errors naming the file.

pub mod capture;
pub mod codes;
pub mod coords;
pub mod debruijn;
pub mod decode;
pub mod gamma;
pub mod patterns;
pub mod phase;
pub mod stripe;
pub mod subpixel;
pub mod triangulate;

use std::path::{Path, PathBuf};

pub use capture::{list_images, load_capture_dir, load_capture_files, Capture, CaptureError};
pub use codes::{CodesError, PatternSet};
pub use coords::{CoordsError, ProjectorCoords};
pub use decode::{decode, DecodeError, DecodeParams, ProjectorMap, INVALID};
pub use patterns::{Coding, GrayCodePatterns, PatternError, PatternKind};
pub use subpixel::interpolate_stripe_edges;
pub use triangulate::{RangeImage, TriangulateError, TriangulationParams, Triangulator};

/// Errors of [`save_map_png`].
#[derive(Debug, thiserror::Error)]
pub enum MapWriteError {
    /// A PNG could not be written.
    #[error("cannot write {}", path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// The encoder's error.
        #[source]
        source: image::ImageError,
    },
}

/// Writes the map as two 16-bit grey PNGs, `columns.png` and `rows.png` in `dir` (projector
/// pixels per camera pixel, 65535 where the pixel did not decode).
pub fn save_map_png(map: &ProjectorMap, dir: &Path) -> Result<(), MapWriteError> {
    for (name, data) in [("columns.png", map.columns()), ("rows.png", map.rows())] {
        let path = dir.join(name);
        let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(
            map.width() as u32,
            map.height() as u32,
            data.to_vec(),
        );
        let res = match img {
            Some(img) => img.save(&path),
            None => Err(image::ImageError::Parameter(image::error::ParameterError::from_kind(
                image::error::ParameterErrorKind::DimensionMismatch,
            ))),
        };
        res.map_err(|source| MapWriteError::Write { path, source })?;
    }
    Ok(())
}
