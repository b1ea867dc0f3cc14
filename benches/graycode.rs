//! Gray-code decoding throughput: the band-streaming decoder against a per-pixel reference decoder (each
//! pixel gathers its 42 samples across the images, as a straightforward per-pixel decoder does),
//! measured in the same run. Prints one summary line with the ratio; criterion then measures both.
//!
//! `cargo bench --bench graycode`. Uses the full chessboard capture when `SCANRIG_GRAYCODE_DATA`
//! points at it (a directory with `capture_0/`), else the 128x128 crop in the test fixtures. The
//! OpenCV comparison is `benches/opencv_graycode_peer.py`.

use std::hint::black_box;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use criterion::{criterion_group, criterion_main, Criterion};
use scanrig::pipeline::structured_light::{
    decode, load_capture_dir, Capture, DecodeParams, GrayCodePatterns, ProjectorMap,
};

fn capture(p: &GrayCodePatterns) -> Capture {
    let dir = match std::env::var_os("SCANRIG_GRAYCODE_DATA") {
        Some(d) => PathBuf::from(d).join("capture_0"),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/graycode/capture_crop"),
    };
    load_capture_dir(&dir, p.count()).expect("capture loads")
}

/// Per-pixel reference: for each pixel, read its 42 samples, threshold, Gray-decode.
fn per_pixel(p: &GrayCodePatterns, imgs: &[&[u8]], prm: &DecodeParams, col: &mut [u16], row: &mut [u16]) -> usize {
    let (cb, rb) = (p.column_bits() as usize, p.row_bits() as usize);
    let (wi, bi) = (p.white_index(), p.black_index());
    let mut valid = 0;
    for i in 0..col.len() {
        let mut ok = imgs[wi][i].abs_diff(imgs[bi][i]) > prm.black_threshold;
        let mut code = [0u32; 2];
        for k in 0..cb + rb {
            let (a, b) = (imgs[2 * k][i], imgs[2 * k + 1][i]);
            ok &= a.abs_diff(b) >= prm.white_threshold;
            let axis = usize::from(k >= cb);
            code[axis] = (code[axis] << 1) | u32::from(a > b);
        }
        let (c, r) = (p.coding().decode(code[0]), p.coding().decode(code[1]));
        ok &= c < p.width() && r < p.height();
        col[i] = if ok { c as u16 } else { u16::MAX };
        row[i] = if ok { r as u16 } else { u16::MAX };
        valid += usize::from(ok);
    }
    valid
}

fn median_time(mut f: impl FnMut(), runs: usize) -> Duration {
    let mut t: Vec<Duration> = (0..runs)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed()
        })
        .collect();
    t.sort();
    t[runs / 2]
}

fn bench(c: &mut Criterion) {
    let p = GrayCodePatterns::new(1024, 768).expect("valid projector");
    let cap = capture(&p);
    let imgs = cap.slices();
    let prm = DecodeParams::default();
    let n = cap.width * cap.height;
    let mut map = ProjectorMap::new();
    let (mut col, mut row) = (vec![0u16; n], vec![0u16; n]);
    let ours = median_time(|| _ = black_box(decode(&p, &imgs, cap.width, cap.height, &prm, &mut map)), 21);
    let reference = median_time(|| _ = black_box(per_pixel(&p, &imgs, &prm, &mut col, &mut row)), 5);
    assert_eq!(map.columns(), col.as_slice(), "the two decoders disagree");
    let mpx = |d: Duration| n as f64 / d.as_secs_f64() / 1e6;
    println!(
        "graycode {}x{}: band decoder {:.2} ms ({:.0} Mpx/s), per-pixel reference {:.2} ms ({:.0} Mpx/s), ratio {:.1}x, valid {:.2}%",
        cap.width,
        cap.height,
        ours.as_secs_f64() * 1e3,
        mpx(ours),
        reference.as_secs_f64() * 1e3,
        mpx(reference),
        reference.as_secs_f64() / ours.as_secs_f64(),
        100.0 * map.valid_fraction()
    );
    let mut g = c.benchmark_group("graycode");
    g.sample_size(20);
    g.bench_function("row_wise", |b| b.iter(|| decode(&p, &imgs, cap.width, cap.height, &prm, &mut map)));
    g.bench_function("per_pixel_reference", |b| b.iter(|| per_pixel(&p, &imgs, &prm, &mut col, &mut row)));
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
