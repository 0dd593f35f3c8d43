//! Byte transports between the host and a rig controller, each with the clock the link runs
//! on: the wall clock for hardware, simulated time for the in-process virtual device.
//!
//! A transport carries frames as bytes; framing, retransmission and ordering are the link's
//! job ([`lightrig_protocol::link`]), so a transport may lose or damage bytes.

use std::fmt;
use std::io::{self, Read, Write};
use std::time::{Duration, Instant};

use lightrig_firmware::sim::{SimBoard, SimClock};
use lightrig_firmware::{Clock, Controller};
use lightrig_protocol::session::DeviceInfo;
use lightrig_protocol::MAX_FRAME;

/// Bytes to and from a device.
pub trait Transport {
    /// Sends `bytes`.
    fn send(&mut self, bytes: &[u8]) -> io::Result<()>;

    /// Waits until bytes arrive or the clock reaches `deadline` (µs), whichever is first, and
    /// returns how many were put in `buf` (0 at the deadline).
    fn recv(&mut self, buf: &mut [u8], deadline: u64) -> io::Result<usize>;

    /// The transport's clock, µs.
    fn now_us(&self) -> u64;

    /// Where the device is, for messages ("serial /dev/ttyACM0", "virtual rig").
    fn describe(&self) -> String;
}

/// A serial port: CDC-ACM over USB, or a UART.
pub struct SerialTransport {
    port: Box<dyn serialport::SerialPort>,
    path: String,
    epoch: Instant,
}

impl SerialTransport {
    /// Opens `path` at `baud` (ignored by CDC-ACM).
    pub fn open(path: &str, baud: u32) -> Result<Self, serialport::Error> {
        let port = serialport::new(path, baud).timeout(Duration::from_millis(10)).open()?;
        Ok(Self { port, path: path.to_string(), epoch: Instant::now() })
    }
}

impl Transport for SerialTransport {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.port.write_all(bytes)
    }

    fn recv(&mut self, buf: &mut [u8], deadline: u64) -> io::Result<usize> {
        let now = self.now_us();
        let wait = Duration::from_micros(deadline.saturating_sub(now).max(1));
        self.port.set_timeout(wait).map_err(io::Error::other)?;
        match self.port.read(buf) {
            Ok(n) => Ok(n),
            Err(e) if e.kind() == io::ErrorKind::TimedOut => Ok(0),
            Err(e) => Err(e),
        }
    }

    fn now_us(&self) -> u64 {
        self.epoch.elapsed().as_micros() as u64
    }

    fn describe(&self) -> String {
        format!("serial {}", self.path)
    }
}

/// The firmware controller in this process on a simulated board, under simulated time that the
/// host and the device share (1 tick = 1 µs). `recv` moves time forward to the device's next
/// deadline or the host's, so a run is fast and exactly repeatable.
pub struct VirtualTransport {
    clock: SimClock,
    device: Controller<SimClock, SimBoard>,
    /// Device frames not yet handed to the host.
    pending: Vec<u8>,
}

impl VirtualTransport {
    /// A virtual device described by `info` (its `tick_hz` must be 1 MHz: host µs = ticks).
    pub fn new(info: DeviceInfo, board: SimBoard) -> Self {
        let clock = SimClock::default();
        let device = Controller::new(clock.clone(), board, info, 2_000);
        Self { clock, device, pending: Vec::new() }
    }

    /// The device, for inspection (its simulated board's record).
    pub fn device(&self) -> &Controller<SimClock, SimBoard> {
        &self.device
    }

    /// The device, mutably (to change simulated inputs).
    pub fn device_mut(&mut self) -> &mut Controller<SimClock, SimBoard> {
        &mut self.device
    }

    fn collect(&mut self) {
        let mut out = [0u8; MAX_FRAME];
        self.device.poll();
        while let Some(n) = self.device.poll_transmit(&mut out) {
            self.pending.extend_from_slice(&out[..n]);
        }
    }
}

impl Transport for VirtualTransport {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.device.receive(bytes);
        Ok(())
    }

    fn recv(&mut self, buf: &mut [u8], deadline: u64) -> io::Result<usize> {
        loop {
            self.collect();
            if !self.pending.is_empty() {
                let n = self.pending.len().min(buf.len());
                buf[..n].copy_from_slice(&self.pending[..n]);
                self.pending.drain(..n);
                return Ok(n);
            }
            let now = self.clock.now();
            if now >= deadline {
                return Ok(0);
            }
            // Jump to whatever comes first: the device's next work or the host's deadline.
            let next = self.device.next_deadline().map_or(deadline, |d| d.max(now + 1).min(deadline));
            self.clock.set(next);
        }
    }

    fn now_us(&self) -> u64 {
        self.clock.now()
    }

    fn describe(&self) -> String {
        "virtual rig (in-process)".to_string()
    }
}

impl fmt::Debug for VirtualTransport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("VirtualTransport").field("now", &self.clock.now()).finish()
    }
}
