//! Camera controls locked for a scan and restored after it: the device-free half of the real camera
//! drivers.
//!
//! A scan needs every frame taken with the same exposure, gain, white balance and focus, so the driver
//! turns the automatic modes off and sets manual values when it opens the camera, remembering what was
//! there, and puts the old values back (in reverse order: manual values first, then the auto modes)
//! when it is closed. The control ids and units are V4L2's; a [`ControlBackend`] reads and writes them
//! (the V4L2 device, or a map in a test).

pub use crate::config::vocab::ManualControls;

/// V4L2 control ids (`linux/v4l2-controls.h`) used by the scan settings.
pub mod cid {
    /// `V4L2_CID_EXPOSURE_AUTO`: a menu, see [`super::EXPOSURE_MANUAL`].
    pub const EXPOSURE_AUTO: u32 = 0x009a_0901;
    /// `V4L2_CID_EXPOSURE_ABSOLUTE`: exposure time in units of 100 microseconds.
    pub const EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
    /// `V4L2_CID_AUTOGAIN`: boolean.
    pub const AUTOGAIN: u32 = 0x0098_0912;
    /// `V4L2_CID_GAIN`: device units.
    pub const GAIN: u32 = 0x0098_0913;
    /// `V4L2_CID_AUTO_WHITE_BALANCE`: boolean.
    pub const AUTO_WHITE_BALANCE: u32 = 0x0098_090c;
    /// `V4L2_CID_WHITE_BALANCE_TEMPERATURE`: kelvin.
    pub const WHITE_BALANCE_TEMPERATURE: u32 = 0x0098_091a;
    /// `V4L2_CID_FOCUS_AUTO`: boolean.
    pub const FOCUS_AUTO: u32 = 0x009a_090c;
    /// `V4L2_CID_FOCUS_ABSOLUTE`: device units (often 0 = infinity).
    pub const FOCUS_ABSOLUTE: u32 = 0x009a_090a;
}

/// `V4L2_EXPOSURE_MANUAL`, the value of [`cid::EXPOSURE_AUTO`] for a fixed exposure time.
pub const EXPOSURE_MANUAL: i64 = 1;
/// `V4L2_EXPOSURE_APERTURE_PRIORITY`, what UVC cameras use for automatic exposure.
pub const EXPOSURE_APERTURE_PRIORITY: i64 = 3;

/// Exposure time in microseconds to V4L2's `EXPOSURE_ABSOLUTE` units of 100 µs, rounded to the
/// nearest unit and at least 1.
pub fn exposure_us_to_v4l2(us: u32) -> i64 {
    ((us as i64 + 50) / 100).max(1)
}

/// V4L2 `EXPOSURE_ABSOLUTE` units (100 µs) to microseconds.
pub fn exposure_v4l2_to_us(units: i64) -> u64 {
    units.max(0) as u64 * 100
}

/// What a device says about one control.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ControlRange {
    /// Smallest value.
    pub min: i64,
    /// Largest value.
    pub max: i64,
    /// Step between values (at least 1).
    pub step: i64,
}

impl ControlRange {
    /// `value` moved into the range and onto its step grid (counted from `min`).
    pub fn clamp(&self, value: i64) -> i64 {
        let step = self.step.max(1);
        let v = value.clamp(self.min, self.max);
        let snapped = self.min + ((v - self.min) + step / 2) / step * step;
        if snapped > self.max {
            snapped - step
        } else {
            snapped
        }
    }
}

/// Reads and writes integer controls by V4L2 id or by name.
pub trait ControlBackend {
    /// The control's range, or `None` when the device does not have it.
    fn range(&self, id: u32) -> Option<ControlRange>;
    /// The id of the control with this name (case-insensitive), for vendor controls such as a
    /// trigger mode.
    fn id_by_name(&self, name: &str) -> Option<u32>;
    /// The current value.
    fn get(&mut self, id: u32) -> std::io::Result<i64>;
    /// Set a value.
    fn set(&mut self, id: u32, value: i64) -> std::io::Result<()>;
}

/// Why a control could not be locked or restored.
#[derive(Debug, thiserror::Error)]
pub enum ControlError {
    /// The camera has no such control.
    #[error("the camera has no control `{name}` (needed for `{setting}`)")]
    Missing {
        /// The control's name.
        name: String,
        /// The rig-file setting that needs it.
        setting: String,
    },
    /// The device refused a read or write.
    #[error("control `{name}` (id {id:#010x}): {op} failed")]
    Io {
        /// The control's name.
        name: String,
        /// V4L2 id.
        id: u32,
        /// `read` or `write`.
        op: &'static str,
        /// The error.
        #[source]
        source: std::io::Error,
    },
}

/// One control written by [`ControlLock::apply`]: what it was, and what it was set to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Changed {
    /// V4L2 id.
    pub id: u32,
    /// Name for messages.
    pub name: String,
    /// The value before the scan.
    pub previous: i64,
    /// The value set (after clamping to the device's range).
    pub applied: i64,
}

/// The controls a scan changed, to be restored after it.
#[derive(Debug, Default)]
pub struct ControlLock {
    changed: Vec<Changed>,
}

impl ControlLock {
    /// Turn the automatic modes off and set the manual values of `settings`, in this order: auto
    /// exposure -> manual, exposure; auto gain off, gain; auto white balance off, temperature;
    /// autofocus off, focus; then the extra controls. A setting whose control the device lacks is an
    /// error; a missing *auto* control is skipped (some cameras have only the manual one). On error
    /// the controls already changed are put back before returning.
    pub fn apply(backend: &mut dyn ControlBackend, settings: &ManualControls) -> Result<Self, ControlError> {
        /// One write: control id, name, value, whether the device may lack it (auto switches), and
        /// the rig-file setting it comes from.
        struct Step {
            id: u32,
            name: String,
            value: i64,
            optional: bool,
            setting: String,
        }
        let mut plan: Vec<Step> = Vec::new();
        let mut manual = |auto: (u32, &str, i64), value: (u32, &str, i64), setting: &str| {
            let (id, name, v) = auto;
            plan.push(Step { id, name: name.to_owned(), value: v, optional: true, setting: setting.to_owned() });
            let (id, name, v) = value;
            plan.push(Step { id, name: name.to_owned(), value: v, optional: false, setting: setting.to_owned() });
        };
        if let Some(us) = settings.exposure_us {
            manual(
                (cid::EXPOSURE_AUTO, "auto_exposure", EXPOSURE_MANUAL),
                (cid::EXPOSURE_ABSOLUTE, "exposure_time_absolute", exposure_us_to_v4l2(us)),
                "exposure_us",
            );
        }
        if let Some(g) = settings.gain {
            manual((cid::AUTOGAIN, "gain_automatic", 0), (cid::GAIN, "gain", g), "gain");
        }
        if let Some(k) = settings.white_balance_k {
            manual(
                (cid::AUTO_WHITE_BALANCE, "white_balance_automatic", 0),
                (cid::WHITE_BALANCE_TEMPERATURE, "white_balance_temperature", k),
                "white_balance_k",
            );
        }
        if let Some(f) = settings.focus {
            manual(
                (cid::FOCUS_AUTO, "focus_automatic_continuous", 0),
                (cid::FOCUS_ABSOLUTE, "focus_absolute", f),
                "focus",
            );
        }
        for (name, &value) in &settings.extra {
            let Some(id) = backend.id_by_name(name) else {
                return Err(ControlError::Missing { name: name.clone(), setting: format!("controls.{name}") });
            };
            plan.push(Step { id, name: name.clone(), value, optional: false, setting: format!("controls.{name}") });
        }

        let mut lock = ControlLock::default();
        for Step { id, name, value, optional, setting } in plan {
            let Some(range) = backend.range(id) else {
                if optional {
                    continue;
                }
                lock.restore(backend);
                return Err(ControlError::Missing { name, setting });
            };
            let applied = range.clamp(value);
            let step = (|| {
                let previous = backend.get(id).map_err(|source| ControlError::Io {
                    name: name.clone(),
                    id,
                    op: "read",
                    source,
                })?;
                backend.set(id, applied).map_err(|source| ControlError::Io {
                    name: name.clone(),
                    id,
                    op: "write",
                    source,
                })?;
                Ok(previous)
            })();
            match step {
                Ok(previous) => {
                    if applied != value {
                        tracing::warn!(control = %name, asked = value, applied, "control value clamped to the device's range");
                    }
                    lock.changed.push(Changed { id, name, previous, applied });
                }
                Err(e) => {
                    lock.restore(backend);
                    return Err(e);
                }
            }
        }
        Ok(lock)
    }

    /// The controls changed, in the order they were set.
    pub fn changed(&self) -> &[Changed] {
        &self.changed
    }

    /// Put every changed control back, last changed first (so a manual value is restored while its
    /// auto mode is still off, then the auto mode). Failures are logged, not returned: restoring runs
    /// at the end of a scan and from `Drop`, and one failure must not stop the others. Returns the
    /// number of controls that could not be restored. Idempotent.
    pub fn restore(&mut self, backend: &mut dyn ControlBackend) -> usize {
        let mut failed = 0;
        while let Some(c) = self.changed.pop() {
            if let Err(e) = backend.set(c.id, c.previous) {
                failed += 1;
                tracing::warn!(control = %c.name, value = c.previous, error = %e, "could not restore a camera control");
            }
        }
        failed
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    /// A camera's controls in a map; records every write.
    #[derive(Debug, Default)]
    struct FakeControls {
        values: HashMap<u32, i64>,
        ranges: HashMap<u32, ControlRange>,
        names: HashMap<String, u32>,
        writes: Vec<(u32, i64)>,
        fail_write: Option<u32>,
    }

    impl FakeControls {
        fn webcam() -> Self {
            let mut f = FakeControls::default();
            let r = |min, max, step| ControlRange { min, max, step };
            for (id, v, range) in [
                (cid::EXPOSURE_AUTO, EXPOSURE_APERTURE_PRIORITY, r(0, 3, 1)),
                (cid::EXPOSURE_ABSOLUTE, 156, r(3, 2047, 1)),
                (cid::GAIN, 64, r(0, 255, 1)),
                (cid::AUTO_WHITE_BALANCE, 1, r(0, 1, 1)),
                (cid::WHITE_BALANCE_TEMPERATURE, 4000, r(2000, 6500, 10)),
                (cid::FOCUS_AUTO, 1, r(0, 1, 1)),
                (cid::FOCUS_ABSOLUTE, 30, r(0, 250, 5)),
                (0x0099_0001, 0, r(0, 2, 1)),
            ] {
                f.values.insert(id, v);
                f.ranges.insert(id, range);
            }
            f.names.insert("trigger_mode".into(), 0x0099_0001);
            f
        }
    }

    impl ControlBackend for FakeControls {
        fn range(&self, id: u32) -> Option<ControlRange> {
            self.ranges.get(&id).copied()
        }
        fn id_by_name(&self, name: &str) -> Option<u32> {
            self.names.iter().find(|(n, _)| n.eq_ignore_ascii_case(name)).map(|(_, &id)| id)
        }
        fn get(&mut self, id: u32) -> std::io::Result<i64> {
            self.values.get(&id).copied().ok_or_else(|| std::io::Error::from(std::io::ErrorKind::NotFound))
        }
        fn set(&mut self, id: u32, value: i64) -> std::io::Result<()> {
            if self.fail_write == Some(id) {
                return Err(std::io::Error::from_raw_os_error(libc::EIO));
            }
            self.writes.push((id, value));
            self.values.insert(id, value);
            Ok(())
        }
    }

    #[test]
    fn exposure_units_are_100_microseconds() {
        assert_eq!(exposure_us_to_v4l2(20_000), 200);
        assert_eq!(exposure_us_to_v4l2(149), 1);
        assert_eq!(exposure_us_to_v4l2(150), 2);
        assert_eq!(exposure_us_to_v4l2(0), 1);
        assert_eq!(exposure_v4l2_to_us(200), 20_000);
    }

    #[test]
    fn clamp_snaps_to_the_step_grid() {
        let r = ControlRange { min: 2000, max: 6500, step: 10 };
        assert_eq!(r.clamp(4604), 4600);
        assert_eq!(r.clamp(4605), 4610);
        assert_eq!(r.clamp(9000), 6500);
        let r = ControlRange { min: 0, max: 7, step: 5 };
        assert_eq!(r.clamp(7), 5);
    }

    #[test]
    fn lock_sets_auto_off_before_values_and_restores_in_reverse() {
        let mut cam = FakeControls::webcam();
        let before = cam.values.clone();
        let settings = ManualControls {
            exposure_us: Some(20_000),
            gain: Some(300),
            white_balance_k: Some(4604),
            focus: Some(0),
            extra: [("Trigger_Mode".to_owned(), 1)].into(),
        };
        let mut lock = ControlLock::apply(&mut cam, &settings).expect("lock");
        assert_eq!(
            cam.writes,
            vec![
                (cid::EXPOSURE_AUTO, EXPOSURE_MANUAL),
                (cid::EXPOSURE_ABSOLUTE, 200),
                // The camera has no auto gain control: skipped.
                (cid::GAIN, 255),
                (cid::AUTO_WHITE_BALANCE, 0),
                (cid::WHITE_BALANCE_TEMPERATURE, 4600),
                (cid::FOCUS_AUTO, 0),
                (cid::FOCUS_ABSOLUTE, 0),
                (0x0099_0001, 1),
            ]
        );
        assert_eq!(lock.changed()[2], Changed { id: cid::GAIN, name: "gain".into(), previous: 64, applied: 255 });
        cam.writes.clear();
        assert_eq!(lock.restore(&mut cam), 0);
        assert_eq!(cam.values, before);
        assert_eq!(cam.writes.first(), Some(&(0x0099_0001, 0)));
        assert_eq!(cam.writes.last(), Some(&(cid::EXPOSURE_AUTO, EXPOSURE_APERTURE_PRIORITY)));
        // Idempotent.
        cam.writes.clear();
        assert_eq!(lock.restore(&mut cam), 0);
        assert!(cam.writes.is_empty());
    }

    #[test]
    fn a_missing_control_or_failed_write_undoes_what_was_set() {
        let mut cam = FakeControls::webcam();
        let before = cam.values.clone();
        cam.ranges.remove(&cid::FOCUS_ABSOLUTE);
        let settings = ManualControls { exposure_us: Some(10_000), focus: Some(10), ..Default::default() };
        let e = ControlLock::apply(&mut cam, &settings).expect_err("no focus control");
        assert!(matches!(&e, ControlError::Missing { setting, .. } if setting == "focus"), "{e}");
        assert_eq!(cam.values, before, "exposure and autofocus were put back");

        let mut cam = FakeControls::webcam();
        cam.fail_write = Some(cid::EXPOSURE_ABSOLUTE);
        let e = ControlLock::apply(&mut cam, &ManualControls { exposure_us: Some(5000), ..Default::default() })
            .expect_err("write fails");
        assert!(matches!(e, ControlError::Io { op: "write", .. }));
        assert_eq!(cam.values[&cid::EXPOSURE_AUTO], EXPOSURE_APERTURE_PRIORITY);

        let mut cam = FakeControls::webcam();
        let extra = [("strobe".to_owned(), 1)].into();
        let e = ControlLock::apply(&mut cam, &ManualControls { extra, ..Default::default() }).expect_err("unknown");
        assert!(e.to_string().contains("strobe"));
    }
}
