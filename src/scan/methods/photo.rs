//! The photo-consistency methods' part of a scan or reconstruction: from the visual hull and the
//! images to a carved, coloured model and its figures (`voxel-coloring`, `space-carving-photo`).
//!
//! The visual hull (silhouette carving, done by the caller) is the starting volume. Both methods use
//! every view: `voxel-coloring` runs one sweep per [`ordinal_sweeps`] entry, each with the views
//! that satisfy the ordinal visibility constraint along its direction (which views those are is in
//! the report); `space-carving-photo` judges every voxel against every view that sees it. The hull
//! is coloured the same way as the result, so the two can be compared (ground truth on simulated
//! rigs, photometric re-projection always).

use nalgebra::Vector3;
use rayon::prelude::*;

use crate::config::{Method, PhotoConfig};
use crate::geometry::VoxelGrid;
use crate::pipeline::photo_consistency::UNSEEN_COLOUR;
use crate::pipeline::{
    carve_photo, carve_photo_measured, color_voxels_sweeps, colour_surface, measure_noise_and_colour, ordinal_sweeps,
    reprojection_error, ColouredSurface, Occupancy, PhotoError, PhotoParams, PhotoView, TriangleMesh,
};
use crate::scan::report::{PhotoReport, VisualHull};

/// The pipeline parameters of a `[reconstruction.photo]` section; without a fixed threshold, the
/// pipeline's default stands in until [`reconstruct_photo`] measures the data's noise.
pub fn photo_params(c: &PhotoConfig) -> PhotoParams {
    PhotoParams {
        threshold: c.threshold.map_or(PhotoParams::default().threshold, |t| t as f32),
        min_ncc: c.min_ncc.map(|x| x as f32),
        min_views: c.min_views,
        min_cos: c.min_cos as f32,
        max_iterations: c.max_iterations,
    }
}

/// The simulated scene's truth on the result's grid: occupancy and the true surface colour (8-bit
/// RGB) at a grid-frame point, metres.
pub struct Truth<'a> {
    /// True occupancy on the same grid.
    pub occupancy: &'a Occupancy,
    /// True surface colour at a point.
    pub colour_at: &'a (dyn Fn(&Vector3<f64>) -> [u8; 3] + Sync),
}

impl std::fmt::Debug for Truth<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Truth").field("voxels", &self.occupancy.count()).finish_non_exhaustive()
    }
}

/// What the output writer needs from a photo-consistency run.
#[derive(Debug, Clone)]
pub struct PhotoOutputs {
    grid: VoxelGrid,
    /// The result's coloured surface.
    pub surface: ColouredSurface,
    /// Colour error of the result against the truth (simulated rigs).
    pub colour_error: Option<f64>,
    /// The hull, measured like the result.
    pub visual_hull: VisualHull,
    /// Counters and figures.
    pub report: PhotoReport,
}

/// Marks a voxel of [`PhotoOutputs::colour_grid`] that no seen surface voxel colours.
const NO_COLOUR: u32 = u32::MAX;

impl PhotoOutputs {
    /// Per voxel of the grid (linear index), the colour of the seen surface voxel there packed as
    /// `0xRRGGBB`, else [`NO_COLOUR`]: a flat table, so looking a voxel up costs one load.
    fn colour_grid(&self) -> Vec<u32> {
        let mut out = vec![NO_COLOUR; self.grid.len()];
        for ((v, c), &seen) in self.surface.voxels.iter().zip(&self.surface.colours).zip(&self.surface.seen) {
            if seen {
                out[self.grid.index(v[0] as usize, v[1] as usize, v[2] as usize)] =
                    u32::from_be_bytes([0, c[0], c[1], c[2]]);
            }
        }
        out
    }

    /// The colours of a result's mesh vertices and voxels, from one [`PhotoOutputs::colour_grid`]:
    /// see [`PhotoOutputs::mesh_colours`] and [`PhotoOutputs::voxel_colours`].
    pub fn colours(&self, mesh: &TriangleMesh, occupancy: &Occupancy) -> (Vec<[u8; 3]>, Vec<[u8; 3]>) {
        let table = self.colour_grid();
        (self.mesh_colours(&table, mesh), self.voxel_colours(&table, occupancy))
    }

    /// Colours of the occupied voxels of `occupancy` in `for_each_occupied` order: surface voxels
    /// take their colour, interior and unseen voxels [`UNSEEN_COLOUR`].
    fn voxel_colours(&self, table: &[u32], occupancy: &Occupancy) -> Vec<[u8; 3]> {
        let d = self.grid.dims;
        let mut out = Vec::new();
        occupancy.for_each_occupied(|i, j, k| {
            let c = if i < d[0] && j < d[1] && k < d[2] { table[self.grid.index(i, j, k)] } else { NO_COLOUR };
            out.push(unpack(c))
        });
        out
    }

    /// Vertex colours of a mesh of the result: each vertex takes the colour of the nearest seen
    /// surface voxel within two voxels ([`UNSEEN_COLOUR`] when there is none); ties go to the
    /// first in z, y, x order of the offsets.
    fn mesh_colours(&self, table: &[u32], mesh: &TriangleMesh) -> Vec<[u8; 3]> {
        let g = &self.grid;
        let dims = g.dims.map(|d| d as i64);
        let s = g.voxel_size as f32;
        mesh.vertices
            .par_iter()
            .map(|p| {
                let f = [0, 1, 2].map(|a| (p[a] - g.origin[a] as f32) / s - 0.5);
                let base = f.map(|x| x.round() as i64);
                let mut best: Option<(f32, u32)> = None;
                for dz in -2..=2i64 {
                    for dy in -2..=2i64 {
                        for dx in -2..=2i64 {
                            let c = [base[0] + dx, base[1] + dy, base[2] + dz];
                            if (0..3).any(|a| c[a] < 0 || c[a] >= dims[a]) {
                                continue;
                            }
                            let col = table[g.index(c[0] as usize, c[1] as usize, c[2] as usize)];
                            if col == NO_COLOUR {
                                continue;
                            }
                            let d2: f32 = (0..3).map(|a| (c[a] as f32 - f[a]).powi(2)).sum();
                            if best.is_none_or(|(b, _)| d2 < b) {
                                best = Some((d2, col));
                            }
                        }
                    }
                }
                best.map_or(UNSEEN_COLOUR, |b| unpack(b.1))
            })
            .collect()
    }
}

/// The colour of a [`PhotoOutputs::colour_grid`] entry ([`UNSEEN_COLOUR`] for [`NO_COLOUR`]).
fn unpack(c: u32) -> [u8; 3] {
    if c == NO_COLOUR {
        return UNSEEN_COLOUR;
    }
    let [_, r, g, b] = c.to_be_bytes();
    [r, g, b]
}

/// Mean absolute colour error per channel (0..255) of the seen surface voxels next to the true
/// surface, against the true colour at their centres.
fn colour_error(surface: &ColouredSurface, grid: &VoxelGrid, truth: &Truth<'_>) -> Option<f64> {
    let (mut sum, mut n) = (0f64, 0u64);
    for ((v, c), &seen) in surface.voxels.iter().zip(&surface.colours).zip(&surface.seen) {
        // Only voxels next to the true surface (their 3x3x3 neighbourhood holds both truly occupied
        // and truly empty voxels) have a true surface colour to compare with.
        let (a, b, c0) = (v[0] as i64, v[1] as i64, v[2] as i64);
        let mut inside = 0;
        for dz in -1..=1 {
            for dy in -1..=1 {
                for dx in -1..=1 {
                    inside += truth.occupancy.get_signed(a + dx, b + dy, c0 + dz) as u32;
                }
            }
        }
        if !seen || inside == 0 || inside == 27 {
            continue;
        }
        let t = (truth.colour_at)(&grid.centre(v[0] as usize, v[1] as usize, v[2] as usize));
        for ch in 0..3 {
            sum += (c[ch] as f64 - t[ch] as f64).abs();
        }
        n += 3;
    }
    (n > 0).then(|| sum / n as f64)
}

/// Run `method` (a photo method) from the visual `hull` with `views`, returning the carved occupancy
/// and what the output writer needs. `truth` adds ground-truth figures.
pub fn reconstruct_photo(
    method: Method,
    config: &PhotoConfig,
    hull: &Occupancy,
    views: &[PhotoView<'_>],
    truth: Option<&Truth<'_>>,
) -> Result<(Occupancy, PhotoOutputs), PhotoError> {
    let grid = *hull.grid();
    let used = views;
    // The threshold: fixed by the configuration, else derived from the measured noise of these
    // views over the hull's surface. Measuring it colours the hull's surface on the way (the
    // colouring only depends on `min_cos`, not on the threshold).
    // Generalized space carving measures on the state it then carves from, built once.
    let mut measured_model = None;
    let (params, noise, hull_coloured) = match config.threshold {
        Some(_) => (photo_params(config), None, None),
        None => {
            let p = photo_params(config);
            let (noise, surface, error) = if method == Method::VoxelColoring {
                measure_noise_and_colour(hull, used, &p)?
            } else {
                let (noise, surface, error, model) = carve_photo_measured(hull, used, &p)?;
                measured_model = Some(model);
                (noise, surface, error)
            };
            tracing::info!(threshold = noise.threshold(), image_sigma = noise.image_sigma, "photo threshold measured");
            (p.with_measured_noise(&noise), Some(noise), Some((surface, error)))
        }
    };
    let carve = || {
        if method == Method::VoxelColoring {
            color_voxels_sweeps(hull, used, &params)
        } else {
            carve_photo(hull, used, &params)
        }
    };
    // Without a measurement, the hull is coloured alongside the carving (they are independent).
    let (model, (hull_surface, hull_reprojection)) = match hull_coloured {
        Some(h) => match measured_model {
            Some(m) => (m, h),
            None => (carve()?, h),
        },
        None => {
            let colour_hull = || -> Result<(ColouredSurface, f64), PhotoError> {
                let surface = colour_surface(hull, used, &params)?;
                let error = reprojection_error(&grid, &surface, used);
                Ok((surface, error))
            };
            let (model, h) = rayon::join(carve, colour_hull);
            (model?, h?)
        }
    };
    tracing::info!(
        method = method.name(),
        views = used.len(),
        carved = model.stats.carved,
        iterations = model.stats.iterations,
        seconds = model.stats.seconds,
        "photo-consistency done"
    );
    let hull_overlap = truth.and_then(|t| hull.iou_and_containment(t.occupancy).ok());
    let visual_hull = VisualHull {
        voxels: hull.count(),
        volume_m3: hull.volume_m3(),
        iou: hull_overlap.map(|o| o.iou),
        containment: hull_overlap.map(|o| o.containment),
        colour_error: truth.and_then(|t| colour_error(&hull_surface, &grid, t)),
        reprojection_error: Some(hull_reprojection),
    };
    let report = PhotoReport {
        threshold: f64::from(params.threshold),
        measured_noise: noise,
        min_ncc: config.min_ncc,
        views: used.len(),
        iterations: model.stats.iterations,
        sweeps: model.stats.sweeps,
        ordinal_sweeps: if method == Method::VoxelColoring {
            ordinal_sweeps(&grid, used, params.min_views)
        } else {
            Vec::new()
        },
        visits: model.stats.visits,
        carved: model.stats.carved,
        seconds: model.stats.seconds,
        surface_voxels: model.surface.voxels.len(),
        seen_surface_voxels: model.surface.seen.iter().filter(|&&s| s).count(),
        reprojection_error: model.reprojection_error,
    };
    let colour_error = truth.and_then(|t| colour_error(&model.surface, &grid, t));
    Ok((model.occupancy, PhotoOutputs { grid, surface: model.surface, colour_error, visual_hull, report }))
}
