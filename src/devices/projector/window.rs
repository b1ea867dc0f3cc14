//! A projector on an X11 output driven as a borderless full-screen window (cargo feature `x11`,
//! pure-Rust `x11rb`: no system library at build or run time, only an X server to talk to).
//!
//! The window is override-redirect (no window manager decorations or placement), covers the chosen
//! output exactly and stays on top. The output is chosen by its RandR name (`HDMI-1`) on any screen
//! of the display, or as a whole X screen (`screen:N`).
//!
//! Presentation: each pattern is drawn into an off-screen pixmap, then handed to the server with the
//! Present extension (`PresentPixmap`, copy mode, at the next vertical blank); the server's
//! `PresentCompleteNotify` says when it reached the screen (`ust`, microseconds on the server's
//! monotonic clock) and at which refresh (`msc`). `show` returns that instant plus the projector's
//! own latency, so the sequencer captures only after the pattern is on screen. The refresh period is
//! measured from those notifications. Without Present (or with `vsync = false`) the pattern is drawn
//! directly and one refresh period is allowed after the server confirms the drawing.
//!
//! A lost X connection (server gone) or a window destroyed by someone else is
//! [`DeviceError::Disconnected`].

use std::os::fd::AsRawFd;
use std::time::{Duration, Instant};

use x11rb::connection::{Connection, RequestConnection};
use x11rb::errors::{ConnectionError, ReplyError, ReplyOrIdError};
use x11rb::protocol::present::{self, ConnectionExt as _};
use x11rb::protocol::randr::{self, ConnectionExt as _};
use x11rb::protocol::xproto::{
    self, ConfigureWindowAux, ConnectionExt as _, CreateGCAux, CreateWindowAux, EventMask, ImageFormat, ImageOrder,
    StackMode, WindowClass,
};
use x11rb::protocol::Event;
use x11rb::rust_connection::RustConnection;

use super::framebuffer::{visible_at, Channel, FbLayout};
use super::Pattern;
use crate::config::WindowProjectorConfig;
use crate::devices::camera::stream::monotonic_now;
use crate::devices::DeviceError;

const NAME: &str = "projector";

/// `PresentOptionCopy`: copy the pixmap (never flip), so it is free again once presented.
const PRESENT_OPTION_COPY: u32 = 2;

fn lost(detail: String) -> DeviceError {
    DeviceError::Disconnected {
        device: NAME.into(),
        source: Some(std::io::Error::new(std::io::ErrorKind::ConnectionReset, detail)),
    }
}

fn conn_error(e: ConnectionError) -> DeviceError {
    lost(format!("X connection: {e}"))
}

fn reply_error(what: &str, e: ReplyError) -> DeviceError {
    match e {
        ReplyError::ConnectionError(c) => conn_error(c),
        ReplyError::X11Error(x) => {
            DeviceError::Protocol { device: NAME.into(), detail: format!("{what}: X error {:?}", x.error_kind) }
        }
    }
}

fn id_error(e: ReplyOrIdError) -> DeviceError {
    match e {
        ReplyOrIdError::ConnectionError(c) => conn_error(c),
        ReplyOrIdError::X11Error(x) => {
            DeviceError::Protocol { device: NAME.into(), detail: format!("X error {:?}", x.error_kind) }
        }
        ReplyOrIdError::IdsExhausted => DeviceError::Protocol { device: NAME.into(), detail: "X ids exhausted".into() },
    }
}

fn invalid(field: &'static str, problem: String) -> DeviceError {
    DeviceError::InvalidConfig { device: NAME.into(), field, problem }
}

/// Where the window goes: a screen and a rectangle on it, with the mode's refresh if known.
#[derive(Debug, Clone, PartialEq)]
pub struct OutputPlacement {
    /// X screen number.
    pub screen: usize,
    /// Left edge on the screen, pixels.
    pub x: i16,
    /// Top edge, pixels.
    pub y: i16,
    /// Width, pixels.
    pub width: u16,
    /// Height, pixels.
    pub height: u16,
    /// Refresh period of the output's mode, when it reports a pixel clock.
    pub mode_period: Option<Duration>,
}

/// The RandR outputs with a CRTC on screen `screen`: name and placement.
fn outputs_of(
    conn: &RustConnection,
    screen: usize,
    root: xproto::Window,
) -> Result<Vec<(String, OutputPlacement)>, DeviceError> {
    let res = conn
        .randr_get_screen_resources_current(root)
        .map_err(conn_error)?
        .reply()
        .map_err(|e| reply_error("RRGetScreenResourcesCurrent", e))?;
    let mut out = Vec::new();
    for &o in &res.outputs {
        let info = conn
            .randr_get_output_info(o, res.config_timestamp)
            .map_err(conn_error)?
            .reply()
            .map_err(|e| reply_error("RRGetOutputInfo", e))?;
        if info.crtc == x11rb::NONE {
            continue;
        }
        let crtc = conn
            .randr_get_crtc_info(info.crtc, res.config_timestamp)
            .map_err(conn_error)?
            .reply()
            .map_err(|e| reply_error("RRGetCrtcInfo", e))?;
        let mode_period = res.modes.iter().find(|m| m.id == crtc.mode).and_then(|m| {
            let dots = m.htotal as u64 * m.vtotal as u64;
            (m.dot_clock > 0 && dots > 0).then(|| Duration::from_secs_f64(dots as f64 / m.dot_clock as f64))
        });
        out.push((
            String::from_utf8_lossy(&info.name).into_owned(),
            OutputPlacement { screen, x: crtc.x, y: crtc.y, width: crtc.width, height: crtc.height, mode_period },
        ));
    }
    Ok(out)
}

/// Find `output` (a RandR output name, or `screen:N`) on the display.
fn place(conn: &RustConnection, output: &str) -> Result<OutputPlacement, DeviceError> {
    let roots: Vec<(usize, xproto::Window, u16, u16)> = conn
        .setup()
        .roots
        .iter()
        .enumerate()
        .map(|(i, s)| (i, s.root, s.width_in_pixels, s.height_in_pixels))
        .collect();
    let has_randr = conn.extension_information(randr::X11_EXTENSION_NAME).map_err(conn_error)?.is_some();
    let mut all = Vec::new();
    if has_randr {
        for &(i, root, _, _) in &roots {
            all.extend(outputs_of(conn, i, root)?);
        }
    }
    if let Some(n) = output.strip_prefix("screen:") {
        let n: usize = n.parse().map_err(|_| invalid("output", format!("`{output}`: expected screen:N")))?;
        let &(screen, _, width, height) = roots
            .get(n)
            .ok_or_else(|| invalid("output", format!("the display has {} screens, no screen {n}", roots.len())))?;
        // The screen's refresh: that of its only output, if it has exactly one.
        let on_screen: Vec<&OutputPlacement> = all.iter().map(|(_, p)| p).filter(|p| p.screen == n).collect();
        let mode_period = match on_screen.as_slice() {
            [one] => one.mode_period,
            _ => None,
        };
        return Ok(OutputPlacement { screen, x: 0, y: 0, width, height, mode_period });
    }
    let found: Vec<&(String, OutputPlacement)> = all.iter().filter(|(name, _)| name == output).collect();
    match found.as_slice() {
        [(_, p)] => Ok(p.clone()),
        [] => Err(invalid(
            "output",
            format!(
                "no active output `{output}` (outputs: {}; or screen:0..{})",
                if all.is_empty() {
                    "none".to_owned()
                } else {
                    all.iter().map(|(n, p)| format!("{n} on screen {}", p.screen)).collect::<Vec<_>>().join(", ")
                },
                roots.len().saturating_sub(1)
            ),
        )),
        many => Err(invalid("output", format!("`{output}` is on {} screens; use screen:N", many.len()))),
    }
}

/// The pixel layout of a ZPixmap image of `depth` on this server.
fn layout(
    conn: &RustConnection,
    screen: &xproto::Screen,
    width: u32,
    height: u32,
) -> Result<(FbLayout, bool), DeviceError> {
    let depth = screen.root_depth;
    let format = conn.setup().pixmap_formats.iter().find(|f| f.depth == depth).ok_or_else(|| {
        DeviceError::Unsupported { device: NAME.into(), operation: "a pixmap format for the root depth" }
    })?;
    let visual = screen
        .allowed_depths
        .iter()
        .flat_map(|d| d.visuals.iter())
        .find(|v| v.visual_id == screen.root_visual)
        .ok_or_else(|| DeviceError::Unsupported { device: NAME.into(), operation: "finding the root visual" })?;
    let channel = |mask: u32| Channel { offset: mask.trailing_zeros(), length: mask.count_ones().min(8) };
    let bpp = format.bits_per_pixel as u32;
    let pad = format.scanline_pad as u32;
    let row_bits = width * bpp;
    let line_length = row_bits.div_ceil(pad.max(8)) * pad.max(8) / 8;
    let l = FbLayout {
        width,
        height,
        line_length,
        bits_per_pixel: bpp,
        red: channel(visual.red_mask),
        green: channel(visual.green_mask),
        blue: channel(visual.blue_mask),
        origin: 0,
    };
    l.check().map_err(|e| DeviceError::Protocol { device: NAME.into(), detail: format!("X visual: {e}") })?;
    Ok((l, conn.setup().image_byte_order == ImageOrder::MSB_FIRST))
}

/// A borderless full-screen window on one X output.
#[derive(Debug)]
pub struct WindowProjector {
    conn: RustConnection,
    window: xproto::Window,
    pixmap: xproto::Pixmap,
    gc: xproto::Gcontext,
    depth: u8,
    layout: FbLayout,
    msb_first: bool,
    placement: OutputPlacement,
    present: bool,
    period: Duration,
    latency: Duration,
    serial: u32,
    /// (ust µs, msc) of the first and the last completed presentation.
    first_complete: Option<(u64, u64)>,
    last_complete: Option<(u64, u64)>,
    buffer: Vec<u8>,
}

impl WindowProjector {
    /// Connect to the display, find the output, and map a black full-screen window on it.
    pub fn open(config: &WindowProjectorConfig) -> Result<Self, DeviceError> {
        let (conn, _) = RustConnection::connect(config.display.as_deref()).map_err(|e| {
            lost(format!("cannot connect to X display {:?}: {e}", config.display.as_deref().unwrap_or("$DISPLAY")))
        })?;
        let placement = place(&conn, &config.output)?;
        if (placement.width as u32, placement.height as u32) != (config.width, config.height) {
            return Err(invalid(
                "width",
                format!(
                    "output `{}` is {}x{}, the rig file says {}x{}",
                    config.output, placement.width, placement.height, config.width, config.height
                ),
            ));
        }
        let screen = conn.setup().roots[placement.screen].clone();
        let (layout, msb_first) = layout(&conn, &screen, config.width, config.height)?;
        let window = conn.generate_id().map_err(id_error)?;
        conn.create_window(
            screen.root_depth,
            window,
            screen.root,
            placement.x,
            placement.y,
            placement.width,
            placement.height,
            0,
            WindowClass::INPUT_OUTPUT,
            screen.root_visual,
            &CreateWindowAux::new()
                .override_redirect(1)
                .background_pixel(screen.black_pixel)
                .event_mask(EventMask::STRUCTURE_NOTIFY),
        )
        .map_err(conn_error)?;
        conn.map_window(window).map_err(conn_error)?;
        conn.configure_window(window, &ConfigureWindowAux::new().stack_mode(StackMode::ABOVE)).map_err(conn_error)?;
        let gc = conn.generate_id().map_err(id_error)?;
        conn.create_gc(gc, window, &CreateGCAux::new().graphics_exposures(0)).map_err(conn_error)?;
        let pixmap = conn.generate_id().map_err(id_error)?;
        conn.create_pixmap(screen.root_depth, pixmap, window, placement.width, placement.height).map_err(conn_error)?;

        let present = config.vsync
            && conn.extension_information(present::X11_EXTENSION_NAME).map_err(conn_error)?.is_some()
            && conn.present_query_version(1, 2).map_err(conn_error)?.reply().is_ok();
        if present {
            let eid = conn.generate_id().map_err(id_error)?;
            conn.present_select_input(eid, window, present::EventMask::COMPLETE_NOTIFY).map_err(conn_error)?;
        }
        // The window is up once the server answered a round trip after the map.
        conn.get_input_focus().map_err(conn_error)?.reply().map_err(|e| reply_error("GetInputFocus", e))?;
        let period = placement.mode_period.unwrap_or_else(|| Duration::from_secs_f64(1.0 / config.refresh_hz));
        tracing::info!(output = %config.output, ?placement, present, ?period, "window projector mapped");
        Ok(WindowProjector {
            conn,
            window,
            pixmap,
            gc,
            depth: screen.root_depth,
            layout,
            msb_first,
            placement,
            present,
            period,
            latency: Duration::from_millis(config.latency_ms),
            serial: 0,
            first_complete: None,
            last_complete: None,
            buffer: Vec::new(),
        })
    }

    /// Where the window is.
    pub fn placement(&self) -> &OutputPlacement {
        &self.placement
    }

    /// The X window id (for reading it back).
    pub fn window(&self) -> u32 {
        self.window
    }

    /// True when patterns go through the Present extension at vertical blank.
    pub fn uses_present(&self) -> bool {
        self.present
    }

    /// The refresh period measured from the server's presentation notifications (time between the
    /// first and last completed presentation over the refreshes between them); `None` before two
    /// presentations on different refreshes.
    pub fn measured_refresh_period(&self) -> Option<Duration> {
        let ((u0, m0), (u1, m1)) = (self.first_complete?, self.last_complete?);
        (m1 > m0 && u1 > u0).then(|| Duration::from_micros((u1 - u0) / (m1 - m0)))
    }

    /// Draw `pattern` into `target` (the pixmap or the window), in row bands within the server's
    /// request size.
    fn put(&mut self, pattern: &Pattern, target: u32) -> Result<(), DeviceError> {
        self.layout.check_pattern(pattern).map_err(|e| invalid("width", e.to_string()))?;
        let line = self.layout.line_length as usize;
        let h = self.layout.height as usize;
        self.buffer.resize(line * h, 0);
        for y in 0..h {
            self.layout.pack_row(pattern, y as u32, &mut self.buffer[y * line..(y + 1) * line]);
        }
        if self.msb_first {
            let bpp = self.layout.bytes_per_pixel();
            for row in self.buffer.chunks_exact_mut(line) {
                for px in row[..self.layout.width as usize * bpp].chunks_exact_mut(bpp) {
                    px.reverse();
                }
            }
        }
        let max = self.conn.maximum_request_bytes().saturating_sub(64).max(line);
        let rows = (max / line).max(1);
        for y0 in (0..h).step_by(rows) {
            let n = rows.min(h - y0);
            self.conn
                .put_image(
                    ImageFormat::Z_PIXMAP,
                    target,
                    self.gc,
                    self.layout.width as u16,
                    n as u16,
                    0,
                    y0 as i16,
                    0,
                    self.depth,
                    &self.buffer[y0 * line..(y0 + n) * line],
                )
                .map_err(conn_error)?;
        }
        Ok(())
    }

    /// Wait for the next event until `deadline`.
    fn next_event(&self, deadline: Instant) -> Result<Option<Event>, DeviceError> {
        loop {
            if let Some(e) = self.conn.poll_for_event().map_err(conn_error)? {
                return Ok(Some(e));
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(None);
            }
            let mut fd = libc::pollfd { fd: self.conn.stream().as_raw_fd(), events: libc::POLLIN, revents: 0 };
            let ms = left.as_millis().clamp(1, i32::MAX as u128) as i32;
            // SAFETY: one valid pollfd for the duration of the call.
            let rc = unsafe { libc::poll(&mut fd, 1, ms) };
            if rc < 0 {
                let e = std::io::Error::last_os_error();
                if e.kind() != std::io::ErrorKind::Interrupted {
                    return Err(lost(format!("waiting for the X server: {e}")));
                }
            }
        }
    }

    fn check_window_event(&self, event: &Event) -> Result<(), DeviceError> {
        match event {
            Event::DestroyNotify(e) if e.window == self.window => {
                Err(lost("the projector window was destroyed".into()))
            }
            Event::UnmapNotify(e) if e.window == self.window => Err(lost("the projector window was unmapped".into())),
            Event::Error(e) => {
                Err(DeviceError::Protocol { device: NAME.into(), detail: format!("X error {:?}", e.error_kind) })
            }
            _ => Ok(()),
        }
    }

    /// The server's monotonic microseconds `ust` as an [`Instant`]; the receipt time `now` when the
    /// clock does not look like ours (a remote server).
    fn ust_instant(ust: u64, now: Instant) -> Instant {
        let mono = monotonic_now();
        let ust = Duration::from_micros(ust);
        if ust > mono || mono - ust > Duration::from_secs(10) {
            return now;
        }
        now.checked_sub(mono - ust).unwrap_or(now)
    }
}

impl super::Projector for WindowProjector {
    fn resolution(&self) -> (u32, u32) {
        (self.layout.width, self.layout.height)
    }

    fn show(&mut self, pattern: &Pattern, timeout: Duration) -> Result<Instant, DeviceError> {
        let start = Instant::now();
        let deadline = start + timeout;
        let at = if self.present {
            self.put(pattern, self.pixmap)?;
            self.serial = self.serial.wrapping_add(1);
            let serial = self.serial;
            self.conn
                .present_pixmap(
                    self.window,
                    self.pixmap,
                    serial,
                    x11rb::NONE,
                    x11rb::NONE,
                    0,
                    0,
                    x11rb::NONE,
                    x11rb::NONE,
                    x11rb::NONE,
                    PRESENT_OPTION_COPY,
                    0,
                    0,
                    0,
                    &[],
                )
                .map_err(conn_error)?;
            self.conn.flush().map_err(conn_error)?;
            loop {
                let Some(event) = self.next_event(deadline)? else {
                    return Err(DeviceError::Timeout {
                        device: NAME.into(),
                        waiting_for: "the pattern on screen",
                        timeout,
                    });
                };
                self.check_window_event(&event)?;
                if let Event::PresentCompleteNotify(c) = event {
                    if c.window == self.window && c.serial == serial {
                        let now = Instant::now();
                        self.first_complete.get_or_insert((c.ust, c.msc));
                        self.last_complete = Some((c.ust, c.msc));
                        break Self::ust_instant(c.ust, now) + self.latency;
                    }
                }
            }
        } else {
            self.put(pattern, self.window)?;
            self.conn.get_input_focus().map_err(conn_error)?.reply().map_err(|e| reply_error("GetInputFocus", e))?;
            while let Some(event) = self.conn.poll_for_event().map_err(conn_error)? {
                self.check_window_event(&event)?;
            }
            visible_at(Instant::now(), None, self.period, self.latency)
        };
        if at > deadline {
            return Err(DeviceError::Timeout { device: NAME.into(), waiting_for: "the pattern on screen", timeout });
        }
        let now = Instant::now();
        if at > now {
            std::thread::sleep(at - now);
        }
        Ok(at)
    }

    fn blank(&mut self, timeout: Duration) -> Result<(), DeviceError> {
        let black = Pattern::uniform(self.layout.width, self.layout.height, [0, 0, 0]);
        self.show(&black, timeout).map(|_| ())
    }
}

impl Drop for WindowProjector {
    fn drop(&mut self) {
        let _ = self.conn.free_pixmap(self.pixmap);
        let _ = self.conn.free_gc(self.gc);
        let _ = self.conn.destroy_window(self.window);
        let _ = self.conn.flush();
    }
}
