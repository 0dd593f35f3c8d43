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

use crate::virtual_rig::pacing::RealTime;
use crate::virtual_rig::timeline::Timeline;

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

/// USB vendor id of lightrig controllers (pid.codes open-source VID).
pub const USB_VID: u16 = 0x1209;
/// USB product id of lightrig controllers (to be registered with pid.codes before release).
pub const USB_PID: u16 = 0x4C52;
/// The vendor-class interface carrying the protocol, and its bulk endpoints.
pub const USB_INTERFACE: u8 = 0;
/// Bulk OUT endpoint (host to device).
pub const USB_EP_OUT: u8 = 0x01;
/// Bulk IN endpoint (device to host).
pub const USB_EP_IN: u8 = 0x81;

/// The vendor bulk interface of a controller, through nusb (no kernel driver needed).
pub struct UsbTransport {
    tx: nusb::io::EndpointWrite<nusb::transfer::Bulk>,
    rx: nusb::io::EndpointRead<nusb::transfer::Bulk>,
    name: String,
    epoch: Instant,
}

impl UsbTransport {
    /// Opens the first controller (or the one with `serial`) on the bus.
    pub fn open(serial: Option<&str>) -> io::Result<Self> {
        use nusb::transfer::{Bulk, In, Out};
        use nusb::MaybeFuture;
        let info = usb_devices()?
            .into_iter()
            .find(|d| serial.is_none_or(|s| d.serial_number() == Some(s)))
            .ok_or_else(|| {
                io::Error::new(
                    io::ErrorKind::NotFound,
                    format!(
                        "no lightrig controller on USB (VID {USB_VID:04x}, PID {USB_PID:04x}{}); is it plugged in and \
                         are the udev rules installed (docs/boards)?",
                        serial.map(|s| format!(", serial {s}")).unwrap_or_default()
                    ),
                )
            })?;
        let name = format!(
            "usb {}:{} ({})",
            info.bus_id(),
            info.device_address(),
            info.serial_number().unwrap_or("?")
        );
        let device = info.open().wait().map_err(io::Error::other)?;
        let interface = device.claim_interface(USB_INTERFACE).wait().map_err(io::Error::other)?;
        let tx = interface.endpoint::<Bulk, Out>(USB_EP_OUT).map_err(io::Error::other)?.writer(512);
        let rx = interface.endpoint::<Bulk, In>(USB_EP_IN).map_err(io::Error::other)?.reader(512);
        Ok(Self { tx, rx, name, epoch: Instant::now() })
    }
}

/// The lightrig controllers on the USB bus.
pub fn usb_devices() -> io::Result<Vec<nusb::DeviceInfo>> {
    use nusb::MaybeFuture;
    let all = nusb::list_devices().wait().map_err(io::Error::other)?;
    Ok(all.filter(|d| d.vendor_id() == USB_VID && d.product_id() == USB_PID).collect())
}

impl Transport for UsbTransport {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.tx.write_all(bytes)?;
        // Frames are latency-bound: end the transfer now rather than fill a packet.
        self.tx.flush_end()
    }

    fn recv(&mut self, buf: &mut [u8], deadline: u64) -> io::Result<usize> {
        let wait = Duration::from_micros(deadline.saturating_sub(self.now_us()).max(1));
        self.rx.set_read_timeout(wait);
        match self.rx.read(buf) {
            Ok(n) => Ok(n),
            Err(e) if e.kind() == io::ErrorKind::TimedOut => Ok(0),
            Err(e) => Err(e),
        }
    }

    fn now_us(&self) -> u64 {
        self.epoch.elapsed().as_micros() as u64
    }

    fn describe(&self) -> String {
        self.name.clone()
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
    impairment: Impairment,
    rng: u64,
    /// Unplugged: every call fails until [`VirtualTransport::replug`].
    unplugged: bool,
    /// Pull the cable when the clock reaches this tick.
    unplug_at: Option<u64>,
    /// Simulated time held to the wall clock ([`VirtualTransport::pace_in_real_time`]).
    real_time: Option<RealTime>,
    /// The board's changes handed on to the virtual camera ([`VirtualTransport::timeline`]).
    timeline: Option<Timeline>,
}

/// Byte-level damage on the virtual wire, per mille of bytes, each direction.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Impairment {
    /// Bytes lost.
    pub drop: u32,
    /// Bytes with one bit flipped.
    pub corrupt: u32,
    /// Bytes sent twice.
    pub duplicate: u32,
    /// Seed of the damage pattern.
    pub seed: u64,
}

fn splitmix(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

fn impair(bytes: &[u8], imp: &Impairment, rng: &mut u64) -> Vec<u8> {
    if imp.drop == 0 && imp.corrupt == 0 && imp.duplicate == 0 {
        return bytes.to_vec();
    }
    let mut out = Vec::with_capacity(bytes.len());
    for &b in bytes {
        let r = splitmix(rng);
        let roll = (r % 1000) as u32;
        if roll < imp.drop {
            continue;
        }
        let b = if roll < imp.drop + imp.corrupt { b ^ (1 << ((r >> 20) % 8)) } else { b };
        out.push(b);
        if roll >= imp.drop + imp.corrupt && roll < imp.drop + imp.corrupt + imp.duplicate {
            out.push(b);
        }
    }
    out
}

/// A boot id for a virtual device: different at every start, as on a real one.
pub(crate) fn fresh_boot_id() -> u32 {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u32(std::process::id());
    h.finish() as u32
}

impl VirtualTransport {
    /// A virtual device described by `info` (its `tick_hz` must be 1 MHz: host µs = ticks). A
    /// `boot_id` of 0 is replaced by a fresh one, as a real device's differs at every start.
    pub fn new(mut info: DeviceInfo, board: SimBoard) -> Self {
        if info.boot_id == 0 {
            info.boot_id = fresh_boot_id();
        }
        let clock = SimClock::default();
        let device = Controller::new(clock.clone(), board, info, 2_000);
        Self {
            clock,
            device,
            pending: Vec::new(),
            impairment: Impairment::default(),
            rng: 0,
            unplugged: false,
            unplug_at: None,
            real_time: None,
            timeline: None,
        }
    }

    /// The simulated board's output changes from now on, with their ticks, for the virtual
    /// camera to rebuild the rig's state at any tick of an exposure. The board hands its
    /// record over to it (and records steps too) from now on.
    pub fn timeline(&mut self) -> Timeline {
        if let Some(t) = &self.timeline {
            return t.clone();
        }
        let t = Timeline::default();
        t.attach(self.device.rig_mut().board_mut());
        self.timeline = Some(t.clone());
        t
    }

    /// From now on, simulated time moves no faster than the wall clock (as a real rig's
    /// would); by default it jumps to whatever is due next. See [`crate::virtual_rig::pacing`].
    pub fn pace_in_real_time(&mut self) {
        self.real_time = Some(RealTime::starting_at(self.clock.now()));
    }

    /// Damages bytes on the wire from now on.
    pub fn impair(&mut self, impairment: Impairment) {
        self.rng = impairment.seed;
        self.impairment = impairment;
    }

    /// Pulls the cable when simulated time reaches `tick`.
    pub fn unplug_at(&mut self, tick: u64) {
        self.unplug_at = Some(tick);
    }

    /// Plugs the cable back in. Bytes in flight were lost; the device kept running meanwhile.
    pub fn replug(&mut self) {
        self.unplugged = false;
        self.unplug_at = None;
        self.pending.clear();
    }

    fn check_plugged(&mut self) -> io::Result<()> {
        if self.unplug_at.is_some_and(|t| self.clock.now() >= t) {
            self.unplugged = true;
            self.unplug_at = None;
        }
        if self.unplugged {
            return Err(io::Error::new(io::ErrorKind::BrokenPipe, "device unplugged"));
        }
        Ok(())
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
        if let Some(t) = &self.timeline {
            t.take(self.device.rig_mut().board_mut(), self.clock.now());
        }
        while let Some(n) = self.device.poll_transmit(&mut out) {
            let bytes = impair(&out[..n], &self.impairment, &mut self.rng);
            self.pending.extend_from_slice(&bytes);
        }
    }
}

impl Transport for VirtualTransport {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.check_plugged()?;
        let bytes = impair(bytes, &self.impairment, &mut self.rng);
        self.device.receive(&bytes);
        Ok(())
    }

    fn recv(&mut self, buf: &mut [u8], deadline: u64) -> io::Result<usize> {
        loop {
            self.check_plugged()?;
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
            if let Some(rt) = &self.real_time {
                rt.wait_until(next);
            }
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

impl<T: Transport + ?Sized> Transport for Box<T> {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        (**self).send(bytes)
    }

    fn recv(&mut self, buf: &mut [u8], deadline: u64) -> io::Result<usize> {
        (**self).recv(buf, deadline)
    }

    fn now_us(&self) -> u64 {
        (**self).now_us()
    }

    fn describe(&self) -> String {
        (**self).describe()
    }
}

/// Where to find a device, as written on the command line or in a rig file:
/// `virtual`, `serial:/dev/ttyACM0`, `serial:/dev/ttyUSB0@115200`, `usb`, `usb:SERIAL`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Connect {
    /// The in-process virtual device.
    Virtual,
    /// A serial port at a baud rate.
    Serial { path: String, baud: u32 },
    /// A USB controller, optionally by serial number.
    Usb { serial: Option<String> },
}

impl std::str::FromStr for Connect {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let bad =
            || format!("`{s}`: expected `virtual`, `serial:PATH`, `serial:PATH@BAUD`, `usb` or `usb:SERIAL`");
        match s.split_once(':') {
            None if s == "virtual" => Ok(Connect::Virtual),
            None if s == "usb" => Ok(Connect::Usb { serial: None }),
            Some(("usb", serial)) if !serial.is_empty() => Ok(Connect::Usb { serial: Some(serial.into()) }),
            Some(("serial", rest)) if !rest.is_empty() => {
                let (path, baud) = match rest.rsplit_once('@') {
                    Some((p, b)) => {
                        (p, b.parse().map_err(|_| format!("{}: baud `{b}` is not a number", bad()))?)
                    }
                    None => (rest, 115_200),
                };
                Ok(Connect::Serial { path: path.into(), baud })
            }
            _ => Err(bad()),
        }
    }
}

/// The form [`Connect`] parses: `virtual`, `serial:PATH@BAUD`, `usb`, `usb:SERIAL`.
impl std::fmt::Display for Connect {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Connect::Virtual => f.write_str("virtual"),
            Connect::Serial { path, baud } => write!(f, "serial:{path}@{baud}"),
            Connect::Usb { serial: None } => f.write_str("usb"),
            Connect::Usb { serial: Some(s) } => write!(f, "usb:{s}"),
        }
    }
}

impl Connect {
    /// Opens the transport.
    pub fn open(&self) -> io::Result<Box<dyn Transport>> {
        Ok(match self {
            Connect::Virtual => Box::new(VirtualTransport::new(
                crate::selfcheck::virtual_device_info(),
                lightrig_firmware::sim::SimBoard::default(),
            )),
            Connect::Serial { path, baud } => Box::new(SerialTransport::open(path, *baud).map_err(|e| {
                io::Error::other(format!(
                    "serial {path}: {e}; check the path (`lightrig devices`) and permissions (dialout group)"
                ))
            })?),
            Connect::Usb { serial } => Box::new(UsbTransport::open(serial.as_deref())?),
        })
    }
}

/// A candidate device port.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct Candidate {
    /// How to connect to it.
    pub connect: String,
    /// What the system says it is.
    pub description: String,
}

/// Serial ports and USB controllers attached to this machine.
pub fn candidates() -> Vec<Candidate> {
    let mut out = Vec::new();
    for p in serialport::available_ports().unwrap_or_default() {
        let description = match &p.port_type {
            serialport::SerialPortType::UsbPort(u) => {
                format!("USB serial {:04x}:{:04x} {}", u.vid, u.pid, u.product.clone().unwrap_or_default())
            }
            other => format!("{other:?}"),
        };
        out.push(Candidate { connect: format!("serial:{}", p.port_name), description });
    }
    for d in usb_devices().unwrap_or_default() {
        let serial = d.serial_number().unwrap_or("").to_string();
        out.push(Candidate {
            connect: if serial.is_empty() { "usb".into() } else { format!("usb:{serial}") },
            description: format!("lightrig USB {} {}", d.bus_id(), d.product_string().unwrap_or("")),
        });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::Connect;

    #[test]
    fn connect_specs_parse_or_say_what_is_expected() {
        assert_eq!("virtual".parse(), Ok(Connect::Virtual));
        assert_eq!("usb".parse(), Ok(Connect::Usb { serial: None }));
        assert_eq!("usb:LR0042".parse(), Ok(Connect::Usb { serial: Some("LR0042".into()) }));
        assert_eq!(
            "serial:/dev/ttyACM0".parse(),
            Ok(Connect::Serial { path: "/dev/ttyACM0".into(), baud: 115_200 })
        );
        assert_eq!(
            "serial:/dev/ttyUSB1@921600".parse(),
            Ok(Connect::Serial { path: "/dev/ttyUSB1".into(), baud: 921_600 })
        );
        let e = "tcp:1.2.3.4".parse::<Connect>().unwrap_err();
        assert!(e.contains("expected `virtual`, `serial:PATH`"), "{e}");
        assert!("serial:/dev/x@fast".parse::<Connect>().unwrap_err().contains("baud `fast`"));
    }

    #[test]
    fn connect_specs_print_as_they_parse() {
        for s in ["virtual", "usb", "usb:LR0042", "serial:/dev/ttyUSB1@921600"] {
            assert_eq!(s.parse::<Connect>().unwrap().to_string(), s);
        }
        assert_eq!(
            "serial:/dev/ttyACM0".parse::<Connect>().unwrap().to_string(),
            "serial:/dev/ttyACM0@115200"
        );
    }
}
