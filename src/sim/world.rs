//! The shared state of the simulated world: the immutable scene and renderer, and the mutable rig
//! state (turntable angle, lights, lasers, projector pattern) that the simulated drivers change and
//! the simulated cameras see.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Instant;

use nalgebra::Vector3;

use super::render::{Lighting, LineLaser, PointLight, ProjectorModel, Renderer};
use super::scene::Scene;
use super::{SimConfigError, SimError};
use crate::config::{ProjectorConfig, RigConfig, SimConfig};
use crate::devices::Pattern;

/// The rig state at one instant, as a camera exposing then would see it.
#[derive(Debug, Clone)]
pub struct WorldState {
    /// Turntable angle, degrees (counter-clockwise seen from above; any real value).
    pub turntable_deg: f64,
    /// Level of each white light, 0..=1, by index.
    pub light_levels: Vec<f32>,
    /// Whether each line laser is on, by index.
    pub lasers_on: Vec<bool>,
    /// The projector's current pattern; `None` = blank (black).
    pub pattern: Option<Pattern>,
    /// A pattern handed to the projector that is not on screen yet, and the instant it appears
    /// (projector latency and refresh); it replaces `pattern` from then on.
    pub pending_pattern: Option<(Option<Pattern>, Instant)>,
    /// Number of changes made to the state so far.
    pub changes: u64,
    /// When the state last changed (monotonic).
    pub last_change: Instant,
}

#[derive(Debug)]
struct Inner {
    renderer: Renderer,
    state: Mutex<WorldState>,
}

/// The simulated world, shared by every simulated device of a rig (cheap to clone: clones share
/// the state). All state changes are atomic and counted.
#[derive(Debug, Clone)]
pub struct SimWorld {
    inner: Arc<Inner>,
}

impl SimWorld {
    /// A world with `scene` under `lighting`, everything off, the turntable at 0°.
    pub fn new(scene: Scene, lighting: Lighting) -> SimWorld {
        let state = WorldState {
            turntable_deg: 0.0,
            light_levels: vec![0.0; lighting.lights.len()],
            lasers_on: vec![false; lighting.lasers.len()],
            pattern: None,
            pending_pattern: None,
            changes: 0,
            last_change: Instant::now(),
        };
        SimWorld { inner: Arc::new(Inner { renderer: Renderer::new(scene, lighting), state: Mutex::new(state) }) }
    }

    /// Build the world from the rig file: the `[sim]` scene, the `[lights]` geometry and the
    /// `[projector]` calibration.
    pub fn from_config(sim: &SimConfig, rig: &RigConfig) -> Result<SimWorld, SimConfigError> {
        let scene = Scene::preset(&sim.scene, sim.scale).map_err(|source| SimConfigError {
            section: "sim",
            field: "scene",
            source,
        })?;
        let (lights, lasers) = match &rig.lights {
            None => (Vec::new(), Vec::new()),
            Some(l) => (
                l.lights
                    .iter()
                    .map(|l| PointLight { position_m: Vector3::from(l.position_m), intensity: l.intensity })
                    .collect(),
                l.lasers
                    .iter()
                    .map(|l| {
                        let n = Vector3::from(l.plane_normal);
                        let norm = n.norm();
                        if !(norm.is_finite() && norm > 0.0) {
                            return Err(SimConfigError {
                                section: "lights",
                                field: "plane_normal",
                                source: SimError::DegenerateLaserPlane,
                            });
                        }
                        Ok(LineLaser { origin_m: Vector3::from(l.origin_m), normal: n / norm, colour: l.colour })
                    })
                    .collect::<Result<Vec<_>, _>>()?,
            ),
        };
        let projector = rig.projector.as_ref().and_then(|p| match p {
            ProjectorConfig::Sim(p) => {
                Some(ProjectorModel { model: p.calibration.model(p.width, p.height), intensity: p.intensity })
            }
            // A real projector lights the real world, not the simulated one.
            ProjectorConfig::Fbdev(_) | ProjectorConfig::Window(_) => None,
        });
        if !(sim.ambient.is_finite() && (0.0..=1.0).contains(&sim.ambient)) {
            return Err(SimConfigError {
                section: "sim",
                field: "ambient",
                source: SimError::InvalidAmbient { ambient: sim.ambient },
            });
        }
        let lighting = Lighting { lights, lasers, projector, ambient: sim.ambient, background: sim.background };
        tracing::debug!(scene = %sim.scene, scale = sim.scale, "simulated world built");
        Ok(SimWorld::new(scene, lighting))
    }

    /// The scene: the ground truth, object frame.
    pub fn scene(&self) -> &Scene {
        self.inner.renderer.scene()
    }

    /// The renderer (scene and lighting).
    pub fn renderer(&self) -> &Renderer {
        &self.inner.renderer
    }

    /// A copy of the current state.
    pub fn snapshot(&self) -> WorldState {
        self.snapshot_timed().0
    }

    /// A copy of the state and the instant it holds for: a pending pattern due by then is on screen
    /// in it, one due later is not. A camera exposing at that instant sees exactly this state.
    pub fn snapshot_timed(&self) -> (WorldState, Instant) {
        let mut s = self.lock();
        let now = Instant::now();
        if s.pending_pattern.as_ref().is_some_and(|(_, at)| *at <= now) {
            if let Some((pattern, at)) = s.pending_pattern.take() {
                s.pattern = pattern;
                s.changes += 1;
                s.last_change = at;
            }
        }
        (s.clone(), now)
    }

    /// Number of state changes so far.
    pub fn change_count(&self) -> u64 {
        self.lock().changes
    }

    /// When the state last changed.
    pub fn last_change(&self) -> Instant {
        self.lock().last_change
    }

    /// Set the turntable angle, degrees.
    pub fn set_turntable_angle(&self, degrees: f64) {
        self.change(|s| s.turntable_deg = degrees);
    }

    /// Set white light `index` to `level` (0..=1).
    pub fn set_light(&self, index: usize, level: f32) -> Result<(), SimError> {
        if !(level.is_finite() && (0.0..=1.0).contains(&level)) {
            return Err(SimError::InvalidLevel { level });
        }
        let count = self.inner.renderer.lighting().lights.len();
        if index >= count {
            return Err(SimError::NoSuchLight { index, count });
        }
        self.change(|s| s.light_levels[index] = level);
        Ok(())
    }

    /// Switch line laser `index` on or off.
    pub fn set_laser(&self, index: usize, on: bool) -> Result<(), SimError> {
        let count = self.inner.renderer.lighting().lasers.len();
        if index >= count {
            return Err(SimError::NoSuchLaser { index, count });
        }
        self.change(|s| s.lasers_on[index] = on);
        Ok(())
    }

    /// Show `pattern` on the projector (`None` = blank). The pattern must match the projector's
    /// resolution and hold `3 · width · height` bytes.
    pub fn set_pattern(&self, pattern: Option<Pattern>) -> Result<(), SimError> {
        self.check_pattern(pattern.as_ref())?;
        self.change(|s| {
            s.pattern = pattern;
            s.pending_pattern = None;
        });
        Ok(())
    }

    /// Hand `pattern` to the projector (`None` = blank); it appears on screen at `visible_at`, and
    /// until then cameras see the previous one. A pattern still pending is replaced.
    pub fn set_pattern_at(&self, pattern: Option<Pattern>, visible_at: Instant) -> Result<(), SimError> {
        self.check_pattern(pattern.as_ref())?;
        // A pattern due by now is on screen: promote it before queueing the next one.
        let _ = self.snapshot_timed();
        self.lock().pending_pattern = Some((pattern, visible_at));
        Ok(())
    }

    fn check_pattern(&self, pattern: Option<&Pattern>) -> Result<(), SimError> {
        if let Some(p) = pattern {
            let proj = self.inner.renderer.lighting().projector.as_ref().ok_or(SimError::NoProjector)?;
            let (w, h) = (proj.model.width, proj.model.height);
            if p.width != w || p.height != h || p.rgb.len() != 3 * w as usize * h as usize {
                return Err(SimError::PatternSize {
                    expected: (w, h),
                    width: p.width,
                    height: p.height,
                    bytes: p.rgb.len(),
                });
            }
        }
        Ok(())
    }

    fn change(&self, f: impl FnOnce(&mut WorldState)) {
        let mut s = self.lock();
        f(&mut s);
        s.changes += 1;
        s.last_change = Instant::now();
    }

    fn lock(&self) -> MutexGuard<'_, WorldState> {
        // The state is plain data that every writer leaves consistent, so a poisoned lock is safe to use.
        self.inner.state.lock().unwrap_or_else(|e| e.into_inner())
    }
}
