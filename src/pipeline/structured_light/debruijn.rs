//! One-shot colour stripes coded by a De Bruijn sequence (after Zhang, Curless & Seitz, 3DPVT
//! 2002), with a simpler decoder than their multi-pass dynamic programming.
//!
//! **Pattern.** `k` colours are taken in order from the six fully saturated hues (red, yellow,
//! green, cyan, blue, magenta: each channel fully on or off). The stripe colours follow the
//! transitions of a De Bruijn sequence `B(k - 1, n)` over the steps `1..k` around that list:
//! stripe `i + 1` has colour `(c_i + d_i) mod k` with `d_i` the sequence's symbol + 1, so
//! neighbouring stripes always differ and every run of `n` consecutive transitions (`n + 1`
//! stripes) occurs at most once: it names its position. Stripes are `stripe` projector pixels wide;
//! stripe `i` covers columns `i·stripe .. (i+1)·stripe` and the boundary after it is at
//! `(i+1)·stripe` (continuous projector coordinates as in [`ProjectorCoords`]: column `x` covers
//! `[x, x + 1)`).
//!
//! **Decoding** (per camera row, rows in parallel):
//! 1. each pixel's colour is classified by which channels exceed half its brightest channel
//!    (robust to the surface colour and shading as long as no channel of the albedo is below half
//!    the largest); pixels too dark (brightest channel under `min_level`) or whose channels do not
//!    form one of the `k` colours are unknown;
//! 2. the row is cut into runs of one colour; runs shorter than `min_run` pixels are unknown;
//!    neighbouring runs separated by at most `max_gap` unknown pixels are chained;
//! 3. in each chain, every window of `n` consecutive transitions is looked up in the sequence
//!    table; a run is labelled with a stripe index only when every window covering it agrees
//!    (one mislabelled run breaks at most its own windows instead of shifting the chain);
//! 4. at each edge between runs labelled `i` and `i + 1`, the boundary column is known, placed at
//!    the middle of the edge in the camera; pixels between two consecutive labelled edges get the
//!    column interpolated linearly between them (the surface is taken as smooth within a stripe).
//!
//! Output is per pixel, `NaN` outside chains of decoded edges.

use rayon::prelude::*;

use super::coords::ProjectorCoords;

/// The six saturated hues in the order colours are taken, RGB with channels fully on or off.
pub const HUES: [[u8; 3]; 6] = [[255, 0, 0], [255, 255, 0], [0, 255, 0], [0, 255, 255], [0, 0, 255], [255, 0, 255]];

/// Errors of the De Bruijn stripe layout and decoder.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DeBruijnError {
    /// Colours outside 3..=6, a window below 1, or a stripe width of 0.
    #[error(
        "{colours} colours, window {window}, stripe {stripe} pixels: need 3..=6 colours, window >= 1, stripe >= 1"
    )]
    Layout {
        /// Colours asked for.
        colours: usize,
        /// Window length (transitions).
        window: usize,
        /// Stripe width, projector pixels.
        stripe: u32,
    },
    /// The projector is wider than the unique part of the sequence.
    #[error("a {width}-pixel projector needs {needed} stripes; B({symbols}, {window}) gives {available}")]
    TooWide {
        /// Projector width, pixels.
        width: u32,
        /// Stripes needed.
        needed: usize,
        /// Stripes the sequence can name.
        available: usize,
        /// Transition symbols (`colours - 1`).
        symbols: usize,
        /// Window length.
        window: usize,
    },
    /// A projector side of 0 or more than 32768 pixels.
    #[error("projector resolution {width}x{height} pixels: each side must be 1..=32768")]
    Resolution {
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
    },
    /// An output buffer of the wrong length.
    #[error("pattern buffer holds {found} bytes, the projector needs {expected} (RGB)")]
    Buffer {
        /// `3 * width * height`.
        expected: usize,
        /// The buffer's length.
        found: usize,
    },
    /// A captured RGB image of the wrong size (or an empty camera).
    #[error("image holds {found} bytes, a {width}x{height} RGB camera image has {}", 3 * width * height)]
    ImageSize {
        /// Camera width, pixels.
        width: usize,
        /// Camera height, pixels.
        height: usize,
        /// The buffer's length.
        found: usize,
    },
}

/// The De Bruijn sequence `B(k, n)` (cyclic, length `k^n`) by the Lyndon-word (FKM) algorithm.
pub fn de_bruijn(k: usize, n: usize) -> Vec<u8> {
    fn db(t: usize, p: usize, k: usize, n: usize, a: &mut [u8], out: &mut Vec<u8>) {
        if t > n {
            if n % p == 0 {
                out.extend_from_slice(&a[1..=p]);
            }
        } else {
            a[t] = a[t - p];
            db(t + 1, p, k, n, a, out);
            for j in usize::from(a[t - p]) + 1..k {
                a[t] = j as u8;
                db(t + 1, t, k, n, a, out);
            }
        }
    }
    let mut out = Vec::with_capacity(k.pow(n as u32));
    if k == 0 || n == 0 {
        return out;
    }
    let mut a = vec![0u8; n + 1];
    db(1, 1, k, n, &mut a, &mut out);
    out
}

/// Decoder settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DeBruijnDecodeParams {
    /// A pixel whose brightest channel is below this (8-bit) is unknown.
    pub min_level: u8,
    /// Runs shorter than this many camera pixels are unknown.
    pub min_run: usize,
    /// Runs separated by at most this many unknown pixels are still neighbours (blurred edges).
    pub max_gap: usize,
}

impl Default for DeBruijnDecodeParams {
    /// 30 grey levels, runs of 2 pixels, gaps of 2 pixels.
    fn default() -> Self {
        Self { min_level: 30, min_run: 2, max_gap: 2 }
    }
}

/// A one-shot colour stripe pattern.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DeBruijnStripes {
    width: u32,
    height: u32,
    stripe: u32,
    window: usize,
    /// Colour index (into [`HUES`]) of each stripe.
    colours: Vec<u8>,
    /// Number of colours `k`.
    k: usize,
}

impl DeBruijnStripes {
    /// Stripes `stripe` pixels wide in `colours` colours with transition windows of `window`, for a
    /// `width` x `height` projector.
    pub fn new(width: u32, height: u32, colours: usize, window: usize, stripe: u32) -> Result<Self, DeBruijnError> {
        if !(1..=32768).contains(&width) || !(1..=32768).contains(&height) {
            return Err(DeBruijnError::Resolution { width, height });
        }
        if !(3..=6).contains(&colours) || window == 0 || stripe == 0 || window > 8 {
            return Err(DeBruijnError::Layout { colours, window, stripe });
        }
        let seq = de_bruijn(colours - 1, window);
        let needed = width.div_ceil(stripe) as usize;
        // Linear use of the cyclic sequence: L + window - 1 transitions give L unique windows.
        let available = seq.len() + window;
        if needed > available {
            return Err(DeBruijnError::TooWide { width, needed, available, symbols: colours - 1, window });
        }
        let mut c = vec![0u8; needed];
        for i in 1..needed {
            let d = seq[(i - 1) % seq.len()] as usize + 1;
            c[i] = ((c[i - 1] as usize + d) % colours) as u8;
        }
        Ok(Self { width, height, stripe, window, colours: c, k: colours })
    }

    /// Projector width, pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Projector height, pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Stripe width, projector pixels.
    pub fn stripe_width(&self) -> u32 {
        self.stripe
    }

    /// Colour index (into [`HUES`]) of each stripe, left to right.
    pub fn stripe_colours(&self) -> &[u8] {
        &self.colours
    }

    /// Renders the pattern into `out` (`3 * width * height` RGB bytes, row-major).
    pub fn render_into(&self, out: &mut [u8]) -> Result<(), DeBruijnError> {
        let (w, h) = (self.width as usize, self.height as usize);
        if out.len() != 3 * w * h {
            return Err(DeBruijnError::Buffer { expected: 3 * w * h, found: out.len() });
        }
        let (first, rest) = out.split_at_mut(3 * w);
        for (x, px) in first.chunks_exact_mut(3).enumerate() {
            px.copy_from_slice(&HUES[self.colours[x / self.stripe as usize] as usize]);
        }
        for row in rest.chunks_exact_mut(3 * w) {
            row.copy_from_slice(first);
        }
        Ok(())
    }

    /// The pattern as a new RGB buffer.
    pub fn render(&self) -> Vec<u8> {
        let mut out = vec![0u8; 3 * self.width as usize * self.height as usize];
        // The buffer is sized here, so rendering cannot fail.
        let _ = self.render_into(&mut out);
        out
    }

    /// Decodes one captured RGB image (`3 * width * height` bytes, row-major) into projector
    /// columns (rows are not coded).
    pub fn decode(
        &self,
        rgb: &[u8],
        width: usize,
        height: usize,
        params: &DeBruijnDecodeParams,
    ) -> Result<ProjectorCoords, DeBruijnError> {
        if rgb.len() != 3 * width * height || width == 0 || height == 0 {
            return Err(DeBruijnError::ImageSize { width, height, found: rgb.len() });
        }
        // Window of transitions (as a number in base k-1) -> index of its first stripe.
        let sym = self.k - 1;
        let mut table = std::collections::HashMap::new();
        let trans: Vec<usize> =
            self.colours.windows(2).map(|w| (w[1] as usize + self.k - w[0] as usize) % self.k - 1).collect();
        for (i, win) in trans.windows(self.window).enumerate() {
            table.insert(win.iter().fold(0usize, |a, &d| a * sym + d), i);
        }
        // Channel pattern (bit 0 red, 1 green, 2 blue) -> colour index, 255 when not used.
        let mut class = [255u8; 8];
        for (i, h) in HUES.iter().enumerate().take(self.k) {
            class[usize::from(h[0] > 0) | usize::from(h[1] > 0) << 1 | usize::from(h[2] > 0) << 2] = i as u8;
        }
        let mut column = vec![f32::NAN; width * height];
        let sw = self.stripe as f32;
        column.par_chunks_mut(width).enumerate().for_each(|(y, out)| {
            let row = &rgb[3 * y * width..3 * (y + 1) * width];
            let labels: Vec<u8> = row
                .chunks_exact(3)
                .map(|p| {
                    let m = p[0].max(p[1]).max(p[2]);
                    if m < params.min_level {
                        return 255;
                    }
                    let half = m / 2;
                    class[usize::from(p[0] > half) | usize::from(p[1] > half) << 1 | usize::from(p[2] > half) << 2]
                })
                .collect();
            // Runs: (start, end exclusive, colour).
            let mut runs: Vec<(usize, usize, u8)> = Vec::new();
            let mut x = 0;
            while x < width {
                let c = labels[x];
                let s = x;
                while x < width && labels[x] == c {
                    x += 1;
                }
                if c != 255 && x - s >= params.min_run {
                    runs.push((s, x, c));
                }
            }
            // Chains of neighbouring runs with different colours.
            let mut start = 0;
            for i in 1..=runs.len() {
                let broken =
                    i == runs.len() || runs[i].0 - runs[i - 1].1 > params.max_gap || runs[i].2 == runs[i - 1].2;
                if broken {
                    self.decode_chain(&runs[start..i], &table, out, sw);
                    start = i;
                }
            }
        });
        Ok(ProjectorCoords { width, height, column, row: None })
    }

    /// Labels the runs of one chain and writes the interpolated columns between decoded edges.
    fn decode_chain(
        &self,
        runs: &[(usize, usize, u8)],
        table: &std::collections::HashMap<usize, usize>,
        out: &mut [f32],
        sw: f32,
    ) {
        let n = self.window;
        if runs.len() < n + 1 {
            return;
        }
        let sym = self.k - 1;
        // Candidate stripe index per run; None = no window yet, Some(None) = windows disagree.
        let mut label: Vec<Option<Option<usize>>> = vec![None; runs.len()];
        for s in 0..runs.len() - n {
            let code = (s..s + n)
                .fold(0usize, |a, j| a * sym + (runs[j + 1].2 as usize + self.k - runs[j].2 as usize) % self.k - 1);
            let first = table.get(&code).copied();
            for (j, l) in label.iter_mut().enumerate().skip(s).take(n + 1) {
                let cand = first.map(|f| f + j - s);
                *l = match (*l, cand) {
                    (None, c) => Some(c),
                    (Some(a), c) if a == c => Some(a),
                    _ => Some(None),
                };
            }
        }
        // Edges between consecutive labelled runs: (camera position, projector boundary column).
        let mut edges: Vec<(f32, f32)> = Vec::new();
        for j in 0..runs.len() - 1 {
            if let (Some(Some(a)), Some(Some(b))) = (label[j], label[j + 1]) {
                if b == a + 1 {
                    // The edge lies between the end of run j and the start of run j + 1.
                    let cam = (runs[j].1 as f32 + runs[j + 1].0 as f32) / 2.0 - 0.5;
                    edges.push((cam, b as f32 * sw));
                } else {
                    edges.push((f32::NAN, f32::NAN));
                }
            } else {
                edges.push((f32::NAN, f32::NAN));
            }
        }
        for e in edges.windows(2) {
            let ((u0, c0), (u1, c1)) = (e[0], e[1]);
            if u0.is_nan() || u1.is_nan() || u1 <= u0 || (c1 - c0 - sw).abs() > 0.01 {
                continue;
            }
            let slope = (c1 - c0) / (u1 - u0);
            for x in u0.ceil() as usize..=(u1.floor() as usize).min(out.len() - 1) {
                out[x] = c0 + (x as f32 - u0) * slope;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn de_bruijn_windows_are_unique_and_complete() {
        for (k, n) in [(2, 3), (3, 3), (4, 2), (5, 3)] {
            let s = de_bruijn(k, n);
            assert_eq!(s.len(), k.pow(n as u32));
            let mut seen = std::collections::HashSet::new();
            for i in 0..s.len() {
                let w: Vec<u8> = (0..n).map(|j| s[(i + j) % s.len()]).collect();
                assert!(w.iter().all(|&c| (c as usize) < k));
                assert!(seen.insert(w), "B({k},{n}) repeats a window at {i}");
            }
        }
    }

    #[test]
    fn neighbouring_stripes_differ_and_too_wide_is_refused() {
        let p = DeBruijnStripes::new(800, 2, 6, 3, 8).expect("valid");
        assert_eq!(p.stripe_colours().len(), 100);
        assert!(p.stripe_colours().windows(2).all(|w| w[0] != w[1]));
        assert!(matches!(DeBruijnStripes::new(800, 2, 3, 2, 4), Err(DeBruijnError::TooWide { .. })));
        assert!(matches!(DeBruijnStripes::new(800, 2, 7, 2, 4), Err(DeBruijnError::Layout { .. })));
    }

    #[test]
    fn decodes_a_shaded_tinted_stretched_capture() {
        let p = DeBruijnStripes::new(400, 1, 6, 3, 5).expect("valid");
        let pat = p.render();
        // Camera column x sees projector column 0.6 x + 10; reflectance (0.9, 0.7, 0.6); shading
        // falling from 1 to 0.5 across the row; ambient 12 levels.
        let cw = 600;
        let look = |x: usize| 0.6 * x as f64 + 10.0;
        let mut img = vec![0u8; 3 * cw];
        for x in 0..cw {
            let t = look(x).round() as usize;
            let shade = 1.0 - 0.5 * x as f64 / cw as f64;
            for (ch, a) in [0.9, 0.7, 0.6].iter().enumerate() {
                img[3 * x + ch] = (12.0 + a * shade * f64::from(pat[3 * t.min(399) + ch])).round() as u8;
            }
        }
        let out = p.decode(&img, cw, 1, &DeBruijnDecodeParams::default()).expect("decodes");
        let valid: Vec<usize> = (0..cw).filter(|&x| !out.column[x].is_nan()).collect();
        assert!(valid.len() > cw * 8 / 10, "{} of {cw} decoded", valid.len());
        for &x in &valid {
            let t = look(x) + 0.5; // continuous coordinate of the projector index seen
            assert!((out.column[x] as f64 - t).abs() < 1.0, "camera {x}: {} vs {t}", out.column[x]);
        }
    }
}
