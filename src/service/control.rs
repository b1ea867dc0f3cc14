//! Manual control of the rig between scans: turn the table, switch lights and lasers, show a test
//! pattern or a colour on the projector. The commands run on the device thread (which owns the
//! drivers, see [`super::rig`]); this module holds their vocabulary, the state they leave the rig
//! in, and the one function that applies a command to an open [`Rig`].

use std::time::Duration;

use serde::{Deserialize, Serialize};

use crate::devices::projector::Pattern;
use crate::devices::{DeviceError, Rig};

/// A test image for the projector.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TestPattern {
    /// A black and white chessboard of 8 squares across (for focus and keystone).
    Checker,
    /// A horizontal grey ramp, black at the left to white at the right (for the response curve).
    Gray,
    /// All white.
    White,
    /// All black (unlike blank, a shown image).
    Black,
}

impl TestPattern {
    /// The name the API uses (`checker`, `gray`, `white`, `black`).
    pub fn name(self) -> &'static str {
        match self {
            TestPattern::Checker => "checker",
            TestPattern::Gray => "gray",
            TestPattern::White => "white",
            TestPattern::Black => "black",
        }
    }

    /// The pattern at `width` x `height` projector pixels.
    pub fn render(self, width: u32, height: u32) -> Pattern {
        match self {
            TestPattern::White => Pattern::uniform(width, height, [255; 3]),
            TestPattern::Black => Pattern::uniform(width, height, [0; 3]),
            TestPattern::Checker | TestPattern::Gray => {
                let square = (width / 8).max(1);
                let mut rgb = Vec::with_capacity(3 * width as usize * height as usize);
                for v in 0..height {
                    for u in 0..width {
                        let level = match self {
                            TestPattern::Checker => {
                                if (u / square + v / square) % 2 == 0 {
                                    255
                                } else {
                                    0
                                }
                            }
                            _ => (u64::from(u) * 255 / u64::from(width.saturating_sub(1).max(1))) as u8,
                        };
                        rgb.extend_from_slice(&[level; 3]);
                    }
                }
                Pattern { width, height, rgb: std::sync::Arc::new(rgb) }
            }
        }
    }
}

/// What to put on the projector.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ProjectorShow {
    /// A test pattern.
    Pattern(TestPattern),
    /// One colour over the whole image, 8-bit RGB.
    Colour([u8; 3]),
    /// Nothing (the projector's blank, as after a scan).
    Blank,
}

impl ProjectorShow {
    /// How [`ControlState::projector`] names it: `blank`, `checker`, `colour #rrggbb`...
    pub fn describe(self) -> String {
        match self {
            ProjectorShow::Pattern(p) => p.name().to_owned(),
            ProjectorShow::Colour([r, g, b]) => format!("colour #{r:02x}{g:02x}{b:02x}"),
            ProjectorShow::Blank => "blank".to_owned(),
        }
    }
}

/// One manual command.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ControlCommand {
    /// Turn the table by this many degrees from where it is (positive: the table's positive sense).
    Turn {
        /// Degrees.
        degrees: f64,
    },
    /// Home the table: drive to its end stop where it has one, else turn back to 0 degrees.
    Home,
    /// Switch white light `index` fully on or off.
    Light {
        /// Light index (0-based, as in the rig file).
        index: usize,
        /// On or off.
        on: bool,
    },
    /// Switch line laser `index` on or off.
    Laser {
        /// Laser index (0-based).
        index: usize,
        /// On or off.
        on: bool,
    },
    /// Show something on the projector.
    Projector(ProjectorShow),
}

/// The state the manual commands left the rig in (what `GET /api/v1/control` answers). After a
/// scan, a park or a reconnection it is the parked state: everything off, projector blank.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ControlState {
    /// The turntable's angle, degrees; `None` while the rig is not connected.
    pub angle_deg: Option<f64>,
    /// Each white light, on or off.
    pub lights: Vec<bool>,
    /// Each line laser, on or off.
    pub lasers: Vec<bool>,
    /// What the projector shows (see [`ProjectorShow::describe`]); `None` when the rig has none.
    pub projector: Option<String>,
}

impl ControlState {
    /// The parked state of `rig`: lights and lasers off, projector blank, the table's angle.
    pub fn parked(rig: &Rig) -> ControlState {
        ControlState {
            angle_deg: Some(rig.turntable.angle()),
            lights: vec![false; rig.lights.as_ref().map_or(0, |l| l.light_count())],
            lasers: vec![false; rig.lights.as_ref().map_or(0, |l| l.laser_count())],
            projector: rig.projector.as_ref().map(|_| ProjectorShow::Blank.describe()),
        }
    }
}

/// Why a manual command could not run.
#[derive(Debug, thiserror::Error)]
pub enum ControlError {
    /// The rig has no such device (no light array, no projector).
    #[error("the rig has no {0}")]
    NoDevice(&'static str),
    /// The index is past the devices the rig has.
    #[error("there is no {what} {index}: the rig has {count}")]
    NoSuchIndex {
        /// `light` or `laser`.
        what: &'static str,
        /// The index asked for.
        index: usize,
        /// How many there are.
        count: usize,
    },
    /// The angle is not a finite number of degrees.
    #[error("turn_deg must be a finite number of degrees, not {0}")]
    BadAngle(f64),
    /// The device failed.
    #[error("device error")]
    Device(#[source] DeviceError),
}

/// Apply `cmd` to `rig`, updating `state`. `timeout` bounds each device call.
pub fn apply(
    rig: &mut Rig,
    state: &mut ControlState,
    cmd: ControlCommand,
    timeout: Duration,
) -> Result<(), ControlError> {
    match cmd {
        ControlCommand::Turn { degrees } => {
            if !degrees.is_finite() {
                return Err(ControlError::BadAngle(degrees));
            }
            let target = rig.turntable.angle() + degrees;
            rig.turntable.move_to(target, timeout).map_err(ControlError::Device)?;
        }
        ControlCommand::Home => match rig.turntable.home(timeout) {
            Ok(()) => {}
            Err(e) if e.kind() == crate::devices::ErrorKind::Unsupported => {
                rig.turntable.move_to(0.0, timeout).map_err(ControlError::Device)?;
            }
            Err(e) => return Err(ControlError::Device(e)),
        },
        ControlCommand::Light { index, on } | ControlCommand::Laser { index, on } => {
            let laser = matches!(cmd, ControlCommand::Laser { .. });
            let lights = rig.lights.as_mut().ok_or(ControlError::NoDevice("light array"))?;
            let (what, count) = if laser { ("laser", lights.laser_count()) } else { ("light", lights.light_count()) };
            if index >= count {
                return Err(ControlError::NoSuchIndex { what, index, count });
            }
            if laser {
                lights.set_laser(index, on, timeout).map_err(ControlError::Device)?;
                state.lasers.resize(count, false);
                state.lasers[index] = on;
            } else {
                lights.set_light(index, if on { 1.0 } else { 0.0 }, timeout).map_err(ControlError::Device)?;
                state.lights.resize(count, false);
                state.lights[index] = on;
            }
        }
        ControlCommand::Projector(show) => {
            let projector = rig.projector.as_mut().ok_or(ControlError::NoDevice("projector"))?;
            let (w, h) = projector.resolution();
            match show {
                ProjectorShow::Blank => projector.blank(timeout).map_err(ControlError::Device)?,
                ProjectorShow::Pattern(p) => {
                    projector.show(&p.render(w, h), timeout).map_err(ControlError::Device)?;
                }
                ProjectorShow::Colour(rgb) => {
                    projector.show(&Pattern::uniform(w, h, rgb), timeout).map_err(ControlError::Device)?;
                }
            }
            state.projector = Some(show.describe());
        }
    }
    state.angle_deg = Some(rig.turntable.angle());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn test_patterns_have_the_projector_size_and_the_named_content() {
        let c = TestPattern::Checker.render(16, 4);
        assert_eq!(c.rgb.len(), 3 * 16 * 4);
        // Squares of 16 / 8 = 2 pixels: (0,0) white, (2,0) black, (2,2) white.
        assert_eq!(c.at(0, 0), [255; 3]);
        assert_eq!(c.at(2, 0), [0; 3]);
        assert_eq!(c.at(2, 2), [255; 3]);
        let g = TestPattern::Gray.render(5, 1);
        assert_eq!(g.at(0, 0), [0; 3]);
        assert_eq!(g.at(4, 0), [255; 3]);
        assert!(g.at(2, 0)[0] > 100 && g.at(2, 0)[0] < 155);
        assert_eq!(TestPattern::White.render(2, 2).at(1, 1), [255; 3]);
        assert_eq!(ProjectorShow::Colour([255, 0, 16]).describe(), "colour #ff0010");
    }
}
