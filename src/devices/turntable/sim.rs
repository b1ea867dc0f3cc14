//! The simulated turntable: a stepper with `steps_per_turn` steps, moving at `speed_deg_per_s`.
//!
//! Positions are whole steps; `move_to` rounds the commanded angle to the nearest step and turns the
//! short way (at most half a turn). The world's turntable angle changes when the move has finished.
//! A move that would take longer than its timeout stops where the table had got to when the timeout
//! ran out (rounded towards the start, to a whole step), updates the world to that angle, and returns
//! [`DeviceError::Timeout`]. With `real_time` the driver sleeps for the simulated motion time.

use std::time::Duration;

use crate::config::SimTurntableConfig;
use crate::devices::DeviceError;
use crate::sim::SimWorld;

/// A simulated stepper turntable that turns the simulated world's scene.
#[derive(Debug)]
pub struct SimTurntable {
    world: SimWorld,
    steps_per_turn: u32,
    speed_deg_per_s: f64,
    real_time: bool,
    /// Absolute position in steps (not wrapped).
    position: i64,
    motor_on: bool,
}

impl SimTurntable {
    /// A turntable at 0° (step 0) in `world`.
    pub fn new(world: SimWorld, config: &SimTurntableConfig) -> Self {
        world.set_turntable_angle(0.0);
        SimTurntable {
            world,
            steps_per_turn: config.steps_per_turn.max(1),
            speed_deg_per_s: config.speed_deg_per_s,
            real_time: config.real_time,
            position: 0,
            motor_on: false,
        }
    }

    /// Whether the motor is energised (false after [`park`](super::Turntable::park) until the next move).
    pub fn motor_on(&self) -> bool {
        self.motor_on
    }

    fn deg_per_step(&self) -> f64 {
        360.0 / self.steps_per_turn as f64
    }
}

impl super::Turntable for SimTurntable {
    fn move_to(&mut self, degrees: f64, timeout: Duration) -> Result<(), DeviceError> {
        if !degrees.is_finite() {
            return Err(DeviceError::InvalidConfig {
                device: "turntable".into(),
                field: "degrees",
                problem: format!("target angle must be finite, got {degrees}"),
            });
        }
        if !(self.speed_deg_per_s.is_finite() && self.speed_deg_per_s > 0.0) {
            return Err(DeviceError::InvalidConfig {
                device: "turntable".into(),
                field: "speed_deg_per_s",
                problem: format!("must be a positive number, got {}", self.speed_deg_per_s),
            });
        }
        let spt = self.steps_per_turn as i64;
        // Shortest way to the commanded position modulo a turn; the reported angle is the commanded
        // one rounded to whole steps.
        let target_abs = (degrees / self.deg_per_step()).round();
        if target_abs.abs() > 1e15 {
            return Err(DeviceError::InvalidConfig {
                device: "turntable".into(),
                field: "degrees",
                problem: format!("target angle {degrees} is out of range"),
            });
        }
        let target_abs = target_abs as i64;
        let mut delta = (target_abs - self.position).rem_euclid(spt);
        if delta > spt / 2 {
            delta -= spt;
        }
        self.motor_on = true;
        let move_deg = delta.unsigned_abs() as f64 * self.deg_per_step();
        let move_time = move_deg / self.speed_deg_per_s;
        let (end, result) = if move_time > timeout.as_secs_f64() {
            let reached = (self.speed_deg_per_s * timeout.as_secs_f64() / self.deg_per_step()).floor() as i64;
            let reached = reached.min(delta.abs());
            (
                self.position + delta.signum() * reached,
                Err(DeviceError::Timeout { device: "turntable".into(), waiting_for: "the move to finish", timeout }),
            )
        } else {
            (target_abs, Ok(()))
        };
        if self.real_time {
            std::thread::sleep(Duration::from_secs_f64(move_time.min(timeout.as_secs_f64())));
        }
        self.position = end;
        self.world.set_turntable_angle(self.angle());
        tracing::debug!(target_deg = degrees, angle_deg = self.angle(), ok = result.is_ok(), "turntable moved");
        result
    }

    fn angle(&self) -> f64 {
        self.position as f64 * self.deg_per_step()
    }

    fn steps_per_turn(&self) -> u32 {
        self.steps_per_turn
    }

    fn park(&mut self, _timeout: Duration) -> Result<(), DeviceError> {
        self.motor_on = false;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::super::Turntable;
    use super::*;
    use crate::config::SimTurntableConfig;
    use crate::devices::ErrorKind;
    use crate::sim::tests::small_world;

    fn table(steps: u32, speed: f64) -> (SimTurntable, SimWorld) {
        let world = small_world("box");
        let t = SimTurntable::new(
            world.clone(),
            &SimTurntableConfig { steps_per_turn: steps, speed_deg_per_s: speed, real_time: false },
        );
        (t, world)
    }

    #[test]
    fn moves_are_quantised_to_whole_steps_and_reach_the_world() {
        let (mut t, world) = table(200, 90.0);
        let long = Duration::from_secs(60);
        t.move_to(10.0, long).expect("move");
        // 1.8° per step: 10° rounds to 6 steps = 10.8°.
        assert!((t.angle() - 10.8).abs() < 1e-12, "{}", t.angle());
        assert!((world.snapshot().turntable_deg - 10.8).abs() < 1e-12);
        t.move_to(-0.8, long).expect("move");
        assert!(t.angle().abs() < 1e-12, "{}", t.angle());
        assert!(t.motor_on());
        t.park(long).expect("park");
        assert!(!t.motor_on());
        assert_eq!(t.steps_per_turn(), 200);
    }

    #[test]
    fn a_move_longer_than_the_timeout_stops_part_way_with_a_timeout() {
        let (mut t, world) = table(3600, 10.0);
        // 90° at 10°/s takes 9 s; give it 2 s: it gets to 20°.
        let err = t.move_to(90.0, Duration::from_secs(2)).expect_err("times out");
        assert_eq!(err.kind(), ErrorKind::Timeout);
        assert!((t.angle() - 20.0).abs() < 1e-9, "{}", t.angle());
        assert!((world.snapshot().turntable_deg - 20.0).abs() < 1e-9);
        // The same move with time enough finishes.
        t.move_to(90.0, Duration::from_secs(8)).expect("finishes");
        assert!((t.angle() - 90.0).abs() < 1e-9);
    }

    #[test]
    fn moves_take_the_short_way() {
        let (mut t, _) = table(3600, 10.0);
        t.move_to(350.0, Duration::from_secs(1)).expect("short way: -10°, 1 s");
        assert!((t.angle() - 350.0).abs() < 1e-9);
        assert!(t.move_to(f64::NAN, Duration::from_secs(1)).is_err());
    }
}
