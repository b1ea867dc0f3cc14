//! The link: a transport with a receive buffer and deadline-bounded reads. Every wait ends at a
//! deadline; an I/O error other than a timeout is a disconnect, never retried in a loop.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use super::error::{printable, LinkError};
use super::port::Transport;

/// Longest single read wait, so deadlines are honoured closely.
const READ_SLICE: Duration = Duration::from_millis(50);

/// An open connection to a board.
#[derive(Debug)]
pub struct Link {
    transport: Box<dyn Transport>,
    rx: VecDeque<u8>,
}

impl Link {
    /// Wrap an open transport.
    pub fn new(transport: Box<dyn Transport>) -> Self {
        Link { transport, rx: VecDeque::new() }
    }

    /// Send bytes.
    pub fn send(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        tracing::trace!(bytes = %printable(bytes), "serial tx");
        let io = |e| LinkError::from_io(e, "writing", Duration::ZERO);
        self.transport.write_all(bytes).map_err(io)?;
        self.transport.flush().map_err(io)
    }

    /// One byte, waiting until `deadline` at most. `waiting_for` and `timeout` go into the error.
    pub fn read_byte(
        &mut self,
        deadline: Instant,
        waiting_for: &'static str,
        timeout: Duration,
    ) -> Result<u8, LinkError> {
        loop {
            if let Some(b) = self.rx.pop_front() {
                return Ok(b);
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(LinkError::Timeout { waiting_for, timeout });
            }
            let wait = (deadline - now).min(READ_SLICE).max(Duration::from_millis(1));
            self.transport.set_read_timeout(wait).map_err(|e| LinkError::from_io(e, waiting_for, timeout))?;
            let mut buf = [0u8; 256];
            match self.transport.read(&mut buf) {
                Ok(0) => return Err(LinkError::Disconnected { source: None }),
                Ok(n) => {
                    tracing::trace!(bytes = %printable(&buf[..n]), "serial rx");
                    self.rx.extend(&buf[..n]);
                }
                Err(e) => match LinkError::from_io(e, waiting_for, timeout) {
                    LinkError::Timeout { .. } | LinkError::Io { .. } => continue,
                    other => return Err(other),
                },
            }
        }
    }

    /// Drop whatever has been received and not read yet, and whatever arrives within `quiet`.
    pub fn discard_input(&mut self, quiet: Duration) -> Result<(), LinkError> {
        self.rx.clear();
        let deadline = Instant::now() + quiet;
        loop {
            match self.read_byte(deadline, "discarding input", quiet) {
                Ok(_) => self.rx.clear(),
                Err(LinkError::Timeout { .. }) => return Ok(()),
                Err(e) => return Err(e),
            }
        }
    }
}
