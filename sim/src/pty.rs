//! `lightrig sim --pty`: the virtual rig's controller behind a pseudo-terminal, so any serial
//! client (the host CLI in another process, a lab's own Python script) reaches it exactly as it
//! would a board's USB serial port.
//!
//! The controller is the firmware core on the simulated board [`crate::board::board_for`] builds from
//! the rig file. Its clock is paced in real time ([`crate::pacing`]): a client in another
//! process keeps its own clock, maps the device's onto it by regression, and feeds the
//! heartbeat watchdog by the wall clock, so simulated time cannot run ahead of it here. It is
//! still exact: every deadline is polled at its own tick, however late this process wakes.

use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

use lightrig_firmware::sim::{SimBoard, SimClock};
use lightrig_firmware::{Clock, Controller};
use lightrig_protocol::session::DeviceInfo;
use lightrig_protocol::MAX_FRAME;
use serialport::{SerialPort, TTYPort};

use crate::pacing::RealTime;

/// Longest wait for input when nothing is due: bounds how long a stop request goes unseen.
const IDLE_WAIT: Duration = Duration::from_millis(20);

/// The virtual controller on a pseudo-terminal.
pub struct PtyRig {
    master: TTYPort,
    /// Held open so that the master side keeps working while no client has the port open
    /// (Linux reports EIO on the master once the last slave descriptor closes).
    _slave: TTYPort,
    path: PathBuf,
    clock: SimClock,
    device: Controller<SimClock, SimBoard>,
    real_time: RealTime,
    /// Bytes received from clients.
    pub bytes_in: u64,
    /// Bytes the device sent.
    pub bytes_out: u64,
    /// Bytes the device sent while nobody read them.
    pub dropped: u64,
}

impl PtyRig {
    /// Opens a new pseudo-terminal and puts a controller described by `info` on `board`
    /// behind it.
    /// A `boot_id` of 0 is replaced by a fresh one, as a real device's differs at every start.
    pub fn open(mut info: DeviceInfo, mut board: SimBoard) -> io::Result<Self> {
        if info.boot_id == 0 {
            info.boot_id = crate::transport::fresh_boot_id();
        }
        crate::transport::from_factory(&mut info, &mut board);
        let (master, slave) = TTYPort::pair().map_err(io::Error::other)?;
        let path = slave
            .name()
            .map(PathBuf::from)
            .ok_or_else(|| io::Error::other("the pseudo-terminal has no name"))?;
        let clock = SimClock::default();
        let device = Controller::new(clock.clone(), board, info, 2_000);
        let real_time = RealTime::starting_at(clock.now());
        Ok(Self {
            master,
            _slave: slave,
            path,
            clock,
            device,
            real_time,
            bytes_in: 0,
            bytes_out: 0,
            dropped: 0,
        })
    }

    /// The port a client opens (`/dev/pts/N`).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The controller, for inspection.
    pub fn device(&self) -> &Controller<SimClock, SimBoard> {
        &self.device
    }

    /// Serves the port until `stop` says so (checked at least every 20 ms).
    pub fn serve(&mut self, mut stop: impl FnMut() -> bool) -> io::Result<()> {
        let mut buf = [0u8; 4096];
        while !stop() {
            self.catch_up()?;
            let wait = self
                .device
                .next_deadline()
                .map_or(IDLE_WAIT, |d| self.real_time.until(d).min(IDLE_WAIT))
                .max(Duration::from_micros(1));
            self.master.set_timeout(wait).map_err(io::Error::other)?;
            match self.master.read(&mut buf) {
                Ok(n) => {
                    // Whatever fell due while we waited happens before these bytes arrive.
                    self.catch_up()?;
                    self.bytes_in += n as u64;
                    self.device.receive(&buf[..n]);
                }
                Err(e) if e.kind() == io::ErrorKind::TimedOut => {}
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }

    /// Runs every deadline the wall clock has passed, each at its own tick, then brings the
    /// device's clock up to the wall clock and sends what the device has to say.
    fn catch_up(&mut self) -> io::Result<()> {
        let wall = self.real_time.now();
        // Bounded: a deadline the poll did not consume must not spin us forever.
        for _ in 0..100_000 {
            match self.device.next_deadline() {
                Some(d) if d <= wall && d >= self.clock.now() => {
                    self.clock.set(d);
                    self.device.poll();
                    self.flush()?;
                    if self.device.next_deadline() == Some(d) {
                        break;
                    }
                }
                _ => break,
            }
        }
        self.clock.set(wall);
        self.device.poll();
        self.flush()?;
        if self.device.wants_reset() {
            // The firmware asked (an update to swap in, or one never confirmed): the port
            // stays, as a USB-serial bridge's does while its MCU resets.
            let cause = lightrig_protocol::session::ResetCause::Software;
            self.device = crate::transport::reset(&mut self.device, self.clock.clone(), cause);
        }
        Ok(())
    }

    /// Sends the device's frames. With no client reading, the terminal's buffer fills and
    /// the rest is dropped, as a UART's output with nobody listening is; the link's
    /// retransmission and resynchronisation take care of it when a client comes.
    fn flush(&mut self) -> io::Result<()> {
        let mut out = [0u8; MAX_FRAME];
        self.master.set_timeout(Duration::from_millis(1)).map_err(io::Error::other)?;
        while let Some(n) = self.device.poll_transmit(&mut out) {
            match self.master.write_all(&out[..n]) {
                Ok(()) => self.bytes_out += n as u64,
                Err(e) if e.kind() == io::ErrorKind::TimedOut => self.dropped += n as u64,
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }
}
