//! The device-free half of the GenICam driver: which GenICam features a rig file's settings write,
//! in what order, and whether what the camera reads back is what was asked. Tested without a camera;
//! the [`genicam`](super::genicam) driver (cargo feature `aravis`) applies the writes through Aravis.
//!
//! Trigger modes and the acquisition's fresh-frame rule (a frame counts for a scene change only if
//! its exposure started after the change):
//! - free run (`TriggerMode = Off`): the camera exposes continuously; frames queued before the change
//!   are stale and dropped by the acquisition from their start-of-exposure time;
//! - software (`TriggerSource = Software`): the driver empties the queue and sends `TriggerSoftware`
//!   inside `capture`, after the caller's change, so the frame it returns began exposing after the
//!   trigger: always fresh, one trigger per captured frame;
//! - hardware line (`TriggerSource = LineN`, with `TriggerActivation` and `TriggerDelay`): an
//!   external pulse (a projector's sync out, a controller pin) starts each exposure; frames carry the
//!   host arrival time moved back by exposure and readout, and frames triggered before the change are
//!   dropped as stale like free-run ones.

pub use crate::config::vocab::{GenicamPixelFormat, TriggerActivation, TriggerMode};

impl TriggerActivation {
    /// The GenICam enumeration entry.
    pub fn genicam(self) -> &'static str {
        match self {
            TriggerActivation::RisingEdge => "RisingEdge",
            TriggerActivation::FallingEdge => "FallingEdge",
            TriggerActivation::AnyEdge => "AnyEdge",
            TriggerActivation::LevelHigh => "LevelHigh",
            TriggerActivation::LevelLow => "LevelLow",
        }
    }
}

impl GenicamPixelFormat {
    /// The GenICam `PixelFormat` entry.
    pub fn genicam(self) -> &'static str {
        match self {
            GenicamPixelFormat::Mono8 => "Mono8",
            GenicamPixelFormat::Rgb8 => "RGB8",
        }
    }

    /// The same layout as a [`PixelFormat`](super::pixel::PixelFormat) for conversion.
    pub fn layout(self) -> super::pixel::PixelFormat {
        match self {
            GenicamPixelFormat::Mono8 => super::pixel::PixelFormat::Grey,
            GenicamPixelFormat::Rgb8 => super::pixel::PixelFormat::Rgb24,
        }
    }
}

/// One write of a GenICam enumeration feature, in order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EnumWrite {
    /// The feature (`TriggerMode`).
    pub feature: &'static str,
    /// The entry (`On`).
    pub value: String,
    /// The write may be skipped when the camera lacks the feature (`TriggerSelector` on cameras
    /// with a single trigger).
    pub optional: bool,
}

fn write(feature: &'static str, value: impl Into<String>, optional: bool) -> EnumWrite {
    EnumWrite { feature, value: value.into(), optional }
}

/// The enumeration writes that put the camera in `mode`. The trigger delay, a float, is written
/// after these (see [`DELAY_FEATURES`]).
pub fn trigger_writes(mode: TriggerMode, line: &str, activation: TriggerActivation) -> Vec<EnumWrite> {
    let select = write("TriggerSelector", "FrameStart", true);
    match mode {
        TriggerMode::FreeRun => vec![select, write("TriggerMode", "Off", false)],
        TriggerMode::Software => {
            vec![select, write("TriggerSource", "Software", false), write("TriggerMode", "On", false)]
        }
        TriggerMode::Line => vec![
            select,
            write("TriggerSource", line, false),
            // RisingEdge is what cameras without the feature do; any other needs the feature.
            write("TriggerActivation", activation.genicam(), activation == TriggerActivation::RisingEdge),
            write("TriggerMode", "On", false),
        ],
    }
}

/// The float features that hold the trigger delay, microseconds, by SFNC version (`TriggerDelay`
/// since SFNC 2.0, `TriggerDelayAbs` before).
pub const DELAY_FEATURES: [&str; 2] = ["TriggerDelay", "TriggerDelayAbs"];

/// True when a float setting reads back as asked: within 0.5 % or `absolute` (a device rounds to
/// its register's unit, e.g. whole microseconds of a frame period).
pub fn reads_back(asked: f64, got: f64, absolute: f64) -> bool {
    (asked - got).abs() <= absolute.max(asked.abs() * 0.005)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn software_trigger_selects_frame_start_then_source_then_mode() {
        let w = trigger_writes(TriggerMode::Software, "Line0", TriggerActivation::RisingEdge);
        let order: Vec<(&str, &str)> = w.iter().map(|w| (w.feature, w.value.as_str())).collect();
        assert_eq!(order, [("TriggerSelector", "FrameStart"), ("TriggerSource", "Software"), ("TriggerMode", "On")]);
        assert!(w[0].optional && !w[1].optional && !w[2].optional);
    }

    #[test]
    fn a_line_trigger_needs_activation_support_only_off_the_rising_edge() {
        let rising = trigger_writes(TriggerMode::Line, "Line1", TriggerActivation::RisingEdge);
        assert_eq!(rising[1].value, "Line1");
        assert!(rising[2].optional);
        let falling = trigger_writes(TriggerMode::Line, "Line1", TriggerActivation::FallingEdge);
        assert_eq!(
            (falling[2].feature, falling[2].value.as_str(), falling[2].optional),
            ("TriggerActivation", "FallingEdge", false)
        );
        assert_eq!(falling.last().map(|w| w.value.as_str()), Some("On"));
        let free = trigger_writes(TriggerMode::FreeRun, "Line1", TriggerActivation::FallingEdge);
        assert_eq!(free.last().map(|w| (w.feature, w.value.as_str())), Some(("TriggerMode", "Off")));
    }

    #[test]
    fn read_back_tolerates_register_rounding_only() {
        assert!(reads_back(5000.0, 5000.0, 1.0));
        assert!(reads_back(5000.0, 5020.0, 1.0));
        assert!(!reads_back(5000.0, 5100.0, 1.0));
        assert!(reads_back(3.0, 3.0, 0.01));
        assert!(!reads_back(3.0, 2.0, 0.01));
    }

    #[test]
    fn rig_file_spellings() {
        #[derive(serde::Deserialize)]
        struct T {
            t: TriggerMode,
            a: TriggerActivation,
            p: GenicamPixelFormat,
        }
        let t: T = toml::from_str("t = \"free-run\"\na = \"falling-edge\"\np = \"RGB8\"").expect("parses");
        assert_eq!((t.t, t.a, t.p), (TriggerMode::FreeRun, TriggerActivation::FallingEdge, GenicamPixelFormat::Rgb8));
        assert!(toml::from_str::<T>("t = \"hardware\"\na = \"rising-edge\"\np = \"Mono8\"").is_err());
    }
}
