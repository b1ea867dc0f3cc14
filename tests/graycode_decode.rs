//! Gray-code decoding: round trips through generated patterns, the real capture crop in the
//! fixtures, bad inputs, and (the full capture in `../shared/data/procam-graycode-chessboard`: a directory
//! with `capture_0/` and `graycode_pattern/`) the full real capture.

mod shared_data;

use std::path::{Path, PathBuf};

use scanrig::pipeline::structured_light::{
    decode, load_capture_dir, CaptureError, Coding, DecodeError, DecodeParams, GrayCodePatterns, ProjectorMap, INVALID,
};

/// Region of the full 1280x1024 camera images the fixture was cropped from (x, y, w, h).
const CROP: (usize, usize, usize, usize) = (512, 448, 128, 128);
/// Valid pixels of the full-image decoder (thresholds 40 / 5) inside `CROP`, computed once from the
/// full capture (the full-data test below re-checks it when the data set is present).
const CROP_VALID_FULL_DECODER: usize = 7565;

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/graycode/capture_crop")
}

/// "Captures" the patterns with a camera of `cw` x `ch` pixels that sees projector pixel
/// `look(x, y)`, with lit at `hi` and dark at `lo` grey levels plus a deterministic ripple.
fn synthetic_capture(
    p: &GrayCodePatterns,
    cw: usize,
    ch: usize,
    look: impl Fn(usize, usize) -> (usize, usize),
    hi: u8,
    lo: u8,
) -> Vec<Vec<u8>> {
    let pw = p.width() as usize;
    (0..p.count())
        .map(|i| {
            let pat = p.render(i).expect("index in range");
            let mut img = vec![0u8; cw * ch];
            for y in 0..ch {
                for x in 0..cw {
                    let (px, py) = look(x, y);
                    let ripple = ((x * 7 + y * 13 + i * 5) % 9) as u8; // 0..8 grey levels of "noise"
                    img[y * cw + x] = if pat[py * pw + px] == 255 { hi - ripple } else { lo + ripple };
                }
            }
            img
        })
        .collect()
}

#[test]
fn round_trip_1024x768_projector_identity_camera() {
    let p = GrayCodePatterns::new(1024, 768).expect("valid projector");
    assert_eq!(p.count(), 42);
    let imgs = synthetic_capture(&p, 1024, 768, |x, y| (x, y), 210, 25);
    let slices: Vec<&[u8]> = imgs.iter().map(Vec::as_slice).collect();
    let mut map = ProjectorMap::new();
    let valid = decode(&p, &slices, 1024, 768, &DecodeParams::default(), &mut map).expect("decodes");
    assert_eq!(valid, 1024 * 768);
    for y in 0..768 {
        for x in 0..1024 {
            assert_eq!(map.get(x, y), Some((x as u16, y as u16)), "camera pixel ({x}, {y})");
        }
    }
    assert_eq!(map.horizontal_consistency(1), (1023 * 768, 1023 * 768));
}

#[test]
fn round_trip_odd_projector_scaled_camera_both_codings() {
    for coding in [Coding::Gray, Coding::Binary] {
        let p = GrayCodePatterns::with_coding(800, 600, coding).expect("valid projector");
        // A 500x300 camera seeing every 1.6th projector column and every 2nd row, shifted.
        let look = |x: usize, y: usize| ((x * 8 / 5 + 3).min(799), (y * 2).min(599));
        let imgs = synthetic_capture(&p, 500, 300, look, 180, 40);
        let slices: Vec<&[u8]> = imgs.iter().map(Vec::as_slice).collect();
        let mut map = ProjectorMap::new();
        let valid = decode(&p, &slices, 500, 300, &DecodeParams::default(), &mut map).expect("decodes");
        assert_eq!(valid, 500 * 300, "{coding:?}");
        for y in 0..300 {
            for x in 0..500 {
                let (px, py) = look(x, y);
                assert_eq!(map.get(x, y), Some((px as u16, py as u16)), "{coding:?} camera ({x}, {y})");
            }
        }
    }
}

#[test]
fn thresholds_reject_unlit_and_ambiguous_pixels() {
    let p = GrayCodePatterns::new(64, 32).expect("valid projector");
    let mut imgs = synthetic_capture(&p, 64, 32, |x, y| (x, y), 200, 30);
    let (w, bi, wi) = (64usize, p.black_index(), p.white_index());
    // Pixel (5, 5): white barely above black -> unlit.
    imgs[wi][5 * w + 5] = 60;
    imgs[bi][5 * w + 5] = 30;
    // Pixel (6, 6): one pair nearly equal -> ambiguous bit.
    imgs[4][6 * w + 6] = 100;
    imgs[5][6 * w + 6] = 103;
    let slices: Vec<&[u8]> = imgs.iter().map(Vec::as_slice).collect();
    let mut map = ProjectorMap::new();
    let valid = decode(&p, &slices, 64, 32, &DecodeParams::default(), &mut map).expect("decodes");
    assert_eq!(valid, 64 * 32 - 2);
    assert_eq!(map.get(5, 5), None);
    assert_eq!(map.get(6, 6), None);
    assert_eq!(map.columns()[6 * w + 6], INVALID);
    assert_eq!(map.get(7, 6), Some((7, 6)));
    // Looser thresholds accept both.
    let loose = DecodeParams { black_threshold: 20, white_threshold: 2 };
    assert_eq!(decode(&p, &slices, 64, 32, &loose, &mut map).expect("decodes"), 64 * 32);
    assert_eq!(map.get(6, 6), Some((6, 6)));
}

#[test]
fn rows_beyond_the_projector_are_invalid() {
    // 768 rows need 10 bits; codes of 768..1023 cannot come from the projector.
    let p = GrayCodePatterns::new(4, 768).expect("valid projector");
    let big = GrayCodePatterns::new(4, 1024).expect("valid projector");
    let imgs = synthetic_capture(&big, 4, 1024, |x, y| (x, y), 220, 20);
    let slices: Vec<&[u8]> = imgs.iter().map(Vec::as_slice).collect();
    let mut map = ProjectorMap::new();
    let valid = decode(&p, &slices, 4, 1024, &DecodeParams::default(), &mut map).expect("decodes");
    assert_eq!(valid, 4 * 768);
    assert_eq!(map.get(0, 767), Some((0, 767)));
    assert_eq!(map.get(0, 768), None);
}

#[test]
fn fixture_crop_matches_the_full_image_decoder() {
    let p = GrayCodePatterns::new(1024, 768).expect("valid projector");
    let cap = load_capture_dir(&fixture(), p.count()).expect("fixture loads");
    assert_eq!((cap.width, cap.height), (CROP.2, CROP.3));
    let mut map = ProjectorMap::new();
    let valid = decode(&p, &cap.slices(), cap.width, cap.height, &DecodeParams::default(), &mut map).expect("decodes");
    // Decoding is per pixel, so the crop must give exactly what the full images give on that region.
    assert_eq!(valid, CROP_VALID_FULL_DECODER);
    assert_eq!(map.valid_count(), valid);
    let (pairs, within) = map.horizontal_consistency(2);
    assert!(pairs > 5000, "{pairs} adjacent valid pairs");
    assert!(within as f64 >= 0.999 * pairs as f64, "{within} of {pairs} adjacent valid pixels within 2 columns");
    // Decoded columns/rows fall where the chessboard sits in the projector image: the crop spans a
    // compact projector region, not scattered codes.
    let cols: Vec<u16> = map.columns().iter().copied().filter(|&c| c != INVALID).collect();
    let (lo, hi) = (cols.iter().min().copied().unwrap_or(0), cols.iter().max().copied().unwrap_or(0));
    assert!(hi - lo < 200, "decoded columns span {lo}..{hi}");
}

#[test]
fn wrong_image_count_names_the_directory() {
    let dir = tempfile::tempdir().expect("temp dir");
    for i in 0..41 {
        image::GrayImage::new(8, 4).save(dir.path().join(format!("img_{i:02}.png"))).expect("write png");
    }
    match load_capture_dir(dir.path(), 42) {
        Err(e @ CaptureError::Count { .. }) => {
            let CaptureError::Count { dir: d, expected, found } = &e else { unreachable!() };
            assert_eq!((d.as_path(), *expected, *found), (dir.path(), 42, 41));
            assert!(e.to_string().contains(&dir.path().display().to_string()), "{e}");
        }
        other => panic!("expected a count error, got {other:?}"),
    }
    let p = GrayCodePatterns::new(1024, 768).expect("valid projector");
    let img = vec![0u8; 32];
    let slices = vec![img.as_slice(); 41];
    let err = decode(&p, &slices, 8, 4, &DecodeParams::default(), &mut ProjectorMap::new());
    assert_eq!(err, Err(DecodeError::ImageCount { expected: 42, found: 41 }));
}

#[test]
fn size_mismatch_names_the_file() {
    let dir = tempfile::tempdir().expect("temp dir");
    for i in 0..42 {
        let (w, h) = if i == 17 { (8, 5) } else { (8, 4) };
        image::GrayImage::new(w, h).save(dir.path().join(format!("img_{i:02}.png"))).expect("write png");
    }
    let bad = dir.path().join("img_17.png");
    match load_capture_dir(dir.path(), 42) {
        Err(e @ CaptureError::Size { .. }) => {
            let CaptureError::Size { path, expected, found } = &e else { unreachable!() };
            assert_eq!((path, *expected, *found), (&bad, (8, 4), (8, 5)));
            assert!(e.to_string().contains("img_17.png"), "{e}");
        }
        other => panic!("expected a size error, got {other:?}"),
    }
    // A file that is not an image.
    std::fs::write(&bad, b"not a png").expect("write");
    match load_capture_dir(dir.path(), 42) {
        Err(e @ CaptureError::Read { .. }) => assert!(e.to_string().contains("img_17.png"), "{e}"),
        other => panic!("expected a read error, got {other:?}"),
    }
    // Buffers of the wrong size given directly.
    let p = GrayCodePatterns::new(1024, 768).expect("valid projector");
    let ok = vec![0u8; 32];
    let short = vec![0u8; 31];
    let mut slices = vec![ok.as_slice(); 42];
    slices[3] = &short;
    let err = decode(&p, &slices, 8, 4, &DecodeParams::default(), &mut ProjectorMap::new());
    assert_eq!(err, Err(DecodeError::ImageSize { index: 3, width: 8, height: 4, found: 31 }));
    let err = decode(&p, &vec![&[][..]; 42], 0, 4, &DecodeParams::default(), &mut ProjectorMap::new());
    assert_eq!(err, Err(DecodeError::Empty { width: 0, height: 4 }));
}

/// The full capture in `../shared/data/procam-graycode-chessboard` (fails under CI when missing).
fn full_data() -> Option<PathBuf> {
    shared_data::dataset("procam-graycode-chessboard")
}

#[test]
fn full_capture_meets_the_reference_facts() {
    let Some(root) = full_data() else { return };
    let p = GrayCodePatterns::new(1024, 768).expect("valid projector");
    let cap = load_capture_dir(&root.join("capture_0"), p.count()).expect("capture loads");
    assert_eq!((cap.width, cap.height), (1280, 1024));
    let mut map = ProjectorMap::new();
    let valid = decode(&p, &cap.slices(), cap.width, cap.height, &DecodeParams::default(), &mut map).expect("decodes");
    let frac = valid as f64 / (1280.0 * 1024.0);
    let (pairs, within) = map.horizontal_consistency(2);
    let consistent = within as f64 / pairs as f64;
    eprintln!("full capture: {:.3}% valid, {:.4}% adjacent within 2 columns", 100.0 * frac, 100.0 * consistent);
    assert!(frac >= 0.55, "valid fraction {frac}");
    assert!(consistent >= 0.999, "neighbour consistency {consistent}");
    // The fixture is a crop of this capture: its decode equals the full decode on that region.
    let crop = map.crop(CROP.0, CROP.1, CROP.2, CROP.3);
    assert_eq!(crop.valid_count(), CROP_VALID_FULL_DECODER);
    let fix = load_capture_dir(&fixture(), p.count()).expect("fixture loads");
    let mut fmap = ProjectorMap::new();
    decode(&p, &fix.slices(), fix.width, fix.height, &DecodeParams::default(), &mut fmap).expect("decodes");
    assert_eq!(fmap, crop);
}

#[test]
fn generated_patterns_equal_the_projected_ones_and_decode_to_identity() {
    let Some(root) = full_data() else { return };
    let p = GrayCodePatterns::new(1024, 768).expect("valid projector");
    let cap = load_capture_dir(&root.join("graycode_pattern"), p.count()).expect("patterns load");
    for (i, img) in cap.images.iter().enumerate() {
        assert!(*img == p.render(i).expect("index in range"), "pattern {i} differs from {:?}", cap.paths[i]);
    }
    let mut map = ProjectorMap::new();
    let valid = decode(&p, &cap.slices(), 1024, 768, &DecodeParams::default(), &mut map).expect("decodes");
    assert_eq!(valid, 1024 * 768);
    assert!((0..768).all(|y| (0..1024).all(|x| map.get(x, y) == Some((x as u16, y as u16)))));
}
