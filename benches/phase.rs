//! Phase-shift decoding throughput: the band-streaming decoder against a straightforward per-pixel
//! decoder (each pixel gathers its samples across the images, computes the N-step sums with `sin`
//! and `cos` of each step in `f64`, then reads its Gray bits), measured in the same run on the same
//! images. Prints one summary line with the ratio; criterion then measures both.
//!
//! `cargo bench --bench phase`. The images are the 4-step, 16-pixel-period sequence with Gray-code
//! unwrapping for columns and rows of a 1280x1024 projector, seen by a camera of the same size with
//! a deterministic ripple of a few grey levels (22 images).

use std::f64::consts::TAU;
use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{criterion_group, criterion_main, Criterion};
use scanrig::pipeline::structured_light::phase::{Axis, PhaseDecodeParams, PhaseShiftPatterns, Unwrapping};

const W: usize = 1280;
const H: usize = 1024;

/// Per-pixel reference for Gray-code unwrapping (columns then rows), same conventions as the decoder.
fn per_pixel(p: &PhaseShiftPatterns, imgs: &[&[u8]], min_mod: f64, out: &mut [f32]) {
    let n = p.steps();
    let period = p.periods()[0];
    let cb = p.gray_bits(Axis::Column) as usize;
    let rb = p.gray_bits(Axis::Row) as usize;
    for (axis, (base, bits, len)) in [(0, cb, W as f64), (n + cb, rb, H as f64)].into_iter().enumerate() {
        for i in 0..W * H {
            let (mut s, mut c, mut sum) = (0.0f64, 0.0f64, 0.0f64);
            for k in 0..n {
                let v = f64::from(imgs[base + k][i]);
                let d = TAU * k as f64 / n as f64;
                s += v * d.sin();
                c += v * d.cos();
                sum += v;
            }
            let mean = sum / n as f64;
            let mut code = 0u32;
            for b in 0..bits {
                code = (code << 1) | u32::from(f64::from(imgs[base + n + b][i]) > mean);
            }
            let mut cell = code;
            let mut shift = 1;
            while shift < 32 {
                cell ^= cell >> shift;
                shift <<= 1;
            }
            let wrapped = s.atan2(c).rem_euclid(TAU) / TAU * period;
            let centre = (f64::from(cell) + 0.5) * period / 2.0 - 0.5;
            let x = wrapped + period * ((centre - wrapped) / period).round();
            let ok = (2.0 / n as f64) * s.hypot(c) >= min_mod && (-0.5..=len - 0.5).contains(&x);
            out[axis * W * H + i] = if ok { (x + 0.5) as f32 } else { f32::NAN };
        }
    }
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
    let p = PhaseShiftPatterns::new(W as u32, H as u32, 4, 16.0, Unwrapping::GrayCode, true).expect("valid layout");
    let images: Vec<Vec<u8>> = (0..p.count())
        .map(|i| {
            let mut img = p.render(i, None).expect("in range");
            for (j, v) in img.iter_mut().enumerate() {
                // Contrast 30..230 plus a ripple of 0..4 grey levels.
                *v = (30 + u32::from(*v) * 200 / 255 + ((j * 7 + i * 3) % 5) as u32) as u8;
            }
            img
        })
        .collect();
    let imgs: Vec<&[u8]> = images.iter().map(Vec::as_slice).collect();
    let prm = PhaseDecodeParams::default();
    let mut reference = vec![0f32; 2 * W * H];
    let ours = median_time(|| _ = black_box(p.decode(&imgs, W, H, &prm)), 11);
    let naive = median_time(|| per_pixel(&p, &imgs, f64::from(prm.min_modulation), &mut reference), 3);
    let out = p.decode(&imgs, W, H, &prm).expect("decodes");
    let rows = out.row.as_ref().expect("rows");
    let worst = out
        .column
        .iter()
        .chain(rows.iter())
        .zip(&reference)
        .map(|(a, b)| if a.is_nan() && b.is_nan() { 0.0 } else { (a - b).abs() })
        .fold(0f32, f32::max);
    assert!(worst < 1e-2, "decoders disagree by {worst} px");
    let mpx = |d: Duration| (W * H) as f64 / d.as_secs_f64() / 1e6;
    println!(
        "phase shift {W}x{H}, 4-step + Gray, columns and rows ({} images): streaming {:.2} ms ({:.0} Mpx/s), per-pixel reference {:.2} ms ({:.1} Mpx/s), ratio {:.1}x, valid {:.2}%",
        p.count(),
        ours.as_secs_f64() * 1e3,
        mpx(ours),
        naive.as_secs_f64() * 1e3,
        mpx(naive),
        naive.as_secs_f64() / ours.as_secs_f64(),
        100.0 * out.valid_fraction()
    );
    let mut g = c.benchmark_group("phase");
    g.sample_size(10);
    g.bench_function("streaming", |b| b.iter(|| p.decode(&imgs, W, H, &prm)));
    g.bench_function("per_pixel_reference", |b| {
        b.iter(|| per_pixel(&p, &imgs, f64::from(prm.min_modulation), &mut reference))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
