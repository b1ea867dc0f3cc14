//! Phase shift, De Bruijn colour stripes and a sweeping stripe on simulated captures: each pattern
//! is shown by the simulated projector (with its gamma and black level) and rendered by the
//! simulator's ray caster for a plane and a sphere; the decoded projector coordinates are compared
//! with the truth, the projection of each camera pixel's surface point into the projector.
//!
//! Coordinates are continuous projector pixels (pixel `x` covers `[x, x + 1)`). The renderer samples
//! the pattern at the projector pixel a point falls in (no blur), so the coordinate a camera pixel
//! can show is the centre of that pixel, `floor(u) + 0.5` for the projection `u` — the "lit pixel"
//! truth. Errors against the projection `u` itself are printed too; they add the ±0.5 px
//! quantisation of the simulated projector.

use std::time::Duration;

use nalgebra::Vector3;
use scanrig::devices::projector::sim::{ProjectorResponse, SimProjector};
use scanrig::devices::{Pattern, Projector};
use scanrig::geometry::{CameraModel, Intrinsics, Pose};
use scanrig::pipeline::structured_light::debruijn::{DeBruijnDecodeParams, DeBruijnStripes};
use scanrig::pipeline::structured_light::gamma::{calibration_levels, ResponseCurve};
use scanrig::pipeline::structured_light::phase::{PhaseDecodeParams, PhaseShiftPatterns, Unwrapping};
use scanrig::pipeline::structured_light::stripe::SweepingStripe;
use scanrig::pipeline::structured_light::{PatternSet, ProjectorCoords};
use scanrig::sim::{FrameNoise, Lighting, Material, Primitive, ProjectorModel, RayTable, Scene, SimWorld, Solid};

const PW: u32 = 320;
const PH: u32 = 240;

struct Rig {
    world: SimWorld,
    rays: RayTable,
    projector: SimProjector,
    proj_model: CameraModel,
}

fn rig(scene: &str, response: ProjectorResponse) -> Rig {
    let v = Vector3::new;
    let solid = match scene {
        // A wall facing the camera and projector, 5 cm behind the turntable axis.
        "plane" => Solid::new(
            Primitive::Box { min: v(-0.2, 0.05, -0.1), max: v(0.2, 0.06, 0.2) },
            vec![],
            Material::Uniform([0.8, 0.8, 0.8]),
        ),
        _ => Solid::new(
            Primitive::Sphere { centre: v(0.0, 0.0, 0.035), radius: 0.035 },
            vec![],
            Material::Uniform([0.85, 0.75, 0.6]),
        ),
    }
    .expect("solid");
    let target = v(0.0, 0.0, 0.035);
    let proj_model = CameraModel {
        width: PW,
        height: PH,
        intrinsics: Intrinsics {
            fx: 600.0,
            fy: 600.0,
            cx: 160.0,
            cy: 120.0,
            skew: 0.0,
            k1: 0.0,
            k2: 0.0,
            ..Intrinsics::default()
        },
        pose: Pose::look_at(v(0.12, -0.4, 0.12), target, Vector3::z()),
    };
    let lighting = Lighting {
        lights: vec![],
        lasers: vec![],
        projector: Some(ProjectorModel { model: proj_model, intensity: 0.7 }),
        ambient: 0.05,
        background: [0, 0, 0],
    };
    let world = SimWorld::new(Scene::new(scene, vec![solid]).expect("scene"), lighting);
    let camera = CameraModel {
        width: 160,
        height: 120,
        intrinsics: Intrinsics {
            fx: 380.0,
            fy: 380.0,
            cx: 80.0,
            cy: 60.0,
            skew: 0.0,
            k1: 0.0,
            k2: 0.0,
            ..Intrinsics::default()
        },
        pose: Pose::look_at(v(-0.05, -0.42, 0.1), target, Vector3::z()),
    };
    let projector = SimProjector::with_response(world.clone(), PW, PH, response);
    Rig { world, rays: RayTable::new(camera), projector, proj_model }
}

impl Rig {
    /// Shows each RGB pattern on the projector and renders one noisy frame of it (RGB bytes).
    fn capture(&mut self, patterns: impl Iterator<Item = Vec<u8>>) -> Vec<Vec<u8>> {
        patterns
            .enumerate()
            .map(|(i, rgb)| {
                let p = Pattern { width: PW, height: PH, rgb: std::sync::Arc::new(rgb) };
                self.projector.show(&p, Duration::from_millis(10)).expect("show");
                let noise = FrameNoise { sigma: 1.0, seed: 7, sequence: i as u64 };
                self.world.renderer().render_rgb(&self.rays, &self.world.snapshot(), noise).into_raw()
            })
            .collect()
    }

    fn capture_set(&mut self, set: &PatternSet, lut: Option<&[u8; 256]>) -> ProjectorCoords {
        let frames = self.capture((0..set.count()).map(|i| set.render_rgb(i, lut).expect("pattern")));
        let f: Vec<&[u8]> = frames.iter().map(Vec::as_slice).collect();
        set.decode(&f, 160, 120).expect("decodes")
    }

    /// The continuous projector point `(u, v)` (pixel edges at integers) each camera pixel's surface
    /// point projects to, when the surface is hit and the projector sees it.
    fn truth(&self) -> Vec<Option<(f64, f64)>> {
        let cam = self.rays.model();
        let origin = cam.centre();
        let pc = self.proj_model.centre();
        let mut out = Vec::new();
        for y in 0..cam.height {
            for x in 0..cam.width {
                let d = self.rays.dir(x, y);
                let t = self.world.scene().intersect(&origin, &d, 0.0, 10.0).and_then(|hit| {
                    let to = pc - hit.point;
                    let dist = to.norm();
                    let lifted = hit.point + hit.normal * 1e-7;
                    let faces = hit.normal.dot(&to) > 0.0;
                    let free = !self.world.scene().occluded(&lifted, &(to / dist), 0.0, dist);
                    let q = self.proj_model.project(&hit.point)?;
                    (faces && free && q.x >= 0.0 && q.y >= 0.0 && q.x < f64::from(PW) && q.y < f64::from(PH))
                        .then_some((q.x, q.y))
                });
                out.push(t);
            }
        }
        out
    }
}

/// Errors of the decoded values against the lit-pixel truth `floor(u) + 0.5` and the continuous
/// truth `u`, over pixels that decoded and have a truth; plus the count of truth pixels.
struct Errors {
    lit: Vec<f64>,
    cont: Vec<f64>,
    seen: usize,
}

impl Errors {
    fn of(decoded: &[f32], truth: &[Option<(f64, f64)>], axis_row: bool) -> Errors {
        let (mut lit, mut cont, mut seen) = (Vec::new(), Vec::new(), 0);
        for (d, t) in decoded.iter().zip(truth) {
            let Some((u, v)) = t else { continue };
            let u = if axis_row { *v } else { *u };
            seen += 1;
            if !d.is_nan() {
                lit.push((f64::from(*d) - (u.floor() + 0.5)).abs());
                cont.push((f64::from(*d) - u).abs());
            }
        }
        Errors { lit, cont, seen }
    }

    fn median(v: &[f64]) -> f64 {
        let mut s = v.to_vec();
        s.sort_by(f64::total_cmp);
        s.get(s.len() / 2).copied().unwrap_or(f64::NAN)
    }

    fn within(&self, tol: f64) -> f64 {
        self.cont.iter().filter(|&&e| e <= tol).count() as f64 / self.cont.len().max(1) as f64
    }

    fn report(&self, what: &str) {
        println!(
            "{what}: {} of {} projector-lit pixels decoded ({:.1}%), median error {:.3} px (lit pixel) / {:.3} px (continuous), within 1 px {:.2}%",
            self.lit.len(),
            self.seen,
            100.0 * self.lit.len() as f64 / self.seen.max(1) as f64,
            Self::median(&self.lit),
            Self::median(&self.cont),
            100.0 * self.within(1.0)
        );
    }
}

fn phase_set(unwrapping: Unwrapping, steps: usize, rows: bool) -> PatternSet {
    let p = PhaseShiftPatterns::new(PW, PH, steps, 16.0, unwrapping, rows).expect("layout");
    PatternSet::PhaseShift(p, PhaseDecodeParams::default())
}

#[test]
fn phase_shift_with_gray_and_multi_frequency_unwrapping_on_plane_and_sphere() {
    for scene in ["plane", "sphere"] {
        let mut rig = rig(scene, ProjectorResponse::LINEAR);
        let truth = rig.truth();
        for (name, unwrapping) in [
            ("gray", Unwrapping::GrayCode),
            ("multi-frequency", Unwrapping::MultiFrequency { coarser_periods: vec![96.0, 400.0] }),
        ] {
            let out = rig.capture_set(&phase_set(unwrapping, 4, true), None);
            for (axis, values) in [("column", &out.column), ("row", out.row.as_ref().expect("rows"))] {
                let e = Errors::of(values, &truth, axis == "row");
                e.report(&format!("{scene} phase shift 4-step, {name} unwrapping, {axis}"));
                assert!(e.lit.len() as f64 >= 0.9 * e.seen as f64, "{scene} {name} {axis}: too few decoded");
                assert!(Errors::median(&e.lit) < 0.2, "{scene} {name} {axis}: median error");
                // Unwrapped right: within half a fringe period of the truth.
                let right = e.lit.iter().filter(|&&x| x < 8.0).count() as f64 / e.lit.len() as f64;
                assert!(right >= 0.99, "{scene} {name} {axis}: {:.2}% unwrapped right", 100.0 * right);
            }
        }
    }
}

#[test]
fn gamma_is_measured_and_its_phase_error_compensated() {
    let response = ProjectorResponse { gamma: 2.2, black_level: 0.04 };
    let mut rig = rig("plane", response);
    let truth = rig.truth();
    // Measure: uniform grey levels through the same projector and camera.
    let levels = calibration_levels();
    let frames = rig.capture(levels.iter().map(|&l| Pattern::uniform(PW, PH, [l, l, l]).rgb.to_vec()));
    let grey: Vec<Vec<u8>> = frames.iter().map(|f| f.chunks_exact(3).map(|p| p[1]).collect()).collect();
    let g: Vec<&[u8]> = grey.iter().map(Vec::as_slice).collect();
    let curve = ResponseCurve::fit(&levels, &g, 40.0).expect("fits");
    println!("fitted gamma {:.3}, black {:.1}, white {:.1} grey levels", curve.gamma, curve.black, curve.white);
    assert!((curve.gamma - 2.2).abs() < 0.15, "fitted gamma {}", curve.gamma);
    assert!(curve.black > 5.0, "the projector's black level shows: {}", curve.black);

    let lut = curve.compensation_lut();
    for steps in [3, 4] {
        let set = phase_set(Unwrapping::GrayCode, steps, false);
        let raw = Errors::of(&rig.capture_set(&set, None).column, &truth, false);
        let fixed = Errors::of(&rig.capture_set(&set, Some(&lut)).column, &truth, false);
        raw.report(&format!("gamma 2.2 uncompensated, {steps}-step"));
        fixed.report(&format!("gamma 2.2 compensated, {steps}-step"));
        let (r, f) = (Errors::median(&raw.lit), Errors::median(&fixed.lit));
        assert!(f < 0.2, "{steps}-step compensated median error {f}");
        assert!(r >= f, "{steps}-step: uncompensated {r} vs compensated {f}");
        // N steps cancel fringe harmonics up to N - 2: gamma's strong 2nd harmonic spoils 3 steps,
        // while 4 steps only see the weak 3rd and stay near the noise floor either way.
        if steps == 3 {
            assert!(r > 0.3 && r > 5.0 * f, "3-step: uncompensated {r} vs compensated {f}");
        }
    }
}

#[test]
fn de_bruijn_and_sweeping_stripe_on_plane_and_sphere() {
    for scene in ["plane", "sphere"] {
        let mut rig = rig(scene, ProjectorResponse::LINEAR);
        let truth = rig.truth();
        let db = DeBruijnStripes::new(PW, PH, 6, 3, 6).expect("layout");
        let out = rig.capture_set(&PatternSet::DeBruijn(db, DeBruijnDecodeParams::default()), None);
        let e = Errors::of(&out.column, &truth, false);
        e.report(&format!("{scene} De Bruijn 6 colours, window 3, 6 px stripes"));
        assert!(e.within(1.0) >= 0.95, "{scene} De Bruijn within 1 px: {}", e.within(1.0));
        assert!(e.lit.len() as f64 >= 0.5 * e.seen as f64, "{scene} De Bruijn decoded too few");

        let sweep = SweepingStripe::new(PW, PH, 2, 1).expect("layout");
        let out = rig.capture_set(&PatternSet::SweepingStripe(sweep, 20), None);
        let e = Errors::of(&out.column, &truth, false);
        e.report(&format!("{scene} sweeping stripe 2 px, step 1"));
        assert!(e.within(1.0) >= 0.95, "{scene} sweep within 1 px: {}", e.within(1.0));
        assert!(e.lit.len() as f64 >= 0.9 * e.seen as f64, "{scene} sweep decoded too few");
    }
}
