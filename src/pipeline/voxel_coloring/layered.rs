//! Voxel colouring on the surface only, behind [`super::color_voxels`].
//!
//! The layers and verdicts are those of [`super::color_voxels_every_voxel`]; what differs is which
//! voxels are looked at. The start is cut into 4³ bricks. A brick joins the sweep at the first layer
//! any of its voxels is in and leaves it after the last; when a layer reaches it, the brick's pixel
//! rectangle in every view (every footprint of its voxels lies in it, see
//! `VoxelCamera::box_pixels`, which also bounds distorting lenses) is checked against the claimed
//! pixels: when every pixel of every view's rectangle is claimed or outside the view's silhouette,
//! none of its voxels can sample a pixel in this or any later layer (claims only grow, and pixels
//! outside a silhouette are never sampled), so each would be left unseen and kept; the brick is
//! dropped without projecting a voxel. Interior bricks go that way as soon as the surface in front
//! of them is kept. Without a bound (a corner behind a camera) a brick is never dropped. A kept
//! voxel claims its footprints only in the views still open in its brick (in a closed one the
//! claim would only mark pixels already claimed or outside the silhouette), reusing the footprints
//! its verdict computed, and each view's claims are made on their own thread. The result is the
//! same, voxel for voxel.

use std::time::Instant;

use rayon::prelude::*;

use super::{claim_rect, colouring_verdict_in, ordinal_direction, restore_and_colour, Dense, PhotoModel, PhotoStats};
use crate::geometry::round::floor_f32;
use crate::pipeline::occupancy::Occupancy;
use crate::pipeline::photo_consistency::{check_inputs, PhotoError, PhotoParams, PhotoView, ViewPixels, VoxelCamera};

/// Brick edge, voxels.
const B: u32 = 4;

/// A brick of the start holding occupied voxels.
struct Brick {
    /// Lowest voxel index along each axis.
    lo: [u32; 3],
    /// One past the highest.
    hi: [u32; 3],
    /// First and last layer of its occupied voxels.
    first: i32,
    last: i32,
    /// Per view, the pixel rectangle holding its footprints; `None` without a bound.
    rects: Vec<Option<[usize; 4]>>,
    /// The views (increasing) that may still see one of its voxels: every view at first, then
    /// the ones whose rectangle is not yet all claimed or outside the silhouette (or that have no
    /// rectangle); with each, the number (row-major within the rectangle) of the first pixel
    /// found unsettled there, where the next check resumes.
    open: Vec<(u32, usize)>,
}

/// A kept voxel's footprint in one view: the pixel rectangle `[x0, x1) x [y0, y1)` it claims.
#[derive(Clone, Copy)]
struct Claim {
    view: u32,
    rect: [usize; 4],
}

/// See [`super::color_voxels`].
pub(super) fn color(
    start: &Occupancy,
    views: &[PhotoView<'_>],
    params: &PhotoParams,
) -> Result<PhotoModel, PhotoError> {
    check_inputs(start.grid(), views, params)?;
    let t = Instant::now();
    let grid = *start.grid();
    let d = ordinal_direction(&grid, views)?;
    let pixels = ViewPixels::all(views);
    let (mut dense, mut stats) = color_along(start, views, &pixels, params, d);
    let cams: Vec<VoxelCamera> = views.iter().map(|v| VoxelCamera::new(&v.camera, &grid)).collect();
    let (restored, surface, reprojection_error) = restore_and_colour(start, &mut dense, &cams, &pixels, views, params);
    stats.carved -= restored;
    let occupancy = dense.to_occupancy(grid);
    stats.seconds = t.elapsed().as_secs_f64();
    Ok(PhotoModel { occupancy, surface, stats, reprojection_error })
}

/// Voxel colouring from `start` in layers of increasing `d·x` (`d` a unit vector, grid frame, for
/// which `views` satisfy the ordinal visibility constraint; inputs already checked), with `pixels`
/// the views' [`ViewPixels`] (same order): the carved occupancy (silhouettes not yet restored, see
/// `restore_silhouettes`) and the counters (`seconds` left at 0).
pub(super) fn color_along(
    start: &Occupancy,
    views: &[PhotoView<'_>],
    pixels: &[ViewPixels<'_>],
    params: &PhotoParams,
    d: [f64; 3],
) -> (Dense, PhotoStats) {
    let grid = *start.grid();
    let d = d.map(|x| x as f32);
    let cams: Vec<VoxelCamera> = views.iter().map(|v| VoxelCamera::new(&v.camera, &grid)).collect();
    let mut dense = Dense::from(start);
    let key = |v: [u32; 3]| floor_f32(d[0] * v[0] as f32 + d[1] * v[1] as f32 + d[2] * v[2] as f32) as i32;

    let dims = grid.dims;
    let nb = dims.map(|n| (n as u32).div_ceil(B));
    let mut bricks: Vec<Brick> = (0..nb[0] * nb[1] * nb[2])
        .into_par_iter()
        .filter_map(|b| {
            let c = [b % nb[0], b / nb[0] % nb[1], b / (nb[0] * nb[1])];
            let lo = c.map(|x| x * B);
            let hi = [0, 1, 2].map(|a| (lo[a] + B).min(dims[a] as u32));
            let (mut first, mut last) = (i32::MAX, i32::MIN);
            for k in lo[2]..hi[2] {
                for j in lo[1]..hi[1] {
                    for i in lo[0]..hi[0] {
                        if dense.get(i as i64, j as i64, k as i64) {
                            let l = key([i, j, k]);
                            first = first.min(l);
                            last = last.max(l);
                        }
                    }
                }
            }
            (first <= last).then(|| {
                let rects: Vec<Option<[usize; 4]>> = cams.iter().map(|c| c.box_pixels(lo, hi)).collect();
                Brick { lo, hi, first, last, rects, open: (0..cams.len() as u32).map(|n| (n, 0)).collect() }
            })
        })
        .collect();
    bricks.sort_by_key(|b| b.first);

    let mut claimed: Vec<Vec<bool>> = cams.iter().map(|c| vec![false; c.width * c.height]).collect();
    let mut stats = PhotoStats::default();
    let mut next = 0; // next brick to join
    let mut active: Vec<usize> = Vec::new();
    let mut layer_voxels: Vec<([u32; 3], usize)> = Vec::new();
    let (Some(l0), Some(l1)) = (bricks.first().map(|b| b.first), bricks.iter().map(|b| b.last).max()) else {
        return (dense, stats);
    };
    for layer in l0..=l1 {
        while next < bricks.len() && bricks[next].first == layer {
            active.push(next);
            next += 1;
        }
        active.retain(|&b| bricks[b].last >= layer);
        // Close the views in which a brick's rectangle is all claimed or outside the silhouette,
        // and drop the bricks no view is open in. The bricks' lists of open views are taken out,
        // narrowed side by side in place (each reads the claims only) and put back.
        let mut open: Vec<Vec<(u32, usize)>> = active.iter().map(|&b| std::mem::take(&mut bricks[b].open)).collect();
        open.par_iter_mut().zip(&active).for_each(|(open, &b)| {
            let rects = &bricks[b].rects;
            open.retain_mut(|(n, from)| match rects[*n as usize] {
                None => true,
                Some(r) => {
                    pixels[*n as usize].first_unsettled(&claimed[*n as usize], r, *from).map(|k| *from = k).is_some()
                }
            });
        });
        for (&b, open) in active.iter().zip(open) {
            bricks[b].open = open;
        }
        active.retain(|&b| !bricks[b].open.is_empty());
        layer_voxels.clear();
        for &b in &active {
            let (lo, hi) = (bricks[b].lo, bricks[b].hi);
            for k in lo[2]..hi[2] {
                for j in lo[1]..hi[1] {
                    for i in lo[0]..hi[0] {
                        let v = [i, j, k];
                        if key(v) == layer && dense.get(i as i64, j as i64, k as i64) {
                            layer_voxels.push((v, b));
                        }
                    }
                }
            }
        }
        if layer_voxels.is_empty() {
            continue;
        }
        stats.iterations += 1;
        // Each kept voxel's verdict comes with its footprints in the views it consulted, which are
        // the claims it makes; they are gathered in a scratch list per worker and copied out only
        // for a kept voxel.
        let verdicts: Vec<(Option<bool>, Vec<Claim>)> = layer_voxels
            .par_iter()
            .map_init(Vec::new, |scratch, &(v, b)| {
                scratch.clear();
                let open = bricks[b].open.iter().map(|&(n, _)| n as usize);
                let verdict = colouring_verdict_in(&dense, &cams, pixels, &claimed, v, params, open, |n, fp| {
                    scratch.push(Claim { view: n as u32, rect: [fp.x0, fp.x1, fp.y0, fp.y1] })
                });
                (verdict, if verdict == Some(true) { scratch.clone() } else { Vec::new() })
            })
            .collect();
        stats.visits += layer_voxels.len() as u64;
        let mut kept: Vec<&[Claim]> = Vec::new();
        for (&(v, _), (verdict, claims)) in layer_voxels.iter().zip(&verdicts) {
            match verdict {
                Some(false) => {
                    dense.clear(v);
                    stats.carved += 1;
                }
                Some(true) => kept.push(claims),
                None => {}
            }
        }
        // The layer's kept voxels claim their footprints, each view's claims on their own thread
        // (a layer's voxels judge against the claims of earlier layers only). A voxel claims in
        // the views open in its brick: in a closed one every pixel of the brick's rectangle, which
        // holds the voxel's footprint, is claimed already or outside the silhouette, where a claim
        // changes nothing (no sample, no contour band and no settling check reads a claim there).
        claimed.par_iter_mut().zip(&cams).enumerate().for_each(|(n, (marks, cam))| {
            for claims in &kept {
                if let Ok(i) = claims.binary_search_by_key(&(n as u32), |c| c.view) {
                    claim_rect(cam.width, marks, claims[i].rect);
                }
            }
        });
    }
    (dense, stats)
}
