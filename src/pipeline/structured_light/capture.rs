//! Loading a captured pattern sequence from disk: a directory of 8-bit images whose names sort in
//! sequence order (e.g. `graycode_00.png` .. `graycode_41.png`), all of one camera size.

use std::path::{Path, PathBuf};

use rayon::prelude::*;

/// Errors of [`load_capture_dir`] and [`load_capture_files`]; each names the file or directory.
#[derive(Debug, thiserror::Error)]
pub enum CaptureError {
    /// The directory could not be listed.
    #[error("cannot list {}", dir.display())]
    ListDir {
        /// The directory.
        dir: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The directory holds the wrong number of images for the pattern sequence.
    #[error("{} holds {found} images, the pattern sequence has {expected}", dir.display())]
    Count {
        /// The directory.
        dir: PathBuf,
        /// Images the sequence has.
        expected: usize,
        /// Images found.
        found: usize,
    },
    /// An image could not be read or decoded.
    #[error("cannot read image {}", path.display())]
    Read {
        /// The image file.
        path: PathBuf,
        /// The decoder's error.
        #[source]
        source: image::ImageError,
    },
    /// An image's size differs from the first image's.
    #[error(
        "{} is {}x{} pixels, the first image of the sequence is {}x{}",
        path.display(), found.0, found.1, expected.0, expected.1
    )]
    Size {
        /// The image file.
        path: PathBuf,
        /// Size of the first image, pixels.
        expected: (u32, u32),
        /// Size of this image, pixels.
        found: (u32, u32),
    },
}

/// A captured sequence in memory: 8-bit grey, row-major, `width * height` bytes per image.
#[derive(Debug, Clone)]
pub struct Capture {
    /// Camera width, pixels.
    pub width: usize,
    /// Camera height, pixels.
    pub height: usize,
    /// The images in sequence order.
    pub images: Vec<Vec<u8>>,
    /// Where each image came from.
    pub paths: Vec<PathBuf>,
}

impl Capture {
    /// The images as slices, as [`super::decode`] takes them.
    pub fn slices(&self) -> Vec<&[u8]> {
        self.images.iter().map(Vec::as_slice).collect()
    }
}

/// Image files of a directory (png, pgm, bmp, tif/tiff, jpg/jpeg), sorted by name.
pub fn list_images(dir: &Path) -> Result<Vec<PathBuf>, CaptureError> {
    let list_err = |source| CaptureError::ListDir { dir: dir.to_path_buf(), source };
    let mut paths = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(list_err)? {
        let path = entry.map_err(list_err)?.path();
        let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
        if matches!(ext.as_deref(), Some("png" | "pgm" | "bmp" | "tif" | "tiff" | "jpg" | "jpeg")) && path.is_file() {
            paths.push(path);
        }
    }
    paths.sort();
    Ok(paths)
}

/// Loads the `expected` images of a directory (sorted by name), converting colour to grey.
pub fn load_capture_dir(dir: &Path, expected: usize) -> Result<Capture, CaptureError> {
    let paths = list_images(dir)?;
    if paths.len() != expected {
        return Err(CaptureError::Count { dir: dir.to_path_buf(), expected, found: paths.len() });
    }
    load_capture_files(&paths)
}

/// Loads the given image files in order (in parallel), converting colour to grey; all must have the
/// size of the first.
pub fn load_capture_files(paths: &[PathBuf]) -> Result<Capture, CaptureError> {
    let loaded: Vec<image::GrayImage> = paths
        .par_iter()
        .map(|p| {
            image::open(p).map(|i| i.into_luma8()).map_err(|source| CaptureError::Read { path: p.clone(), source })
        })
        .collect::<Result<_, _>>()?;
    let expected = loaded.first().map(|i| i.dimensions()).unwrap_or((0, 0));
    if let Some((img, path)) = loaded.iter().zip(paths).find(|(i, _)| i.dimensions() != expected) {
        return Err(CaptureError::Size { path: path.clone(), expected, found: img.dimensions() });
    }
    Ok(Capture {
        width: expected.0 as usize,
        height: expected.1 as usize,
        images: loaded.into_iter().map(|i| i.into_raw()).collect(),
        paths: paths.to_vec(),
    })
}
