//! The conformance suite: the host's real client over a real transport against a device
//! running the real firmware. Every check is exact (ticks, counters, error values). Pin-level
//! checks need the emulated board's recorder and are skipped on a real board.

use std::time::{Duration, Instant};

use lightrig_firmware::record::Output;
use lightrig_host::client::{Client, ClientError, EventRecord};
use lightrig_host::transport::Transport;
use lightrig_protocol::config::*;
use lightrig_protocol::event::{DeviceState, FaultCause};
use lightrig_protocol::frame::{FrameDecoder, FrameError};
use lightrig_protocol::link::{FrameKind, Header, LinkStats, SyncAckBody};
use lightrig_protocol::message::Status;
use lightrig_protocol::sequence::{Action, Chunk, Item, StartAt};
use lightrig_protocol::session::DeviceInfo;
use lightrig_protocol::{
    Command, ConfigError, ConfigField, DeviceMsg, Error, Event, HostMsg, InvalidReason, Reply,
    MAX_CHUNK_ITEMS, MAX_FRAME, MAX_PACKET, PROTOCOL_VERSION, SCHEMA_HASH,
};

use crate::debug::{only, DebugPort};

type Dyn = Box<dyn Transport>;
/// A check's outcome: `Err` says what differed.
pub type Check = Result<(), String>;

/// The device under test.
pub struct Target {
    /// Opens a fresh transport to the device.
    pub open: Box<dyn Fn() -> Result<Dyn, String>>,
    /// The emulated board's recorder, if there is one.
    pub debug: Option<DebugPort>,
    /// The boot id the device must report (the emulated board gets it from the harness).
    pub boot_id: Option<u32>,
    /// Still alive (the emulated board's QEMU has not exited)?
    pub alive: Box<dyn FnMut() -> bool>,
}

/// The suite's state between tests.
pub struct Suite {
    target: Target,
    client: Option<Client<Dyn>>,
    info: Option<DeviceInfo>,
    /// Every event index seen, to check that none is lost or repeated.
    last_index: Option<u32>,
    /// The longest the host has been seen to take, in device ticks, from the clock reading a
    /// start tick is fixed from to the device's processing of `SequenceStart` (the loading
    /// between them). Leads are at least twice this: see [`lead_for`].
    load_ticks: u64,
    /// Starts refused `StartInPast` and made again later, since the suite began (not counting
    /// the one `slow_host_start_is_moved_later` forces).
    restarts: u32,
    /// A pause before each chunk loaded ahead of a start: a slow host, simulated
    /// (`LIGHTRIG_HIL_LOAD_DELAY_MS`, and the `slow_host_start_is_moved_later` test).
    load_delay: Duration,
}

/// Sets [`Suite::load_delay`] for the whole suite: a pause of this many milliseconds before
/// each chunk that is loaded before a sequence starts, as on a slow or busy host.
pub const LOAD_DELAY_ENV: &str = "LIGHTRIG_HIL_LOAD_DELAY_MS";

/// Attempts at starting one sequence: the first at the test's lead (or twice the loading seen
/// so far), each later one at twice the loading the refused one measured.
const START_ATTEMPTS: u32 = 3;

/// The lead (ticks from the clock reading to the start) for a sequence: the test's own `base`,
/// or twice the longest loading seen, `load` (a busy host's next loading may well take longer
/// than its last), whichever is longer. On a quiet host the base is longer and the ticks are
/// the ones the test always used.
fn lead_for(base: u64, load: u64) -> u64 {
    base.max(load.saturating_mul(2))
}

/// `items`, calling `pause` before each chunk's first item among the first `ahead` (those the
/// host loads before it starts the sequence): the host's client takes a chunk's items from the
/// iterator just before it loads the chunk.
fn paced<I: Iterator<Item = Item>>(
    items: I,
    ahead: usize,
    mut pause: impl FnMut(usize),
) -> impl Iterator<Item = Item> {
    items.enumerate().map(move |(k, item)| {
        if k < ahead && k % MAX_CHUNK_ITEMS == 0 {
            pause(k);
        }
        item
    })
}

fn nonce() -> u32 {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u128(
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos()),
    );
    h.finish() as u32
}

fn err(e: ClientError) -> String {
    e.to_string()
}

macro_rules! ensure_eq {
    ($a:expr, $b:expr $(,)?) => {{
        let (a, b) = (&$a, &$b);
        if a != b {
            return Err(format!(
                "{}: expected {:?}, got {:?} ({}:{})",
                stringify!($a),
                b,
                a,
                file!(),
                line!()
            ));
        }
    }};
}

macro_rules! ensure {
    ($c:expr, $($msg:tt)+) => {{
        if !$c {
            return Err(format!($($msg)+));
        }
    }};
}

/// Ticks between markers in the streaming test, and between triggers in the long run: event
/// rates (200/s) that the emulated UART sustains when the host machine is busy. QEMU feeds the
/// UART one byte per turn of its main loop, and the device moves an event into its link only
/// as acknowledgements free the window, so a host slow to answer lets the device's 64-event
/// queue fill (`EventOverflow`): at 500/s that happened in most runs with load 3 on 2 cores
/// (`hil/README.md`).
const MARKER_GAP: u32 = 5000;
const TRIGGER_GAP: u32 = 5000;
/// Items streamed through the 256-item buffer.
const STREAMED: u32 = 600;

const CAMERA: CameraConfig = CameraConfig {
    camera: 0,
    pulse_ticks: 50,
    polarity: Polarity::ActiveHigh,
    exposure_input: Input::Unused,
    min_interval_ticks: 0,
};

const LASER: LaserConfig = LaserConfig {
    channel: 0,
    wavelength_nm: 532,
    warmup_ticks: 0,
    max_on_ticks: 60_000_000,
    enable: Polarity::ActiveHigh,
    interlock: Input::Unused,
};

fn galvo() -> GalvoConfig {
    let axis = GalvoAxis { min_code: 0, max_code: 65535, zero_code: 32768, nanorad_per_code: 5000 };
    GalvoConfig {
        galvo: 0,
        dac: DacKind::Dac8563,
        x: axis,
        y: axis,
        park: Xy { x: 32768, y: 32768 },
        settle_ticks: 0,
    }
}

impl Suite {
    /// A suite against `target`.
    pub fn new(target: Target) -> Self {
        let load_delay = std::env::var(LOAD_DELAY_ENV)
            .ok()
            .and_then(|v| v.trim().parse::<u64>().ok())
            .map_or(Duration::ZERO, Duration::from_millis);
        if !load_delay.is_zero() {
            println!(
                "lightrig-hil: {LOAD_DELAY_ENV}: pausing {} ms before each chunk loaded ahead of a start",
                load_delay.as_millis()
            );
        }
        Self { target, client: None, info: None, last_index: None, load_ticks: 0, restarts: 0, load_delay }
    }

    /// Runs every test; returns how many failed.
    pub fn run(&mut self, only_tests: &[String]) -> usize {
        type Test = fn(&mut Suite) -> Check;
        let tests: [(&str, Test); 10] = [
            ("handshake_and_schema", Suite::handshake),
            ("configuration_errors", Suite::configuration_errors),
            ("sequence_triggers_and_events", Suite::sequence_with_triggers),
            ("flow_control_and_underrun", Suite::flow_control_and_underrun),
            ("slow_host_start_is_moved_later", Suite::slow_host),
            ("heartbeat_loss_turns_lasers_off", Suite::heartbeat_loss),
            ("interlock_opening_turns_lasers_off", Suite::interlock),
            ("damaged_frames_are_rejected_and_counted", Suite::damaged_frames),
            ("undecodable_requests_are_answered_rejected", Suite::rejected_messages),
            ("long_run_loses_no_event", Suite::long_run),
        ];
        let mut failed = 0;
        for (name, test) in tests {
            if !only_tests.is_empty() && !only_tests.iter().any(|o| name.contains(o.as_str())) {
                continue;
            }
            let t0 = Instant::now();
            let result = test(self).and_then(|()| self.still_running());
            let secs = t0.elapsed().as_secs_f64();
            match result {
                Ok(()) => println!("ok    {name} ({secs:.1} s)"),
                Err(e) => {
                    failed += 1;
                    println!("FAIL  {name} ({secs:.1} s): {e}");
                    // Start the next test from a fresh connection.
                    let _ = self.disconnect();
                    self.client = None;
                }
            }
        }
        if let Some(info) = self.info {
            let ms = self.load_ticks * 1000 / u64::from(info.tick_hz).max(1);
            println!(
                "lightrig-hil: loading ahead of a start took at most {ms} ms of device time; {} start(s) refused \
                 StartInPast and made later (besides the one slow_host_start_is_moved_later forces)",
                self.restarts
            );
        }
        failed
    }

    /// The device never resets on bad input: it still runs, with the same boot id.
    fn still_running(&mut self) -> Check {
        ensure!((self.target.alive)(), "the device stopped (QEMU exited: a panic or a fault)");
        let boot = self.info.map(|i| i.boot_id);
        let status = self.status()?;
        ensure!(
            !matches!(status.state, DeviceState::AwaitingHello),
            "the device lost the session: {status:?}"
        );
        let now_boot = self.client()?.info().boot_id;
        ensure_eq!(Some(now_boot), boot.or(Some(now_boot)));
        Ok(())
    }

    fn client(&mut self) -> Result<&mut Client<Dyn>, String> {
        if self.client.is_none() {
            let transport = (self.target.open)()?;
            let mut c = Client::connect(transport, nonce()).map_err(err)?;
            c.set_heartbeat_us(50_000);
            if let Some(info) = self.info {
                ensure_eq!(c.info().boot_id, info.boot_id);
            }
            self.info = Some(*c.info());
            // Events of the previous connection that the device sends again are not new.
            self.client = Some(c);
        }
        self.client.as_mut().ok_or_else(|| "no client".to_string())
    }

    fn request(&mut self, command: Command) -> Result<Reply, String> {
        self.client()?.request(command).map_err(err)
    }

    fn refused(&mut self, command: Command, expected: Error) -> Check {
        match self.client()?.request(command.clone()) {
            Err(ClientError::Refused { error, .. }) if error == expected => Ok(()),
            other => Err(format!("{command:?}: expected refusal {expected:?}, got {other:?}")),
        }
    }

    fn now(&mut self) -> Result<u64, String> {
        match self.request(Command::GetClock)? {
            Reply::Clock { tick } => Ok(tick),
            other => Err(format!("GetClock answered {other:?}")),
        }
    }

    fn status(&mut self) -> Result<Status, String> {
        match self.request(Command::GetStatus)? {
            Reply::Status(s) => Ok(s),
            other => Err(format!("GetStatus answered {other:?}")),
        }
    }

    /// Checks the device's event numbering: no gap. `false` for an event seen before (the
    /// device sends unacknowledged events again after a reconnection).
    fn track(&mut self, index: u32) -> Result<bool, String> {
        match self.last_index {
            Some(last) if index <= last => return Ok(false),
            Some(last) => ensure!(index == last + 1, "event {index} follows {last}: events lost"),
            None => {}
        }
        self.last_index = Some(index);
        Ok(true)
    }

    /// The next new event.
    fn event(&mut self, timeout_us: u64) -> Result<EventRecord, String> {
        loop {
            let e = self.client()?.next_event(timeout_us).map_err(err)?.ok_or("no event in time")?;
            if self.track(e.index)? {
                return Ok(e);
            }
        }
    }

    /// Streams `items` as sequence `id` through the client, tracking its events, started at
    /// least `lead_ms` after the clock reading it is fixed from. Returns the start tick used
    /// (every tick the test expects is relative to it), the `SequenceDone` tick and the new
    /// events.
    ///
    /// The client loads as much as the device's buffer holds and only then sends
    /// `SequenceStart`, so the lead must cover the loading, which takes as long as the host
    /// and the link make it (a busy lab PC, QEMU on a loaded CI runner). The lead is therefore
    /// the test's, or twice the longest loading measured so far ([`lead_for`]); the loading of
    /// every started sequence is measured by the tick of its `State { Running }` event. If
    /// the device still refuses the start `StartInPast { now }`, `now` measures this loading:
    /// the loaded sequence is aborted and streamed again with twice that lead, and the suite
    /// says so.
    fn stream(&mut self, id: u32, items: &[Item], lead_ms: u64) -> Result<(u64, u64, Vec<Event>), String> {
        let base = u64::from(self.ticks_ms(lead_ms)?);
        let ahead = usize::from(self.client()?.info().capabilities.sequence_buffer);
        let hz = u64::from(self.client()?.info().tick_hz);
        let ms = |ticks: u64| ticks * 1000 / hz.max(1);
        let mut last = String::new();
        for _ in 0..START_ATTEMPTS {
            let lead = lead_for(base, self.load_ticks);
            let fixed = self.now()?;
            let start = fixed + lead;
            let mut got = Vec::new();
            let delay = self.load_delay;
            let pause = move |_| {
                if !delay.is_zero() {
                    std::thread::sleep(delay)
                }
            };
            let result = self.client()?.run_sequence(
                id,
                paced(items.iter().cloned(), ahead, pause),
                StartAt::Tick(start),
                |e| got.push((e.index, e.event.clone())),
            );
            let mut events = Vec::new();
            for (index, e) in got {
                if self.track(index)? {
                    events.push(e);
                }
            }
            let outcome = match result {
                Ok(outcome) => outcome,
                Err(ClientError::Refused { error: Error::StartInPast { now }, .. }) => {
                    let took = now.saturating_sub(fixed);
                    self.load_ticks = self.load_ticks.max(took);
                    self.restarts += 1;
                    // Refused, the sequence stays loaded (and never ran): clear it.
                    self.request(Command::SequenceAbort { sequence: id })?;
                    last = format!(
                        "sequence {id}: the start at tick {start}, {} ms after the clock reading, was refused \
                         StartInPast {{ now: {now} }}: loading took {} ms of device time",
                        ms(lead),
                        ms(took)
                    );
                    println!(
                        "      ({last}; streaming it again with a {} ms lead)",
                        ms(lead_for(base, self.load_ticks))
                    );
                    continue;
                }
                Err(e) => return Err(err(e)),
            };
            // How long the loading took, for the leads of the sequences after this one.
            let started = events.iter().find_map(|e| match *e {
                Event::State { state: DeviceState::Running { sequence }, tick, .. } if sequence == id => {
                    Some(tick)
                }
                _ => None,
            });
            if let Some(tick) = started {
                ensure!(tick <= start, "sequence {id} started at {start} but was running at {tick}");
                self.load_ticks = self.load_ticks.max(tick.saturating_sub(fixed));
            }
            let done = events.iter().find_map(|e| match *e {
                Event::SequenceDone { sequence, items, tick } if sequence == id => Some((items, tick)),
                _ => None,
            });
            ensure_eq!(done, Some((outcome.items, outcome.tick)));
            return Ok((start, outcome.tick, events));
        }
        Err(format!("{START_ATTEMPTS} starts refused; the last: {last}"))
    }

    /// Starts the loaded sequence `id` at least `lead_ms` after the clock reading it is fixed
    /// from, as [`Self::stream`] does: later, and saying so, if the device refuses the start
    /// `StartInPast` (a refused start leaves the sequence loaded). Returns the start tick.
    fn start_loaded(&mut self, id: u32, lead_ms: u64) -> Result<u64, String> {
        let base = u64::from(self.ticks_ms(lead_ms)?);
        let hz = u64::from(self.client()?.info().tick_hz);
        let ms = |ticks: u64| ticks * 1000 / hz.max(1);
        let mut last = String::new();
        for _ in 0..START_ATTEMPTS {
            let lead = lead_for(base, self.load_ticks);
            let fixed = self.now()?;
            let start = fixed + lead;
            match self.client()?.request(Command::SequenceStart { sequence: id, at: StartAt::Tick(start) }) {
                Ok(_) => return Ok(start),
                Err(ClientError::Refused { error: Error::StartInPast { now }, .. }) => {
                    let took = now.saturating_sub(fixed);
                    self.load_ticks = self.load_ticks.max(took);
                    self.restarts += 1;
                    last = format!(
                        "sequence {id}: the start at tick {start}, {} ms after the clock reading, was refused \
                         StartInPast {{ now: {now} }} ({} ms later)",
                        ms(lead),
                        ms(took)
                    );
                    println!("      ({last}; starting it later)");
                }
                Err(e) => return Err(err(e)),
            }
        }
        Err(format!("{START_ATTEMPTS} starts refused; the last: {last}"))
    }

    /// Microseconds of host time to wait for an event due `ticks` from now, beyond the usual
    /// timeouts: device ticks at least, twice that for an emulated device that runs slower.
    fn lead_us(&mut self, ticks: u64) -> Result<u64, String> {
        let hz = u64::from(self.client()?.info().tick_hz).max(1);
        Ok(ticks.saturating_mul(2_000_000) / hz)
    }

    /// Drops the connection after everything the device sent was acknowledged, so that the
    /// next one starts clean.
    fn disconnect(&mut self) -> Check {
        if self.client.is_some() {
            self.drain()?;
        }
        self.client = None;
        Ok(())
    }

    /// Events until one matches `done` (included), at most `timeout_us` apart.
    fn events_until(&mut self, timeout_us: u64, done: impl Fn(&Event) -> bool) -> Result<Vec<Event>, String> {
        let mut out = Vec::new();
        loop {
            let e = self.event(timeout_us)?.event;
            let stop = done(&e);
            out.push(e);
            if stop {
                return Ok(out);
            }
        }
    }

    /// Takes every event already sent, after a short quiet spell.
    fn drain(&mut self) -> Check {
        self.client()?.idle(200_000).map_err(err)?;
        while let Some(e) = self.client()?.next_event(0).map_err(err)? {
            self.track(e.index)?;
        }
        Ok(())
    }

    /// No fault latched, no sequence, heartbeat at 1 s.
    fn reset_state(&mut self) -> Check {
        self.client()?.set_heartbeat_us(50_000);
        let s = self.status()?;
        if let DeviceState::Running { sequence } = s.state {
            self.request(Command::SequenceAbort { sequence })?;
        }
        if let Some(b) = s.buffer {
            let _ = self.request(Command::SequenceAbort { sequence: b.sequence });
        }
        self.request(Command::ClearFault)?;
        let second = self.ticks_ms(1000)?;
        self.request(Command::Configure(ConfigItem::Safety(SafetyConfig {
            heartbeat_timeout_ticks: second,
        })))?;
        self.drain()
    }

    fn ticks_ms(&mut self, ms: u64) -> Result<u32, String> {
        let hz = u64::from(self.client()?.info().tick_hz);
        u32::try_from(ms * hz / 1000).map_err(|e| e.to_string())
    }

    fn debug(&mut self) -> Option<&mut DebugPort> {
        self.target.debug.as_mut()
    }

    fn configure_basics(&mut self) -> Check {
        self.request(Command::Configure(ConfigItem::Laser(LASER)))?;
        self.request(Command::Configure(ConfigItem::Camera(CAMERA)))?;
        self.request(Command::Configure(ConfigItem::Galvo(galvo())))?;
        Ok(())
    }

    // ---- the tests ----------------------------------------------------------------------

    fn handshake(&mut self) -> Check {
        self.disconnect()?;
        // A host of another schema is told the device's version and schema, and refused.
        let transport = (self.target.open)()?;
        match Client::connect_as(transport, nonce(), PROTOCOL_VERSION, SCHEMA_HASH ^ 1) {
            Err(ClientError::Incompatible { device_version, device_schema, .. }) => {
                ensure_eq!((device_version, device_schema), (PROTOCOL_VERSION, SCHEMA_HASH));
            }
            other => {
                return Err(format!(
                    "a host with another schema hash: expected Incompatible, got {:?}",
                    other.err()
                ))
            }
        }
        self.client = None;
        let info = *self.client()?.info();
        ensure_eq!((info.protocol_version, info.schema_hash), (PROTOCOL_VERSION, SCHEMA_HASH));
        ensure!(info.tick_hz > 0, "tick_hz is 0");
        ensure_eq!(info.capabilities.link_window, 8);
        ensure_eq!(info.capabilities.sequence_buffer, 256);
        if let Some(boot) = self.target.boot_id {
            ensure_eq!(info.board, lightrig_protocol::session::BoardId::QemuMps2An386);
            ensure_eq!(info.boot_id, boot);
        }
        // Clock: monotonic, and the session is open.
        let (a, b) = (self.now()?, self.now()?);
        ensure!(b > a, "clock did not advance: {a} then {b}");
        let s = self.status()?;
        ensure!(
            matches!(s.state, DeviceState::Ready | DeviceState::Faulted(_)),
            "state after Hello: {:?}",
            s.state
        );
        self.reset_state()
    }

    fn configuration_errors(&mut self) -> Check {
        self.reset_state()?;
        let caps = self.client()?.info().capabilities;
        let hz = u64::from(self.client()?.info().tick_hz);
        let bad = |field, index, reason| Error::InvalidConfig(ConfigError { field, index, reason });
        self.refused(
            Command::Configure(ConfigItem::Laser(LaserConfig { wavelength_nm: 100, ..LASER })),
            bad(ConfigField::LaserWavelength, 0, InvalidReason::TooSmall { min: 200 }),
        )?;
        self.refused(
            Command::Configure(ConfigItem::Laser(LaserConfig { channel: caps.lasers, ..LASER })),
            bad(
                ConfigField::LaserChannel,
                caps.lasers,
                InvalidReason::NoSuchPeripheral { count: caps.lasers },
            ),
        )?;
        self.refused(
            Command::Configure(ConfigItem::Laser(LaserConfig {
                warmup_ticks: 11,
                max_on_ticks: 10,
                ..LASER
            })),
            bad(ConfigField::LaserWarmupTicks, 0, InvalidReason::TooLarge { max: 10 }),
        )?;
        self.refused(
            Command::Configure(ConfigItem::Camera(CameraConfig { pulse_ticks: 0, ..CAMERA })),
            bad(ConfigField::CameraPulseTicks, 0, InvalidReason::Zero),
        )?;
        self.refused(
            Command::Configure(ConfigItem::Safety(SafetyConfig {
                heartbeat_timeout_ticks: (hz / 200) as u32,
            })),
            bad(
                ConfigField::SafetyHeartbeatTimeout,
                0,
                InvalidReason::TooSmall { min: (10 * hz / 1000) as i64 },
            ),
        )?;
        let mut g = galvo();
        g.x.zero_code = 70;
        g.x.min_code = 100;
        self.refused(
            Command::Configure(ConfigItem::Galvo(g)),
            bad(ConfigField::GalvoXZeroCode, 0, InvalidReason::OutsideRange { min: 100, max: 65535 }),
        )?;
        // Refused configurations leave nothing configured: arming needs a configured laser.
        use lightrig_protocol::error::Peripheral;
        let last = caps.lasers - 1;
        self.refused(
            Command::Arm { lasers: 1 << last },
            Error::NotConfigured { kind: Peripheral::Laser, index: last },
        )?;
        if caps.lasers < 8 {
            self.refused(
                Command::Arm { lasers: 1 << caps.lasers },
                Error::NoSuchPeripheral { kind: Peripheral::Laser, index: caps.lasers, count: caps.lasers },
            )?;
        }
        self.configure_basics()?;
        self.request(Command::Disarm)?;
        self.refused(
            Command::Immediate(Action::Laser { channel: 0, on: true }),
            Error::NotArmed { channel: 0 },
        )?;
        self.drain()
    }

    fn sequence_with_triggers(&mut self) -> Check {
        self.reset_state()?;
        self.configure_basics()?;
        self.request(Command::Arm { lasers: 1 })?;
        self.drain()?;
        if let Some(d) = self.debug() {
            d.mark()?;
        }
        let to = Xy { x: 1000, y: 2000 };
        let mut items = vec![
            Item { delta: 0, action: Action::GalvoPoint { galvo: 0, to } },
            Item { delta: 100, action: Action::Laser { channel: 0, on: true } },
        ];
        items.extend(
            (0..10).map(|_| Item { delta: 1000, action: Action::Trigger { camera: 0, exposure: 0 } }),
        );
        items.push(Item { delta: 500, action: Action::Laser { channel: 0, on: false } });
        items.push(Item { delta: 0, action: Action::Marker { id: 77 } });
        let (start, last_tick, events) = self.stream(5, &items, 200)?;
        let end = start + 100 + 10 * 1000 + 500;
        ensure_eq!(last_tick, end);
        let triggers: Vec<_> = events
            .iter()
            .filter_map(|e| match e {
                Event::Trigger(t) => Some(t.clone()),
                _ => None,
            })
            .collect();
        ensure_eq!(triggers.len(), 10);
        for (k, t) in triggers.iter().enumerate() {
            let tick = start + 100 + 1000 * (k as u64 + 1);
            ensure_eq!(
                (t.sequence, t.item, t.frame, t.camera, t.tick, t.width),
                (5, 2 + k as u32, k as u32, 0, tick, 50)
            );
            ensure_eq!((t.snapshot.galvos.first().copied(), t.snapshot.lasers), (Some(to), 1));
        }
        let marker = events.iter().find_map(|e| match *e {
            Event::Marker { sequence, item, id, tick } => Some((sequence, item, id, tick)),
            _ => None,
        });
        ensure_eq!(marker, Some((5, 13, 77, end)));
        self.drain()?;
        if let Some(d) = self.debug() {
            let rec = d.read_new()?;
            let trig = only(&rec, |o| matches!(o, Output::Trigger { .. }));
            let expected: Vec<_> = (0..10u64)
                .flat_map(|k| {
                    let t = start + 100 + 1000 * (k + 1);
                    [
                        (t, Output::Trigger { camera: 0, level: true }),
                        (t + 50, Output::Trigger { camera: 0, level: false }),
                    ]
                })
                .collect();
            ensure_eq!(trig, expected);
            let lasers = only(&rec, |o| matches!(o, Output::Laser { channel: 0, .. }));
            ensure_eq!(
                lasers.first().copied(),
                Some((start + 100, Output::Laser { channel: 0, level: true }))
            );
            ensure_eq!(lasers.get(1).copied(), Some((end, Output::Laser { channel: 0, level: false })));
            ensure!(
                lasers.iter().skip(2).all(|(_, o)| *o == Output::Laser { channel: 0, level: false }),
                "{lasers:?}"
            );
            ensure_eq!(
                only(&rec, |o| matches!(o, Output::Galvo { .. })),
                vec![(start, Output::Galvo { pair: 0, to })]
            );
        }
        Ok(())
    }

    fn flow_control_and_underrun(&mut self) -> Check {
        self.reset_state()?;
        self.configure_basics()?;
        // Credit: 256 items fit, the 257th is refused with the exact free count.
        let markers = |n: u32| -> heapless::Vec<Item, 32> {
            (0..n).map(|i| Item { delta: 1000, action: Action::Marker { id: i } }).collect()
        };
        for chunk in 0..8 {
            let r = self.request(Command::SequenceLoad(Chunk {
                sequence: 30,
                chunk,
                last: false,
                items: markers(32),
            }))?;
            let Reply::Buffer(b) = r else { return Err(format!("SequenceLoad answered {r:?}")) };
            ensure_eq!(
                (b.sequence, b.capacity, b.free, b.next_chunk),
                (30, 256, 256 - 32 * (chunk as u16 + 1), chunk + 1)
            );
        }
        self.refused(
            Command::SequenceLoad(Chunk { sequence: 30, chunk: 8, last: true, items: markers(1) }),
            Error::BufferFull { free: 0 },
        )?;
        self.request(Command::SequenceAbort { sequence: 30 })?;

        // Streaming under credit: more items than the buffer holds, every one on its tick.
        let items: Vec<_> =
            (0..STREAMED).map(|i| Item { delta: MARKER_GAP, action: Action::Marker { id: i } }).collect();
        let (start, last_tick, events) = self.stream(31, &items, 100)?;
        ensure_eq!(last_tick, start + u64::from(STREAMED) * u64::from(MARKER_GAP));
        let marks: Vec<_> = events
            .iter()
            .filter_map(|e| match *e {
                Event::Marker { sequence: 31, item, id, tick } => Some((item, id, tick)),
                _ => None,
            })
            .collect();
        let expected: Vec<_> =
            (0..STREAMED).map(|i| (i, i, start + u64::from(MARKER_GAP) * (u64::from(i) + 1))).collect();
        ensure_eq!(marks, expected);
        // Credit came back as the buffer drained, and the last report says it is empty.
        let credit: Vec<_> = events
            .iter()
            .filter_map(|e| match e {
                Event::Buffer(b) if b.sequence == 31 => Some((b.free, b.executed)),
                _ => None,
            })
            .collect();
        ensure!(credit.len() >= 2, "credit returned only {} times for {STREAMED} items", credit.len());
        ensure_eq!(credit.last().copied(), Some((256, STREAMED)));
        self.drain()?;

        // Underrun: ten items and no last chunk; the buffer runs dry at the tenth item's tick.
        self.request(Command::Arm { lasers: 1 })?;
        self.request(Command::Immediate(Action::Laser { channel: 0, on: true }))?;
        self.drain()?;
        if let Some(d) = self.debug() {
            d.mark()?;
        }
        self.request(Command::SequenceLoad(Chunk {
            sequence: 32,
            chunk: 0,
            last: false,
            items: markers(10),
        }))?;
        let start = self.start_loaded(32, 50)?;
        let wait = 2_000_000 + self.lead_us(lead_for(0, self.load_ticks))?;
        let events = self.events_until(wait, |e| matches!(e, Event::Fault { .. }))?;
        let dry = start + 10 * 1000;
        ensure!(
            events.contains(&Event::Underrun { sequence: 32, item: 10, tick: dry }),
            "no Underrun {{ sequence: 32, item: 10, tick: {dry} }} in {events:?}"
        );
        ensure_eq!(
            events.last(),
            Some(&Event::Fault { cause: FaultCause::Underrun { sequence: 32 }, tick: dry })
        );
        let s = self.status()?;
        ensure_eq!(
            (s.state, s.armed, s.lasers_on),
            (DeviceState::Faulted(FaultCause::Underrun { sequence: 32 }), 0, 0)
        );
        self.refused(Command::Arm { lasers: 1 }, Error::Faulted(FaultCause::Underrun { sequence: 32 }))?;
        if let Some(d) = self.debug() {
            let rec = d.read_new()?;
            ensure_eq!(
                only(&rec, |o| matches!(o, Output::Laser { .. })),
                vec![(dry, Output::Laser { channel: 0, level: false })]
            );
        }
        self.reset_state()
    }

    /// A slow host: a pause before each chunk loaded ahead of the start makes the loading
    /// (3 × 100 ms) outlast the lead (10 ms). The device refuses the start `StartInPast`, and
    /// the sequence is streamed again, started later by twice the loading measured; every
    /// marker comes exactly at its tick from the start used. This is what a busy host does to
    /// every streamed sequence, made to happen.
    fn slow_host(&mut self) -> Check {
        const ITEMS: u32 = 3 * MAX_CHUNK_ITEMS as u32;
        self.reset_state()?;
        let (load, restarts, delay) = (self.load_ticks, self.restarts, self.load_delay);
        // The loading this host was seen to need would lengthen the first lead: not here.
        self.load_ticks = 0;
        self.load_delay = Duration::from_millis(100);
        let items: Vec<_> =
            (0..ITEMS).map(|i| Item { delta: 1000, action: Action::Marker { id: i } }).collect();
        let result = self.stream(33, &items, 10);
        // The simulated slowness is not this host's: later tests lead by what they did before.
        let (measured, forced) = (self.load_ticks, self.restarts - restarts);
        self.load_ticks = load;
        self.load_delay = delay;
        self.restarts = restarts;
        let (start, last_tick, events) = result?;
        ensure!(forced > 0, "a start 10 ms ahead was not refused though loading took {measured} ticks");
        ensure_eq!(last_tick, start + u64::from(ITEMS) * 1000);
        let marks: Vec<_> = events
            .iter()
            .filter_map(|e| match *e {
                Event::Marker { sequence: 33, item, id, tick } => Some((item, id, tick)),
                _ => None,
            })
            .collect();
        let expected: Vec<_> = (0..ITEMS).map(|i| (i, i, start + 1000 * (u64::from(i) + 1))).collect();
        ensure_eq!(marks, expected);
        self.drain()
    }

    fn heartbeat_loss(&mut self) -> Check {
        self.reset_state()?;
        self.configure_basics()?;
        let timeout = self.ticks_ms(200)?;
        self.request(Command::Configure(ConfigItem::Safety(SafetyConfig {
            heartbeat_timeout_ticks: timeout,
        })))?;
        self.request(Command::Arm { lasers: 1 })?;
        if let Some(d) = self.debug() {
            d.mark()?;
        }
        self.request(Command::Immediate(Action::Laser { channel: 0, on: true }))?;
        self.drain()?;
        // The host goes quiet (it still reads and acknowledges events): its last command is
        // this clock request.
        self.client()?.set_heartbeat_us(u64::MAX / 4);
        let last = self.now()?;
        let lost = last + u64::from(timeout);
        let events = self.events_until(5_000_000, |e| matches!(e, Event::Fault { .. }))?;
        ensure_eq!(events.last(), Some(&Event::Fault { cause: FaultCause::HeartbeatLost, tick: lost }));
        self.client()?.set_heartbeat_us(50_000);
        let s = self.status()?;
        ensure_eq!((s.state, s.armed, s.lasers_on), (DeviceState::Faulted(FaultCause::HeartbeatLost), 0, 0));
        if let Some(d) = self.debug() {
            let rec = d.read_new()?;
            let lasers = only(&rec, |o| matches!(o, Output::Laser { .. }));
            ensure_eq!(
                lasers,
                vec![
                    (lasers.first().map_or(0, |l| l.0), Output::Laser { channel: 0, level: true }),
                    (lost, Output::Laser { channel: 0, level: false })
                ]
            );
            ensure!(
                lasers[0].0 < last,
                "the laser went on at {} after the last command at {last}",
                lasers[0].0
            );
            // Galvos park in the safe state, at the same tick.
            ensure_eq!(
                only(&rec, |o| matches!(o, Output::Galvo { .. })),
                vec![(lost, Output::Galvo { pair: 0, to: galvo().park })]
            );
        }
        self.reset_state()
    }

    /// Needs the recorder to open the interlock input; skipped on a real board.
    fn interlock(&mut self) -> Check {
        if self.target.debug.is_none() {
            println!("      (skipped: no recorder to open an interlock on this target)");
            return Ok(());
        }
        self.reset_state()?;
        let wired = LaserConfig { interlock: Input::Wired(Polarity::ActiveHigh), ..LASER };
        self.request(Command::Configure(ConfigItem::Laser(wired)))?;
        self.request(Command::Arm { lasers: 1 })?;
        self.request(Command::Immediate(Action::Laser { channel: 0, on: true }))?;
        self.drain()?;
        if let Some(d) = self.debug() {
            d.mark()?;
            d.set_interlock(0, false)?;
        }
        let events = self.events_until(2_000_000, |e| matches!(e, Event::Fault { .. }));
        if let Some(d) = self.debug() {
            d.set_interlock(0, true)?;
        }
        let events = events?;
        let Some(&Event::Fault { cause, tick }) = events.last() else { return Err(format!("{events:?}")) };
        ensure_eq!(cause, FaultCause::Interlock { channel: 0 });
        if let Some(d) = self.debug() {
            let rec = d.read_new()?;
            ensure_eq!(
                only(&rec, |o| matches!(o, Output::Laser { .. })),
                vec![(tick, Output::Laser { channel: 0, level: false })]
            );
        }
        self.request(Command::Configure(ConfigItem::Laser(LASER)))?;
        self.reset_state()
    }

    fn damaged_frames(&mut self) -> Check {
        self.reset_state()?;
        let before = self.status()?.link;
        // Each blob starts with an idle delimiter and ends one frame. What the device must
        // count for it is found by running it through the protocol's own frame decoder.
        let mut blobs: Vec<(Vec<u8>, FrameError)> = Vec::new();
        let mut add = |bytes: Vec<u8>, expect_link_level: Option<FrameError>| {
            let mut framed = vec![0u8];
            framed.extend_from_slice(&bytes);
            let mut seen = None;
            FrameDecoder::new().feed(&framed, |r| seen = Some(r.err()));
            let why = match (seen, expect_link_level) {
                (Some(Some(e)), _) => e,
                (Some(None), Some(e)) => e,
                _ => return,
            };
            blobs.push((framed, why));
        };
        let frame = |packet: &[u8]| {
            let mut buf = [0u8; MAX_PACKET];
            buf[..packet.len()].copy_from_slice(packet);
            let mut out = [0u8; MAX_FRAME];
            let n = lightrig_protocol::frame::seal(&mut buf, packet.len(), &mut out);
            out[..n].to_vec()
        };
        let get_status = {
            let mut p = postcard::to_allocvec(&Header { kind: FrameKind::Data, epoch: 200, seq: 9, ack: 0 })
                .unwrap_or_default();
            p.extend(
                postcard::to_allocvec(&HostMsg { id: 9, command: Command::GetStatus }).unwrap_or_default(),
            );
            frame(&p)
        };
        // A bit flipped in the CRC.
        let mut flipped = get_status.clone();
        let at = flipped.len() - 2;
        flipped[at] ^= if flipped[at] == 0x80 { 0x40 } else { 0x80 };
        add(flipped, None);
        // Truncated: the first half of a frame, then its delimiter.
        let mut half = get_status[..get_status.len() / 2].to_vec();
        half.push(0);
        add(half, None);
        let mut short = get_status[..3].to_vec();
        short.push(0);
        add(short, None);
        // Valid COBS of a 3-byte packet: shorter than a header and a CRC.
        add(vec![0x04, 0x01, 0x02, 0x03, 0x00], None);
        // Invalid COBS: a code byte promising more than there is.
        add(vec![0x05, 0x11, 0x00], None);
        // Longer than any frame, without a delimiter.
        let mut long = vec![0x55u8; 600];
        long.push(0);
        add(long, None);
        // Intact but of an unknown kind (first header byte 9).
        add(frame(&[9, 1, 0, 0]), Some(FrameError::UnknownType));
        // Intact `Ack` with a body: not allowed.
        add(frame(&[1, 1, 0, 0, 0x42]), Some(FrameError::BadPayload));
        let mut expected = before;
        for (_, why) in &blobs {
            let c = match why {
                FrameError::BadCobs => &mut expected.bad_cobs,
                FrameError::BadCrc => &mut expected.bad_crc,
                FrameError::TooLong => &mut expected.too_long,
                FrameError::TooShort => &mut expected.too_short,
                FrameError::UnknownType => &mut expected.unknown_type,
                FrameError::BadPayload => &mut expected.bad_payload,
            };
            *c += 1;
        }
        let kinds: std::collections::HashSet<_> = blobs.iter().map(|b| b.1).collect();
        ensure_eq!(kinds.len(), 6);
        for (bytes, _) in &blobs {
            let t0 = self.now()?;
            self.client()?.transport_mut().send(bytes).map_err(|e| e.to_string())?;
            // The device keeps running between damaged frames: its clock goes on.
            ensure!(self.now()? > t0, "the clock stopped");
        }
        let after = self.status()?.link;
        let counters =
            |s: &LinkStats| (s.bad_cobs, s.bad_crc, s.too_long, s.too_short, s.unknown_type, s.bad_payload);
        ensure_eq!(counters(&after), counters(&expected));
        ensure!(after.naks_sent > before.naks_sent, "no Nak for {} damaged frames", blobs.len());
        ensure_eq!(after.syncs, before.syncs);
        Ok(())
    }

    fn rejected_messages(&mut self) -> Check {
        self.reset_state()?;
        let syncs = self.status()?.link.syncs;
        // A raw link session: our own Sync/Confirm, then Data frames whose bodies are not
        // messages the device knows.
        self.disconnect()?;
        let mut raw = Raw::new((self.target.open)()?);
        let n = nonce();
        raw.send(FrameKind::Sync, 0, 0, &postcard::to_allocvec(&n).unwrap_or_default())?;
        let ack: SyncAckBody = loop {
            let (h, body) = raw.recv()?;
            if h.kind == FrameKind::SyncAck {
                break postcard::from_bytes(&body).map_err(|e| e.to_string())?;
            }
        };
        ensure_eq!(ack.nonce, n);
        if let Some(info) = self.info {
            ensure_eq!(ack.boot_nonce, info.boot_id);
        }
        raw.send(FrameKind::Confirm, 0, 0, &postcard::to_allocvec(&ack.boot_nonce).unwrap_or_default())?;
        // seq 0: command index 0x7f is unknown; seq 1: GetStatus with a trailing byte;
        // seq 2: GetClock before Hello.
        let bodies: [(Vec<u8>, Result<DeviceMsg, ()>); 3] = [
            (vec![0x05, 0x7f], Ok(DeviceMsg::Rejected { seq: 0, reason: FrameError::UnknownType })),
            (vec![0x06, 0x02, 0x00], Ok(DeviceMsg::Rejected { seq: 1, reason: FrameError::BadPayload })),
            (
                postcard::to_allocvec(&HostMsg { id: 7, command: Command::GetClock }).unwrap_or_default(),
                Ok(DeviceMsg::Response { id: 7, result: Err(Error::HandshakeRequired) }),
            ),
        ];
        for (seq, (body, expected)) in bodies.into_iter().enumerate() {
            raw.send(FrameKind::Data, seq as u16, raw.expected, &body)?;
            // Skip what the device still had unacknowledged from the last session (it sends
            // that first, in the new epoch).
            let got = loop {
                let msg = raw.next_data()?;
                if matches!(msg, DeviceMsg::Rejected { .. } | DeviceMsg::Response { id: 7, .. }) {
                    break msg;
                }
            };
            ensure_eq!(Ok::<_, ()>(got), expected);
        }
        // Whatever the device sends again (our last ack lost) is acknowledged before we go.
        raw.quiesce(500_000)?;
        drop(raw);
        // A normal session again: the same device, no restart (one more epoch per session).
        let s = self.status()?;
        ensure_eq!(s.link.syncs, syncs + 2);
        Ok(())
    }

    fn long_run(&mut self) -> Check {
        const N: u32 = 2000;
        self.reset_state()?;
        self.configure_basics()?;
        self.drain()?;
        if let Some(d) = self.debug() {
            d.mark()?;
        }
        let items: Vec<_> = (0..N)
            .map(|_| Item { delta: TRIGGER_GAP, action: Action::Trigger { camera: 0, exposure: 0 } })
            .collect();
        let (start, last_tick, events) = self.stream(40, &items, 100)?;
        ensure_eq!(last_tick, start + u64::from(TRIGGER_GAP) * u64::from(N));
        let triggers: Vec<_> = events
            .iter()
            .filter_map(|e| match e {
                Event::Trigger(t) => Some((t.frame, t.item, t.tick)),
                _ => None,
            })
            .collect();
        let expected: Vec<_> =
            (0..N).map(|k| (k, k, start + u64::from(TRIGGER_GAP) * (u64::from(k) + 1))).collect();
        ensure_eq!(triggers.len(), expected.len());
        ensure_eq!(triggers, expected);
        self.drain()?;
        if let Some(d) = self.debug() {
            let rec = d.read_new()?;
            let rising: Vec<_> = only(&rec, |o| *o == Output::Trigger { camera: 0, level: true })
                .into_iter()
                .map(|r| r.0)
                .collect();
            let falling: Vec<_> = only(&rec, |o| *o == Output::Trigger { camera: 0, level: false })
                .into_iter()
                .map(|r| r.0)
                .collect();
            let want: Vec<_> = expected.iter().map(|e| e.2).collect();
            ensure_eq!(rising, want);
            ensure_eq!(falling, want.iter().map(|t| t + 50).collect::<Vec<_>>());
        }
        Ok(())
    }
}

/// A link session driven by hand, for frames the host's link would never send.
struct Raw {
    t: Dyn,
    dec: FrameDecoder,
    epoch: u8,
    got: std::collections::VecDeque<(Header, Vec<u8>)>,
    /// The device's next sequence number (our cumulative ack).
    expected: u16,
}

impl Raw {
    fn new(t: Dyn) -> Self {
        Self { t, dec: FrameDecoder::new(), epoch: 1, got: Default::default(), expected: 0 }
    }

    /// The device's next in-order message, acknowledged.
    fn next_data(&mut self) -> Result<DeviceMsg, String> {
        loop {
            let (h, body) = self.recv()?;
            if h.kind != FrameKind::Data {
                continue;
            }
            if h.seq == self.expected {
                self.expected = self.expected.wrapping_add(1);
                self.send(FrameKind::Ack, 0, self.expected, &[])?;
                return lightrig_protocol::link::decode::<DeviceMsg>(&body).map_err(|e| format!("{e:?}"));
            }
            // A repeat: our ack was lost; acknowledge again.
            self.send(FrameKind::Ack, 0, self.expected, &[])?;
        }
    }

    /// Acknowledges whatever arrives for `us` microseconds.
    fn quiesce(&mut self, us: u64) -> Check {
        let end = self.t.now_us() + us;
        while self.t.now_us() < end {
            match self.recv_until(end)? {
                Some((h, _)) if h.kind == FrameKind::Data => {
                    self.send(FrameKind::Ack, 0, self.expected, &[])?
                }
                _ => {}
            }
        }
        Ok(())
    }

    fn send(&mut self, kind: FrameKind, seq: u16, ack: u16, body: &[u8]) -> Check {
        let mut p = postcard::to_allocvec(&Header { kind, epoch: self.epoch, seq, ack })
            .map_err(|e| e.to_string())?;
        p.extend_from_slice(body);
        let mut buf = [0u8; MAX_PACKET];
        buf[..p.len()].copy_from_slice(&p);
        let mut out = [0u8; MAX_FRAME];
        let n = lightrig_protocol::frame::seal(&mut buf, p.len(), &mut out);
        self.t.send(&out[..n]).map_err(|e| e.to_string())
    }

    /// The next intact frame from the device (2 s at most).
    fn recv(&mut self) -> Result<(Header, Vec<u8>), String> {
        let deadline = self.t.now_us() + 2_000_000;
        self.recv_until(deadline)?.ok_or_else(|| "no frame from the device within 2 s".to_string())
    }

    fn recv_until(&mut self, deadline: u64) -> Result<Option<(Header, Vec<u8>)>, String> {
        let mut buf = [0u8; 512];
        loop {
            if let Some(g) = self.got.pop_front() {
                return Ok(Some(g));
            }
            if self.t.now_us() >= deadline {
                return Ok(None);
            }
            let n = self.t.recv(&mut buf, deadline).map_err(|e| e.to_string())?;
            for &b in &buf[..n] {
                if let Some(Ok(len)) = self.dec.push(b) {
                    if let Ok((h, body)) = postcard::take_from_bytes::<Header>(self.dec.packet(len)) {
                        self.got.push_back((h, body.to_vec()));
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_lead_is_the_tests_or_twice_the_loading_seen() {
        assert_eq!(lead_for(100_000, 0), 100_000);
        assert_eq!(lead_for(100_000, 40_000), 100_000);
        assert_eq!(lead_for(100_000, 130_000), 260_000);
        assert_eq!(lead_for(10, u64::MAX), u64::MAX);
    }

    #[test]
    fn a_slow_host_pauses_only_before_chunks_loaded_ahead_of_the_start() {
        let items: Vec<_> =
            (0..100u32).map(|i| Item { delta: 1, action: Action::Marker { id: i } }).collect();
        let mut paused = Vec::new();
        let out: Vec<_> = paced(items.iter().cloned(), 64, |k| paused.push(k)).collect();
        assert_eq!(out, items);
        // Before items 0 and 32 (the chunks loaded before the start), not 64 and 96.
        assert_eq!(paused, [0, 32]);
    }
}
