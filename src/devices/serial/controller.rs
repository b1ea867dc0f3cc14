//! One board on one port: the link, its dialect, the connection state and reconnection with capped
//! backoff. The turntable and the light array of a board share one controller.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use super::dialect::{BoardInfo, Dialect};
use super::error::LinkError;
use super::link::Link;
use super::port::Opener;

/// Consecutive timeouts after which a silent board is treated as gone.
const TIMEOUTS_BEFORE_DISCONNECT: u32 = 3;

/// Whether the board is reachable.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkState {
    /// Handshake done; commands go through.
    Connected,
    /// No link. The next attempt to connect is not made before `retry_at`.
    Disconnected {
        /// When the link was lost (or the first attempt failed).
        since: Instant,
        /// Failed attempts since then.
        attempts: u32,
        /// Earliest next attempt.
        retry_at: Instant,
    },
}

/// Doubling backoff between reconnection attempts, capped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Backoff {
    /// First wait.
    pub initial: Duration,
    /// Longest wait.
    pub max: Duration,
}

impl Backoff {
    /// The wait after `attempts` failed attempts.
    pub fn delay(&self, attempts: u32) -> Duration {
        let factor = 1u32.checked_shl(attempts.saturating_sub(1).min(16)).unwrap_or(u32::MAX);
        self.initial.saturating_mul(factor).min(self.max)
    }
}

/// What the config says the board must be; checked after each handshake.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Expectations {
    /// Steps per turn the rig was calibrated with; a different board value is refused (a mismatch
    /// mirrors or stretches scans).
    pub steps_per_turn: Option<u32>,
}

/// A board on a serial line.
#[derive(Debug)]
pub struct SerialController {
    opener: Box<dyn Opener>,
    dialect: Box<dyn Dialect>,
    link: Option<Link>,
    info: Option<BoardInfo>,
    state: LinkState,
    backoff: Backoff,
    expect: Expectations,
    position_steps: i64,
    timeouts_in_a_row: u32,
}

/// A controller shared by the devices of one board.
pub type SharedController = Arc<Mutex<SerialController>>;

/// Lock a shared controller; a panic in another holder does not make the board unusable.
pub fn lock(c: &SharedController) -> MutexGuard<'_, SerialController> {
    c.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl SerialController {
    /// A controller that is not connected yet; the first command connects.
    pub fn new(opener: Box<dyn Opener>, dialect: Box<dyn Dialect>, backoff: Backoff, expect: Expectations) -> Self {
        let now = Instant::now();
        SerialController {
            opener,
            dialect,
            link: None,
            info: None,
            state: LinkState::Disconnected { since: now, attempts: 0, retry_at: now },
            backoff,
            expect,
            position_steps: 0,
            timeouts_in_a_row: 0,
        }
    }

    /// The link state.
    pub fn state(&self) -> LinkState {
        self.state
    }

    /// What the board said about itself in the last handshake.
    pub fn info(&self) -> Option<&BoardInfo> {
        self.info.as_ref()
    }

    /// The dialect's config name.
    pub fn dialect_name(&self) -> &'static str {
        self.dialect.name()
    }

    /// Last reported position, steps from zero.
    pub fn position_steps(&self) -> i64 {
        self.position_steps
    }

    /// Open the port and handshake, now.
    pub fn connect(&mut self) -> Result<(), LinkError> {
        self.link = None;
        let result = self.opener.open().and_then(|t| {
            let mut link = Link::new(t);
            let info = self.dialect.handshake(&mut link)?;
            if let Some(want) = self.expect.steps_per_turn {
                if want != info.steps_per_turn {
                    return Err(LinkError::Mismatch {
                        problem: format!("board turns {} steps per turn, the config says {want}", info.steps_per_turn),
                    });
                }
            }
            Ok((link, info))
        });
        match result {
            Ok((link, info)) => {
                tracing::info!(port = %self.opener.describe(), board = %info.name, fw = %info.firmware,
                    steps_per_turn = info.steps_per_turn, "serial board connected");
                self.position_steps = info.position_steps;
                self.link = Some(link);
                self.info = Some(info);
                self.state = LinkState::Connected;
                self.timeouts_in_a_row = 0;
                Ok(())
            }
            Err(e) => {
                self.mark_disconnected();
                Err(e)
            }
        }
    }

    fn mark_disconnected(&mut self) {
        self.link = None;
        let now = Instant::now();
        let (since, attempts) = match self.state {
            LinkState::Disconnected { since, attempts, .. } => (since, attempts + 1),
            LinkState::Connected => {
                tracing::warn!(port = %self.opener.describe(), "serial board disconnected");
                (now, 1)
            }
        };
        self.state = LinkState::Disconnected { since, attempts, retry_at: now + self.backoff.delay(attempts) };
    }

    /// Keep trying to connect, with capped backoff, until connected or `deadline`. Returns at the
    /// deadline at the latest.
    pub fn reconnect(&mut self, deadline: Instant) -> Result<(), LinkError> {
        loop {
            if let LinkState::Disconnected { retry_at, .. } = self.state {
                let now = Instant::now();
                if retry_at > now {
                    if retry_at > deadline {
                        return Err(LinkError::Disconnected { source: None });
                    }
                    std::thread::sleep(retry_at - now);
                }
            }
            match self.connect() {
                Ok(()) => return Ok(()),
                Err(e) if Instant::now() >= deadline => return Err(e),
                Err(e) => tracing::debug!(error = %e, "reconnect attempt failed"),
            }
        }
    }

    /// Run `f` on the connected link, connecting first if the backoff allows. A disconnect, a reset
    /// board or repeated silence drops the link so that the next call reconnects.
    pub fn with_link<T>(
        &mut self,
        f: impl FnOnce(&mut dyn Dialect, &mut Link, &BoardInfo) -> Result<T, LinkError>,
    ) -> Result<T, LinkError> {
        if self.link.is_none() {
            match self.state {
                LinkState::Disconnected { retry_at, .. } if Instant::now() < retry_at => {
                    return Err(LinkError::Disconnected { source: None })
                }
                _ => self.connect()?,
            }
        }
        let (Some(link), Some(info)) = (self.link.as_mut(), self.info.as_ref()) else {
            return Err(LinkError::Disconnected { source: None });
        };
        let result = f(self.dialect.as_mut(), link, info);
        match &result {
            Ok(_) => self.timeouts_in_a_row = 0,
            Err(LinkError::Timeout { .. }) => {
                self.timeouts_in_a_row += 1;
                if self.timeouts_in_a_row >= TIMEOUTS_BEFORE_DISCONNECT {
                    tracing::warn!("serial board silent {} times in a row", self.timeouts_in_a_row);
                    self.mark_disconnected();
                }
            }
            Err(e) if e.needs_reconnect() => self.mark_disconnected(),
            Err(_) => {}
        }
        result
    }

    /// Drive to the end stop and zero there (boards without one refuse).
    pub fn home(&mut self, timeout: Duration) -> Result<(), LinkError> {
        let pos = self.with_link(|d, l, _| d.home(l, timeout))?;
        self.position_steps = pos;
        Ok(())
    }

    /// Turn to `steps` and wait for the motion to finish.
    pub fn move_to_steps(&mut self, steps: i64, timeout: Duration) -> Result<i64, LinkError> {
        let pos = self.with_link(|d, l, _| d.move_to(l, steps, timeout))?;
        self.position_steps = pos;
        Ok(pos)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_doubles_then_caps() {
        let b = Backoff { initial: Duration::from_millis(100), max: Duration::from_millis(1000) };
        let delays: Vec<u128> = (1..=7).map(|n| b.delay(n).as_millis()).collect();
        assert_eq!(delays, vec![100, 200, 400, 800, 1000, 1000, 1000]);
        assert_eq!(b.delay(u32::MAX), Duration::from_millis(1000));
    }
}
