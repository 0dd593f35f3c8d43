//! `lightrig selfcheck`: the host's link against the real firmware controller, in-process,
//! over a simulated wire that drops and damages frames, under simulated time.
//!
//! It proves the build's two halves agree: framing, the reliable link both ways, the
//! handshake and schema check, request/response pairing and typed configuration errors.

use std::collections::VecDeque;

use anyhow::{bail, ensure, Context, Result};
use lightrig_firmware::sim::{virtual_device_info, SimBoard, SimClock};
use lightrig_firmware::{Clock, Controller};
use lightrig_protocol::config::{ConfigField, ConfigItem, Input, InvalidReason, LaserConfig, Polarity};
use lightrig_protocol::link::{Delivery, Link, LinkConfig, LinkStats, Role};
use lightrig_protocol::session::DeviceInfo;
use lightrig_protocol::{
    Command, DeviceMsg, Error, HostMsg, Reply, MAX_FRAME, PROTOCOL_VERSION, SCHEMA_HASH,
};

/// How the self-check is run.
#[derive(Debug, Clone, Copy)]
pub struct Options {
    /// Clock requests to exchange.
    pub requests: u32,
    /// Per-mille of frames dropped on the wire, each direction.
    pub drop_per_mille: u32,
    /// Per-mille of frames with a damaged byte.
    pub corrupt_per_mille: u32,
    /// Seed of the wire's fault pattern.
    pub seed: u64,
}

/// What the self-check measured.
#[derive(Debug, Clone)]
pub struct Report {
    /// The device's answer to Hello.
    pub device: DeviceInfo,
    /// Requests answered.
    pub answered: u32,
    /// Simulated device ticks the exchange took.
    pub ticks: u64,
    /// Host link counters.
    pub host_link: LinkStats,
    /// Device link counters.
    pub device_link: LinkStats,
}

struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn chance(&mut self, per_mille: u32) -> bool {
        self.next() % 1000 < u64::from(per_mille)
    }
}

/// Host link, device controller and the wire between them.
struct Bench {
    clock: SimClock,
    host: Link<HostMsg, DeviceMsg, 8>,
    device: Controller<SimClock, SimBoard>,
    to_device: VecDeque<Vec<u8>>,
    to_host: VecDeque<Vec<u8>>,
    rng: Rng,
    opts: Options,
    next_id: u16,
}

/// One simulated tick is 1 µs; frames cross the wire within a tick.
const RTO_TICKS: u64 = 2_000;
const STEP_LIMIT: u64 = 50_000_000;

impl Bench {
    fn new(opts: Options) -> Self {
        let clock = SimClock::default();
        let device = Controller::new(clock.clone(), SimBoard::default(), virtual_device_info(), RTO_TICKS);
        let host =
            Link::new(Role::Initiator, LinkConfig { rto: RTO_TICKS, rx_reserve: 0, nonce: opts.seed as u32 });
        Self {
            clock,
            host,
            device,
            to_device: VecDeque::new(),
            to_host: VecDeque::new(),
            rng: Rng(opts.seed),
            opts,
            next_id: 0,
        }
    }

    fn impair(&mut self, mut frame: Vec<u8>) -> Option<Vec<u8>> {
        if self.rng.chance(self.opts.drop_per_mille) {
            return None;
        }
        if self.rng.chance(self.opts.corrupt_per_mille) {
            let i = (self.rng.next() as usize) % frame.len();
            frame[i] ^= 1 << (self.rng.next() % 8);
        }
        Some(frame)
    }

    /// Moves frames both ways once; returns what the host received.
    fn step(&mut self) -> Vec<Delivery<DeviceMsg>> {
        let now = self.clock.now();
        let mut out = [0u8; MAX_FRAME];
        while let Some(n) = self.host.poll_transmit(now, &mut out) {
            if let Some(f) = self.impair(out[..n].to_vec()) {
                self.to_device.push_back(f);
            }
        }
        while let Some(f) = self.to_device.pop_front() {
            self.device.receive(&f);
        }
        self.device.poll();
        while let Some(n) = self.device.poll_transmit(&mut out) {
            if let Some(f) = self.impair(out[..n].to_vec()) {
                self.to_host.push_back(f);
            }
        }
        let mut got = Vec::new();
        while let Some(f) = self.to_host.pop_front() {
            self.host.receive_all(&f, now, |d| got.push(d));
        }
        self.clock.advance(1);
        got
    }

    /// Sends one request and runs the wire until its answer arrives.
    fn request(&mut self, command: Command) -> Result<Result<Reply, Error>> {
        self.next_id = self.next_id.wrapping_add(1);
        let id = self.next_id;
        self.host.send(HostMsg { id, command }).map_err(|_| anyhow::anyhow!("host link window full"))?;
        let start = self.clock.now();
        while self.clock.now() - start < STEP_LIMIT {
            for d in self.step() {
                match d {
                    Delivery::Message(DeviceMsg::Response { id: got, result }) => {
                        ensure!(got == id, "response id {got} does not match request {id}");
                        return Ok(result);
                    }
                    Delivery::Message(other) => bail!("unexpected message from the device: {other:?}"),
                    Delivery::Connected { .. } => {}
                    other => bail!("unexpected delivery: {other:?}"),
                }
            }
        }
        bail!("no answer to request {id} within {STEP_LIMIT} ticks")
    }
}

/// Runs the self-check.
pub fn run(opts: Options) -> Result<Report> {
    let mut b = Bench::new(opts);
    b.host.connect(0);

    // Before Hello, the device refuses everything else.
    let early = b.request(Command::GetClock).context("request before the handshake")?;
    ensure!(early == Err(Error::HandshakeRequired), "expected HandshakeRequired before Hello, got {early:?}");

    // A Hello with the wrong schema: the device describes itself, then refuses to work,
    // naming both hashes.
    let wrong = SCHEMA_HASH ^ 1;
    let r = b.request(Command::Hello { protocol_version: PROTOCOL_VERSION, schema_hash: wrong })?;
    ensure!(matches!(r, Ok(Reply::Hello(ref i)) if i.schema_hash == SCHEMA_HASH), "Hello answer: {r:?}");
    let r = b.request(Command::GetClock)?;
    ensure!(
        r == Err(Error::SchemaMismatch { device: SCHEMA_HASH, host: wrong }),
        "expected SchemaMismatch, got {r:?}"
    );

    let device =
        match b.request(Command::Hello { protocol_version: PROTOCOL_VERSION, schema_hash: SCHEMA_HASH })? {
            Ok(Reply::Hello(info)) => info,
            other => bail!("handshake failed: {other:?}"),
        };
    ensure!(device.schema_hash == SCHEMA_HASH && device.protocol_version == PROTOCOL_VERSION);

    // Clock requests: every one answered, in order, with a tick that never goes back.
    let start = b.clock.now();
    let mut last_tick = 0;
    for i in 0..opts.requests {
        match b.request(Command::GetClock)? {
            Ok(Reply::Clock { tick }) => {
                ensure!(tick >= last_tick, "device clock went back at request {i}: {tick} < {last_tick}");
                last_tick = tick;
            }
            other => bail!("clock request {i}: {other:?}"),
        }
    }
    let ticks = b.clock.now() - start;

    // A configuration the device must refuse, naming the field.
    let bad = LaserConfig {
        channel: 0,
        wavelength_nm: 635,
        warmup_ticks: 0,
        max_on_ticks: 0,
        enable: Polarity::ActiveHigh,
        interlock: Input::Unused,
    };
    match b.request(Command::Configure(ConfigItem::Laser(bad)))? {
        Err(Error::InvalidConfig(e))
            if e.field == ConfigField::LaserMaxOnTicks && e.reason == InvalidReason::Zero => {}
        other => bail!("expected laser.max_on_ticks to be refused, got {other:?}"),
    }

    Ok(Report {
        device,
        answered: opts.requests,
        ticks,
        host_link: *b.host.stats(),
        device_link: *b.device.link().stats(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clean_wire_needs_no_retransmission() {
        let r = run(Options { requests: 100, drop_per_mille: 0, corrupt_per_mille: 0, seed: 1 }).unwrap();
        assert_eq!(r.answered, 100);
        assert_eq!((r.host_link.retransmits, r.device_link.retransmits), (0, 0));
        assert_eq!(r.host_link.rejected() + r.device_link.rejected(), 0);
    }

    #[test]
    fn lossy_wire_is_survived_and_counted() {
        let r = run(Options { requests: 300, drop_per_mille: 100, corrupt_per_mille: 50, seed: 7 }).unwrap();
        assert_eq!(r.answered, 300);
        assert!(r.host_link.retransmits + r.device_link.retransmits > 0);
        assert!(r.host_link.bad_crc + r.device_link.bad_crc > 0);
    }
}
