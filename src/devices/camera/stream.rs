//! Stream bookkeeping of the real camera drivers, free of any device: driver timestamps to
//! [`Instant`]s at the start of exposure, sequence-number gaps (dropped frames), and whether a frame
//! is fresh for a scene change.

use std::time::{Duration, Instant};

/// Where in the frame's life the driver took its timestamp (V4L2 `V4L2_BUF_FLAG_TSTAMP_SRC_*`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TimestampSource {
    /// Start of exposure (`TSTAMP_SRC_SOE`).
    StartOfExposure,
    /// End of frame, when the last byte arrived (`TSTAMP_SRC_EOF`, the default and what UVC uses).
    EndOfFrame,
}

/// The start of exposure of a frame as an [`Instant`], from a driver timestamp on
/// `CLOCK_MONOTONIC` (`frame_ts`), the monotonic clock read now (`now_ts`) and the matching
/// `now` instant. For an end-of-frame timestamp the exposure time and the readout time (one frame
/// period at most; `readout`) are subtracted, so the result is never later than the real start:
/// a frame judged fresh by it really is.
pub fn exposure_start(
    frame_ts: Duration,
    source: TimestampSource,
    exposure: Duration,
    readout: Duration,
    now_ts: Duration,
    now: Instant,
) -> Instant {
    let start_ts = match source {
        TimestampSource::StartOfExposure => frame_ts,
        TimestampSource::EndOfFrame => frame_ts.saturating_sub(exposure + readout),
    };
    let age = now_ts.saturating_sub(start_ts);
    now.checked_sub(age).unwrap_or(now)
}

/// The monotonic clock (`CLOCK_MONOTONIC`) now, the clock V4L2 timestamps buffers with.
pub fn monotonic_now() -> Duration {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes one timespec through a valid pointer; CLOCK_MONOTONIC always
    // exists on Linux.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    if rc != 0 {
        return Duration::ZERO;
    }
    Duration::new(ts.tv_sec.max(0) as u64, ts.tv_nsec.clamp(0, 999_999_999) as u32)
}

/// Counts frames lost between the ones delivered, from the driver's sequence numbers (32-bit in V4L2,
/// wrapping).
#[derive(Debug, Clone, Default)]
pub struct SequenceTracker {
    last: Option<u32>,
    delivered: u64,
    dropped: u64,
    extended: u64,
}

/// What [`SequenceTracker::observe`] saw for one frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SequenceStep {
    /// The frame's sequence number extended to 64 bits (no wrap), counted from the first frame seen.
    pub sequence: u64,
    /// Frames missing between the previous frame and this one.
    pub dropped: u64,
}

impl SequenceTracker {
    /// A tracker that has seen nothing.
    pub fn new() -> Self {
        Self::default()
    }

    /// Record a frame with the driver's sequence number `seq`.
    pub fn observe(&mut self, seq: u32) -> SequenceStep {
        let dropped = match self.last {
            None => 0,
            Some(prev) => {
                let step = seq.wrapping_sub(prev) as u64;
                if step == 0 || step > u32::MAX as u64 / 2 {
                    // A repeated or backwards number: the driver restarted counting (stream
                    // restart). Nothing is known to be lost.
                    tracing::debug!(prev, seq, "camera sequence restarted");
                    self.extended += 1;
                    0
                } else {
                    self.extended += step;
                    step - 1
                }
            }
        };
        self.last = Some(seq);
        self.delivered += 1;
        self.dropped += dropped;
        if dropped > 0 {
            tracing::warn!(dropped, seq, "camera dropped frames");
        }
        SequenceStep { sequence: self.extended, dropped }
    }

    /// Frames delivered so far.
    pub fn delivered(&self) -> u64 {
        self.delivered
    }

    /// Frames dropped so far (gaps in the sequence numbers).
    pub fn dropped(&self) -> u64 {
        self.dropped
    }
}

/// True when a frame that started exposing at `exposure_start` shows a scene changed at
/// `changed_at`: it started exposing at or after the change.
pub fn is_fresh(exposure_start: Instant, changed_at: Instant) -> bool {
    exposure_start >= changed_at
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn end_of_frame_timestamps_move_back_by_exposure_and_readout() {
        let now = Instant::now();
        let now_ts = Duration::from_secs(1000);
        let ts = Duration::from_millis(999_900); // 100 ms ago
        let soe = exposure_start(
            ts,
            TimestampSource::StartOfExposure,
            Duration::from_millis(20),
            Duration::ZERO,
            now_ts,
            now,
        );
        assert_eq!(now - soe, Duration::from_millis(100));
        let eof = exposure_start(
            ts,
            TimestampSource::EndOfFrame,
            Duration::from_millis(20),
            Duration::from_millis(33),
            now_ts,
            now,
        );
        assert_eq!(now - eof, Duration::from_millis(153));
        // A timestamp from the future (clock skew) is clamped to now.
        let f = exposure_start(
            now_ts + Duration::from_secs(1),
            TimestampSource::StartOfExposure,
            Duration::ZERO,
            Duration::ZERO,
            now_ts,
            now,
        );
        assert_eq!(f, now);
    }

    #[test]
    fn monotonic_clock_advances() {
        let a = monotonic_now();
        let b = monotonic_now();
        assert!(a > Duration::ZERO && b >= a);
    }

    #[test]
    fn gaps_are_counted_across_the_32_bit_wrap() {
        let mut t = SequenceTracker::new();
        assert_eq!(t.observe(u32::MAX - 1), SequenceStep { sequence: 0, dropped: 0 });
        assert_eq!(t.observe(u32::MAX), SequenceStep { sequence: 1, dropped: 0 });
        assert_eq!(t.observe(2), SequenceStep { sequence: 4, dropped: 2 });
        assert_eq!(t.observe(3), SequenceStep { sequence: 5, dropped: 0 });
        // A restart (numbers going back) is no loss and keeps the extended count increasing.
        assert_eq!(t.observe(0), SequenceStep { sequence: 6, dropped: 0 });
        assert_eq!((t.delivered(), t.dropped()), (5, 2));
    }

    #[test]
    fn freshness_is_exposure_after_the_change() {
        let change = Instant::now();
        assert!(is_fresh(change, change));
        assert!(is_fresh(change + Duration::from_millis(1), change));
        assert!(!is_fresh(change - Duration::from_millis(1), change));
    }
}
