//! The in-process virtual device: the firmware controller on a simulated board, under
//! simulated time the host and the device share, behind the host's [`Transport`] trait.

use std::fmt;
use std::io;

use lightrig_firmware::sim::{virtual_device_info, SimBoard, SimClock};
use lightrig_firmware::{Clock, Controller};
use lightrig_host::rigfile::RigFile;
use lightrig_host::transport::{Connect, Transport};
use lightrig_protocol::session::{DeviceInfo, ResetCause};
use lightrig_protocol::MAX_FRAME;

use crate::board::board_for;
use crate::pacing::RealTime;
use crate::timeline::Timeline;

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
    damage: Damage,
    /// Unplugged: every call fails until [`VirtualTransport::replug`].
    unplugged: bool,
    /// Pull the cable when the clock reaches this tick.
    unplug_at: Option<u64>,
    /// Reset the device (a new boot, the cable still in) when the clock reaches this tick.
    reset_at: Option<u64>,
    /// Simulated time held to the wall clock ([`VirtualTransport::pace_in_real_time`]).
    real_time: Option<RealTime>,
    /// The board's changes handed on to the virtual camera ([`VirtualTransport::timeline`]).
    timeline: Option<Timeline>,
    /// Bytes handed to the device as if they came over the wire, when simulated time reaches
    /// their tick ([`VirtualTransport::inject_at`]), earliest first.
    injected: Vec<(u64, Vec<u8>)>,
}

/// Byte-level damage on the virtual wire, per million bytes, each direction.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Impairment {
    /// Bytes lost, per million.
    pub drop_ppm: u32,
    /// Bytes with one bit flipped, per million.
    pub corrupt_ppm: u32,
    /// Bytes sent twice, per million.
    pub duplicate_ppm: u32,
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

/// What the virtual wire did to the bytes it carried, both directions together.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Damage {
    /// Bytes carried.
    pub bytes: u64,
    /// Bytes lost.
    pub dropped: u64,
    /// Bytes with a bit flipped.
    pub flipped: u64,
    /// Bytes sent twice.
    pub duplicated: u64,
}

fn impair(bytes: &[u8], imp: &Impairment, rng: &mut u64, damage: &mut Damage) -> Vec<u8> {
    damage.bytes += bytes.len() as u64;
    let (drop, corrupt, duplicate) = (imp.drop_ppm, imp.corrupt_ppm, imp.duplicate_ppm);
    if drop == 0 && corrupt == 0 && duplicate == 0 {
        return bytes.to_vec();
    }
    let mut out = Vec::with_capacity(bytes.len());
    for &b in bytes {
        let r = splitmix(rng);
        let roll = (r % 1_000_000) as u32;
        if roll < drop {
            damage.dropped += 1;
            continue;
        }
        let b = if roll < drop + corrupt {
            damage.flipped += 1;
            b ^ (1 << ((r >> 40) % 8))
        } else {
            b
        };
        out.push(b);
        if roll >= drop + corrupt && roll < drop + corrupt + duplicate {
            damage.duplicated += 1;
            out.push(b);
        }
    }
    out
}

/// A board without flash slots gets them as it left the factory (its firmware in the active
/// slot); `info` says the version the active slot holds.
pub fn from_factory(info: &mut DeviceInfo, board: &mut SimBoard) {
    let slots = board.slots.get_or_insert_with(|| crate::flash::factory(info.firmware));
    if let Some(running) = crate::flash::running(slots) {
        info.firmware = running.version;
    }
}

/// The device after a reset of the MCU for `cause`: a new boot with a new boot id and nothing
/// configured, on the same physical board (the axes stay where they are, the laser pins go
/// low as an MCU's outputs do); the bootloader runs first, swapping a marked image in or an
/// unconfirmed one back, and the version is the one the active slot then holds.
pub fn reset(
    device: &mut Controller<SimClock, SimBoard>,
    clock: SimClock,
    cause: ResetCause,
) -> Controller<SimClock, SimBoard> {
    let mut info = *device.info();
    info.boot_id = fresh_boot_id().max(info.boot_id.wrapping_add(1)).max(1);
    info.reset_cause = cause;
    let mut board = std::mem::take(device.rig_mut().board_mut());
    board.lasers = Default::default();
    if let Some(slots) = board.slots.as_mut() {
        if slots.0.boot().is_ok() {
            if let Some(running) = crate::flash::running(slots) {
                info.firmware = running.version;
            }
        }
    }
    Controller::new(clock, board, info, 2_000)
}

/// A boot id for a virtual device: different at every start, as on a real one.
pub fn fresh_boot_id() -> u32 {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u32(std::process::id());
    h.finish() as u32
}

impl VirtualTransport {
    /// A virtual device described by `info` (its `tick_hz` must be 1 MHz: host µs = ticks). A
    /// `boot_id` of 0 is replaced by a fresh one, as a real device's differs at every start.
    pub fn new(mut info: DeviceInfo, mut board: SimBoard) -> Self {
        if info.boot_id == 0 {
            info.boot_id = fresh_boot_id();
        }
        from_factory(&mut info, &mut board);
        let clock = SimClock::default();
        let device = Controller::new(clock.clone(), board, info, 2_000);
        Self {
            clock,
            device,
            pending: Vec::new(),
            impairment: Impairment::default(),
            rng: 0,
            damage: Damage::default(),
            unplugged: false,
            unplug_at: None,
            reset_at: None,
            real_time: None,
            timeline: None,
            injected: Vec::new(),
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
    /// would); by default it jumps to whatever is due next. See [`crate::pacing`].
    pub fn pace_in_real_time(&mut self) {
        self.real_time = Some(RealTime::starting_at(self.clock.now()));
    }

    /// What the wire has done to the bytes so far.
    pub fn damage(&self) -> Damage {
        self.damage
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

    /// Resets the device when simulated time reaches `tick`, the link left open (a watchdog
    /// or a brown-out on a board whose USB-serial bridge stays powered, a UART, QEMU): a new
    /// boot with a new boot id and nothing configured, on the same physical board.
    pub fn reset_at(&mut self, tick: u64) {
        self.reset_at = Some(tick);
    }

    /// Hands `bytes` to the device, as if they came over the wire, when simulated time reaches
    /// `tick`: frames of another sender (a stale copy of an earlier host run's `Sync` on a
    /// reordering wire, a stray datagram) in the middle of whatever the host is doing.
    pub fn inject_at(&mut self, tick: u64, bytes: &[u8]) {
        let at = self.injected.partition_point(|(t, _)| *t <= tick);
        self.injected.insert(at, (tick, bytes.to_vec()));
    }

    fn check_injected(&mut self) {
        while self.injected.first().is_some_and(|(t, _)| self.clock.now() >= *t) {
            let (_, bytes) = self.injected.remove(0);
            self.device.receive(&bytes);
        }
    }

    fn check_reset(&mut self) {
        let cause = if self.device.wants_reset() {
            // The firmware asked (an update to swap in, or one never confirmed).
            ResetCause::Software
        } else if self.reset_at.is_some_and(|t| self.clock.now() >= t) {
            self.reset_at = None;
            ResetCause::Watchdog
        } else {
            return;
        };
        self.device = reset(&mut self.device, self.clock.clone(), cause);
        if let Some(t) = &self.timeline {
            t.attach(self.device.rig_mut().board_mut());
        }
        self.pending.clear();
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
        self.check_reset();
        self.check_injected();
        let mut out = [0u8; MAX_FRAME];
        self.device.poll();
        if let Some(t) = &self.timeline {
            t.take(self.device.rig_mut().board_mut(), self.clock.now());
        }
        while let Some(n) = self.device.poll_transmit(&mut out) {
            let bytes = impair(&out[..n], &self.impairment, &mut self.rng, &mut self.damage);
            self.pending.extend_from_slice(&bytes);
        }
    }
}

impl Transport for VirtualTransport {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.check_plugged()?;
        let bytes = impair(bytes, &self.impairment, &mut self.rng, &mut self.damage);
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
            let next = self.injected.first().map_or(next, |(t, _)| next.min((*t).max(now + 1)));
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

    fn runs_alone(&self) -> bool {
        // Simulated time stands still while the host does other work.
        false
    }
}

impl fmt::Debug for VirtualTransport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("VirtualTransport").field("now", &self.clock.now()).finish()
    }
}

/// The virtual device for a rig file, in this process.
pub fn connect(rig: &RigFile, info: DeviceInfo) -> VirtualTransport {
    VirtualTransport::new(info, board_for(rig))
}

/// [`connect`] for a virtual acquisition: paced in real time if `real_time`, and with the
/// board's [`Timeline`] for the camera to
/// [`follow`](crate::camera::VirtualCamera::follow), so each frame sees the rig over its whole
/// exposure.
pub fn connect_for_camera(rig: &RigFile, info: DeviceInfo, real_time: bool) -> (VirtualTransport, Timeline) {
    let mut transport = connect(rig, info);
    if real_time {
        transport.pace_in_real_time();
    }
    let timeline = transport.timeline();
    (transport, timeline)
}

/// Opens what `spec` names: the virtual device (a bare simulated board) in this process, or a
/// real one through [`Connect::open`].
pub fn open(spec: &Connect) -> io::Result<Box<dyn Transport>> {
    match spec {
        Connect::Virtual => Ok(Box::new(VirtualTransport::new(virtual_device_info(), SimBoard::default()))),
        _ => spec.open(),
    }
}
