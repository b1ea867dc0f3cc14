//! The Gray-code decoder against a plain per-pixel reference (gather a pixel's samples, threshold,
//! Gray-decode) on the real capture crop in the fixtures, for several threshold pairs including
//! the edge cases `white_threshold = 0` and `black_threshold = 0`: the fast decoder must give
//! exactly the same columns, rows and valid count.

use std::path::Path;

use scanrig::pipeline::structured_light::{decode, load_capture_dir, DecodeParams, GrayCodePatterns, ProjectorMap};

fn reference(p: &GrayCodePatterns, imgs: &[&[u8]], prm: &DecodeParams) -> (Vec<u16>, Vec<u16>, usize) {
    let n = imgs[0].len();
    let (cb, rb) = (p.column_bits() as usize, p.row_bits() as usize);
    let (mut col, mut row, mut valid) = (vec![u16::MAX; n], vec![u16::MAX; n], 0);
    for i in 0..n {
        let mut ok = imgs[p.white_index()][i].abs_diff(imgs[p.black_index()][i]) > prm.black_threshold;
        let mut code = [0u32; 2];
        for k in 0..cb + rb {
            let (a, b) = (imgs[2 * k][i], imgs[2 * k + 1][i]);
            ok &= a.abs_diff(b) >= prm.white_threshold;
            let axis = usize::from(k >= cb);
            code[axis] = (code[axis] << 1) | u32::from(a > b);
        }
        let (c, r) = (p.coding().decode(code[0]), p.coding().decode(code[1]));
        ok &= c < p.width() && r < p.height();
        if ok {
            (col[i], row[i]) = (c as u16, r as u16);
            valid += 1;
        }
    }
    (col, row, valid)
}

#[test]
fn fast_decoder_equals_the_per_pixel_reference_for_every_threshold() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/graycode/capture_crop");
    // The crop as decoded for a 1024x768 projector, and again as if the projector were smaller
    // (codes beyond it become invalid).
    for (pw, ph) in [(1024, 768), (1000, 600)] {
        let p = GrayCodePatterns::new(pw, ph).expect("valid projector");
        let cap = load_capture_dir(&dir, p.count()).expect("fixture loads");
        let imgs = cap.slices();
        for (bt, wt) in [(40, 5), (0, 0), (10, 0), (0, 12), (200, 30), (255, 255)] {
            let prm = DecodeParams { black_threshold: bt, white_threshold: wt };
            let mut map = ProjectorMap::new();
            let valid = decode(&p, &imgs, cap.width, cap.height, &prm, &mut map).expect("decodes");
            let (col, row, rv) = reference(&p, &imgs, &prm);
            assert_eq!(valid, rv, "{pw}x{ph} thresholds {bt}/{wt}: valid count");
            assert!(map.columns() == col.as_slice(), "{pw}x{ph} thresholds {bt}/{wt}: columns differ");
            assert!(map.rows() == row.as_slice(), "{pw}x{ph} thresholds {bt}/{wt}: rows differ");
        }
    }
}
