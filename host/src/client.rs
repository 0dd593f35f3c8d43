//! The device client: handshake, requests, the acknowledged event stream, heartbeat, the
//! host–device clock mapping, and sequence streaming under credit flow control.
//!
//! One [`Client`] talks to one device over any [`Transport`]. It is synchronous: every call
//! pumps the link (sends, receives, retransmits, heartbeats) until its answer arrives or its
//! time runs out. Events that arrive meanwhile queue up in order, numbered, duplicates (after
//! a reconnection) dropped, each with a host timestamp from the clock mapping.

use std::collections::{HashSet, VecDeque};
use std::fmt;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use lightrig_protocol::event::FaultCause;
use lightrig_protocol::link::{Delivery, Link, LinkConfig, Role};
use lightrig_protocol::sequence::{Chunk, Item, StartAt};
use lightrig_protocol::session::DeviceInfo;
use lightrig_protocol::{
    Command, DeviceMsg, Error, Event, HostMsg, Reply, MAX_CHUNK_ITEMS, MAX_FRAME, PROTOCOL_VERSION,
    SCHEMA_HASH,
};

use crate::clock::ClockMap;
use crate::transport::Transport;

/// Link window, frames in flight.
const WINDOW: usize = 8;
/// Retransmission timeout, µs.
const RTO_US: u64 = 20_000;
/// How often [`Client::busy`] looks whether the work is done, µs.
const BUSY_POLL_US: u64 = 10_000;
/// How often a client with an [`Interrupt`] looks whether a stop was asked, µs.
const STOP_POLL_US: u64 = 50_000;
/// How often those watching the run hear the link's counters, µs.
const LIVE_EVERY_US: u64 = 250_000;

/// A link nonce for one run of a host program: the OS's random source (through the standard
/// library's hasher keys) mixed with the time and the process id, so two runs, even started
/// in the same microsecond, differ.
pub fn fresh_nonce() -> u32 {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u32(std::process::id());
    if let Ok(d) = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH) {
        h.write_u128(d.as_nanos());
    }
    let x = h.finish();
    (x ^ (x >> 32)) as u32
}

/// A request to stop, from outside the thread driving the client (a Ctrl-C handler, the
/// acquisition's control socket): the client sends `EmergencyStop` at its next turn of the
/// link and fails the call in progress with [`ClientError::Interrupted`]. It is final: every
/// later call of a client holding it fails the same way (sending the stop again until one was
/// answered), so nothing after a stop can arm, clear or reconnect in this process.
#[derive(Debug, Default)]
pub struct Interrupt {
    requested: AtomicBool,
    stopped: AtomicBool,
    answered: AtomicBool,
}

impl Interrupt {
    /// Asks the client to stop the device.
    pub fn request(&self) {
        self.requested.store(true, Ordering::SeqCst);
    }

    /// Whether a stop was asked for.
    pub fn requested(&self) -> bool {
        self.requested.load(Ordering::SeqCst)
    }

    /// Whether the device has been sent the stop (answered or not: the link may be gone).
    pub fn stopped(&self) -> bool {
        self.stopped.load(Ordering::SeqCst)
    }

    /// Whether the device answered the stop: it is latched in `Faulted(EmergencyStop)`.
    pub fn answered(&self) -> bool {
        self.answered.load(Ordering::SeqCst)
    }
}

/// What went wrong talking to a device. Each message says what, where and what to do.
#[derive(Debug)]
pub enum ClientError {
    /// The transport failed (port closed, cable pulled).
    Io { device: String, error: std::io::Error },
    /// No answer in time.
    Timeout { device: String, what: String, waited_ms: u64 },
    /// The device speaks another protocol version or message schema.
    Incompatible { device: String, device_version: u16, device_schema: u64 },
    /// The device refused a command.
    Refused { device: String, command: String, error: Error },
    /// The device entered the safe state.
    Fault { device: String, cause: FaultCause, tick: u64 },
    /// The device answered something the protocol does not allow here.
    Protocol { device: String, detail: String },
    /// Stopped at the user's request (Ctrl-C, `lightrig stop`): the device was sent
    /// `EmergencyStop`; `answered` whether it said it stopped.
    Interrupted { device: String, answered: bool },
    /// The device has latched a fault that a person must see to before it is cleared.
    NeedsConfirmation { device: String, cause: FaultCause },
    /// The device no longer knows this host's session: it restarted (reset, watchdog, power)
    /// with the link still open (a new boot nonce in the next link epoch), or it refused a
    /// request for want of a Hello. A new link epoch of the same device run is not this: the
    /// client says Hello again and goes on.
    SessionLost { device: String },
}

impl fmt::Display for ClientError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ClientError::Io { device, error } => {
                write!(f, "{device}: {error}; check the cable and that no other program holds the port")
            }
            ClientError::Timeout { device, what, waited_ms } => write!(
                f,
                "{device}: no answer to {what} within {waited_ms} ms; is the device powered and running lightrig \
                 firmware? (`lightrig devices` lists what answers)"
            ),
            ClientError::Incompatible { device, device_version, device_schema } => write!(
                f,
                "{device}: the firmware speaks protocol {device_version} (schema 0x{device_schema:016x}), this host \
                 speaks protocol {PROTOCOL_VERSION} (schema 0x{SCHEMA_HASH:016x}); flash firmware built from the same \
                 lightrig release as this host, or install the host matching the firmware"
            ),
            ClientError::Refused { device, command, error } => {
                write!(f, "{device} refused {command}: {}", describe_error(error))
            }
            ClientError::Fault { device, cause, tick } => write!(
                f,
                "{device} entered the safe state at tick {tick}: {} ({cause:?}); lasers are off. Fix the cause, then \
                 send ClearFault (`lightrig` does this when you resume)",
                describe_fault(cause)
            ),
            ClientError::Protocol { device, detail } => write!(f, "{device}: protocol error: {detail}"),
            ClientError::Interrupted { device, answered: true } => write!(
                f,
                "stopped by the user: {device} was sent EmergencyStop and answered (lasers off and disarmed, motion \
                 stopped, galvos parked); the stop stays latched until a person clears it: `lightrig resume` at a \
                 terminal asks, or pass --clear-stop"
            ),
            ClientError::Interrupted { device, answered: false } => write!(
                f,
                "stopped by the user: {device} was sent EmergencyStop but did not answer (the link is gone); its \
                 heartbeat watchdog turns the lasers off once this host is silent. Check the rig before going near \
                 it; `lightrig info` says its state"
            ),
            ClientError::SessionLost { device } => write!(
                f,
                "{device} no longer knows this host's session: it restarted (reset, watchdog, power) with the link \
                 left open and has lost its configuration and whatever it was running (or its link was reset \
                 with too many requests in flight to say Hello first). Connecting again says Hello, configures \
                 and homes it"
            ),
            ClientError::NeedsConfirmation { device, cause: FaultCause::EmergencyStop } => write!(
                f,
                "{device} is emergency-stopped (Ctrl-C, `lightrig stop` or its stop input), and only a person may \
                 clear that: once the rig is safe, run `lightrig resume` at a terminal, which asks, or pass \
                 --clear-stop"
            ),
            ClientError::NeedsConfirmation { device, cause } => write!(
                f,
                "{device} has latched a fault: {}. A person must see to it (the enclosure closed, the interlock and \
                 its wiring checked) and confirm before it is cleared: run `lightrig resume` at a terminal, which \
                 asks, or pass --yes once it is safe",
                describe_fault(cause)
            ),
        }
    }
}

impl std::error::Error for ClientError {}

/// A device error in words, with the configuration field's dotted name where there is one.
pub fn describe_error(e: &Error) -> String {
    match e {
        Error::InvalidConfig(c) => format!("invalid configuration: {c}"),
        other => format!("{other:?}"),
    }
}

/// A fault cause in words: what happened and what to look at.
pub fn describe_fault(cause: &FaultCause) -> String {
    use lightrig_protocol::sequence::AxisRef;
    let axis = |a: &AxisRef| match a {
        AxisRef::Stepper(i) => format!("stepper {i}"),
        AxisRef::FilterWheel(i) => format!("filter wheel {i}"),
    };
    match cause {
        FaultCause::HeartbeatLost => {
            "the host went silent for longer than the heartbeat timeout (a host that ended or hung, a \
             pulled cable)"
                .into()
        }
        FaultCause::EmergencyStop => "an emergency stop".into(),
        FaultCause::Interlock { channel } => format!("laser {channel}'s interlock opened"),
        FaultCause::LaserOnTime { channel } => format!("laser {channel} stayed on past its max_on time"),
        FaultCause::Limit { axis: a } => {
            format!("{} hit a limit switch or was sent past a soft limit", axis(a))
        }
        FaultCause::HomingFailed { axis: a } => format!("{} did not find its homing switch", axis(a)),
        FaultCause::Underrun { sequence } => {
            format!(
                "sequence {sequence} ran out of items before its last chunk arrived (the host fell behind)"
            )
        }
        FaultCause::WaitTimeout { sequence, item } => {
            format!("item {item} of sequence {sequence} waited for a condition that did not come in time")
        }
        FaultCause::Late { sequence, item } => {
            format!("item {item} of sequence {sequence} came due later than the device could run it exactly")
        }
        FaultCause::Driver { axis: a } => {
            format!("{}'s driver failed or its move could not be planned", axis(a))
        }
        FaultCause::EventOverflow => {
            "the device's event queue overflowed (the host stopped acknowledging)".into()
        }
        FaultCause::AxisBusy { axis: a } => format!("{} was asked to move while still moving", axis(a)),
        FaultCause::TriggerTooSoon { camera } => {
            format!("camera {camera} was triggered sooner than its min_interval after the last trigger")
        }
        FaultCause::GalvoOutput { galvo } => format!("galvo pair {galvo}'s output (converter or bus) failed"),
    }
}

/// An event as the host keeps it.
#[derive(Debug, Clone, PartialEq)]
pub struct EventRecord {
    /// The device's event number (from 0 at device start).
    pub index: u32,
    /// The device's boot id: with `index`, unique across device restarts.
    pub boot_id: u32,
    /// The event.
    pub event: Event,
    /// Host time of the event's tick (µs on the transport's clock), once the clock is mapped.
    pub host_us: Option<f64>,
}

/// How a streamed sequence ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SequenceOutcome {
    /// Items executed.
    pub items: u32,
    /// Tick of the last item.
    pub tick: u64,
}

/// A connected device.
pub struct Client<T: Transport> {
    transport: T,
    link: Link<HostMsg, DeviceMsg, WINDOW>,
    info: DeviceInfo,
    next_id: u16,
    /// The request whose answer [`Self::request`] waits for.
    awaited: Option<u16>,
    /// Answers not yet collected, by request id.
    answers: Vec<(u16, Result<Reply, Error>)>,
    /// Requests whose answers nobody waits for (heartbeats).
    ignored: HashSet<u16>,
    events: VecDeque<EventRecord>,
    /// Highest event index seen from this boot.
    last_event: Option<u32>,
    clock: ClockMap,
    /// Request id of the heartbeat clock sample in flight, and when it left.
    sample: Option<(u16, u64)>,
    heartbeat_us: u64,
    last_request_us: u64,
    /// A link failure while [`Self::busy`] ran, for the next call to return.
    pending: Option<ClientError>,
    /// Device tick before which events are from an earlier attempt ([`Self::fence`]).
    fence_tick: u64,
    interrupt: Option<Arc<Interrupt>>,
    /// Those watching the run ([`Self::set_live`]), and when the link's counters were last
    /// told them (transport µs).
    live: Option<Arc<crate::live::Live>>,
    live_at: u64,
    /// The handshake is done: a `HandshakeRequired` from now on means the session was lost.
    open: bool,
    /// Faults the host cleared on this device, for the session to journal.
    cleared: Vec<FaultCause>,
    /// The protocol version and schema hash this client says Hello with.
    hello: (u16, u64),
    /// The boot nonce of the device that answered our Hello: a new link epoch with the same
    /// one is the same device run, which only wants Hello again ([`Self::reconnected`]).
    boot_nonce: Option<u32>,
    /// Request id of the Hello said again after a new link epoch, until it is answered.
    rehello: Option<u16>,
}

impl<T: Transport> Client<T> {
    /// Connects: synchronises the link, says Hello, checks protocol version and schema hash.
    /// `nonce` must differ each time the host program starts (e.g. random).
    pub fn connect(transport: T, nonce: u32) -> Result<Self, ClientError> {
        Self::connect_as(transport, nonce, PROTOCOL_VERSION, SCHEMA_HASH)
    }

    /// [`Self::connect`] claiming another version and schema (for tests of the mismatch path).
    pub fn connect_as(transport: T, nonce: u32, version: u16, schema: u64) -> Result<Self, ClientError> {
        let (client, compatible) = Self::connect_inner(transport, nonce, version, schema)?;
        if !compatible {
            return Err(client.incompatible());
        }
        Ok(client)
    }

    /// Connects for a firmware update: a device of another protocol version or schema is kept
    /// (it takes update commands all the same, their encoding being frozen); the flag says
    /// whether it speaks this host's protocol.
    pub fn connect_for_update(transport: T, nonce: u32) -> Result<(Self, bool), ClientError> {
        Self::connect_inner(transport, nonce, PROTOCOL_VERSION, SCHEMA_HASH)
    }

    /// [`Self::connect_for_update`] claiming another version and schema (for tests of the
    /// cross-version path).
    pub fn connect_for_update_as(
        transport: T,
        nonce: u32,
        version: u16,
        schema: u64,
    ) -> Result<(Self, bool), ClientError> {
        Self::connect_inner(transport, nonce, version, schema)
    }

    fn connect_inner(
        transport: T,
        nonce: u32,
        version: u16,
        schema: u64,
    ) -> Result<(Self, bool), ClientError> {
        let now = transport.now_us();
        let mut link = Link::new(Role::Initiator, LinkConfig { rto: RTO_US, rx_reserve: 0, nonce });
        link.connect(now);
        let mut client = Self {
            transport,
            link,
            info: unknown_info(),
            // Request ids start from the nonce, not at 1: after a reconnection the device sends
            // again the answers the last client had not acknowledged (the link is at-least-once
            // across epochs), and those must not match this client's first requests.
            next_id: (nonce ^ (nonce >> 16)) as u16,
            awaited: None,
            answers: Vec::new(),
            ignored: HashSet::new(),
            events: VecDeque::new(),
            last_event: None,
            clock: ClockMap::default(),
            sample: None,
            heartbeat_us: 200_000,
            last_request_us: now,
            pending: None,
            fence_tick: 0,
            interrupt: None,
            live: None,
            live_at: 0,
            open: false,
            cleared: Vec::new(),
            hello: (version, schema),
            boot_nonce: None,
            rehello: None,
        };
        let hello = Command::Hello { protocol_version: version, schema_hash: schema };
        let info = match client.request_timeout(hello, 3_000_000) {
            Ok(Reply::Hello(info)) => info,
            Ok(other) => return Err(client.protocol(format!("Hello answered with {other:?}"))),
            Err(e) => return Err(e),
        };
        client.info = info;
        // The device run that answered: the link's epoch is the one Hello was answered in.
        client.boot_nonce = Some(client.link.peer_boot());
        // Events the device resent before answering (what an earlier host left unacknowledged)
        // came before we knew whose they are.
        for e in &mut client.events {
            e.boot_id = info.boot_id;
        }
        if info.protocol_version != version || info.schema_hash != schema {
            return Ok((client, false));
        }
        client.open = true;
        // Heartbeats well inside the device's default timeout (1 s).
        client.sync_clock(8)?;
        Ok((client, true))
    }

    fn incompatible(&self) -> ClientError {
        ClientError::Incompatible {
            device: self.transport.describe(),
            device_version: self.info.protocol_version,
            device_schema: self.info.schema_hash,
        }
    }

    fn protocol(&self, detail: String) -> ClientError {
        ClientError::Protocol { device: self.transport.describe(), detail }
    }

    /// What the device said about itself.
    pub fn info(&self) -> &DeviceInfo {
        &self.info
    }

    /// The transport (to inspect a virtual device).
    pub fn transport(&self) -> &T {
        &self.transport
    }

    /// The transport, mutably.
    pub fn transport_mut(&mut self) -> &mut T {
        &mut self.transport
    }

    /// Gives the transport back (to reconnect over it after an unplug).
    pub fn into_transport(self) -> T {
        self.transport
    }

    /// Sends a heartbeat (a clock sample) whenever the host has been quiet for `us`; keep it
    /// well under the device's heartbeat timeout (a quarter, say).
    pub fn set_heartbeat_us(&mut self, us: u64) {
        self.heartbeat_us = us.max(1_000);
    }

    /// The host–device clock mapping.
    pub fn clock(&self) -> &ClockMap {
        &self.clock
    }

    /// From now on, `interrupt` stops the device: at the next turn of the link the client
    /// sends `EmergencyStop` and fails the call in progress ([`ClientError::Interrupted`]).
    pub fn set_interrupt(&mut self, interrupt: Arc<Interrupt>) {
        self.interrupt = Some(interrupt);
    }

    /// From now on `live` hears the link's counters, the clock mapping (4 times a second) and
    /// the device's faults.
    pub fn set_live(&mut self, live: Arc<crate::live::Live>) {
        live.set_device(&self.transport.describe(), self.info.boot_id);
        self.live = Some(live);
    }

    /// Those watching the run, if any ([`Self::set_live`]).
    pub fn live(&self) -> Option<&Arc<crate::live::Live>> {
        self.live.as_ref()
    }

    /// Whether a stop was asked of this client ([`Self::set_interrupt`]): from then on every
    /// call fails with [`ClientError::Interrupted`].
    pub fn interrupted(&self) -> Option<&Arc<Interrupt>> {
        self.interrupt.as_ref().filter(|i| i.requested())
    }

    /// Sends `EmergencyStop` as a datagram (acted on even if the reliable queue is stalled) and
    /// reliably, and waits briefly for its answer.
    pub fn emergency_stop(&mut self) -> Result<(), ClientError> {
        self.next_id = self.next_id.wrapping_add(1);
        let _ = self.link.send_datagram(HostMsg { id: self.next_id, command: Command::EmergencyStop });
        self.request_timeout(Command::EmergencyStop, 500_000).map(|_| ())
    }

    /// Runs `work` (a person at a prompt, frames written to disk, files read) on another
    /// thread while this one keeps the link alive: heartbeats, acknowledgements,
    /// retransmissions; events that arrive queue up as always. A device in real time would
    /// otherwise time the host out (`HeartbeatLost`) whenever the host is busy for longer than
    /// its heartbeat timeout. A link failure meanwhile is returned by the next call on the
    /// client. With a device that waits for the host ([`Transport::runs_alone`] false: the
    /// in-process virtual rig) `work` runs here, directly.
    pub fn busy<R: Send>(&mut self, work: impl FnOnce() -> R + Send) -> R {
        if !self.transport.runs_alone() {
            return work();
        }
        std::thread::scope(|scope| {
            let job = scope.spawn(work);
            while !job.is_finished() {
                if self.pending.is_some() {
                    // The link is gone: nothing to keep alive, only the work to wait for.
                    std::thread::sleep(std::time::Duration::from_micros(BUSY_POLL_US));
                    continue;
                }
                let deadline = self.transport.now_us().saturating_add(BUSY_POLL_US);
                if let Err(e) = self.pump(deadline) {
                    self.pending = Some(e);
                }
            }
            job.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic))
        })
    }

    /// The device's tick now, measured by a round trip; events stamped earlier belong to what
    /// came before (an earlier host's run, a cleared fault) and [`Self::run_sequence`] does not
    /// act on them. Returns the tick.
    pub fn fence(&mut self) -> Result<u64, ClientError> {
        match self.request(Command::GetClock)? {
            Reply::Clock { tick } => {
                self.fence_tick = self.fence_tick.max(tick);
                Ok(tick)
            }
            other => Err(self.protocol(format!("GetClock answered with {other:?}"))),
        }
    }

    /// Whether `e` happened before the last [`Self::fence`].
    pub fn before_fence(&self, e: &EventRecord) -> bool {
        event_tick(&e.event).is_some_and(|t| t < self.fence_tick)
    }

    /// Sends a command and waits for its answer (up to 2 s); a refusal is an error naming the
    /// command.
    pub fn request(&mut self, command: Command) -> Result<Reply, ClientError> {
        self.request_timeout(command, 2_000_000)
    }

    /// [`Self::request`] with its own deadline, for commands the device takes long over (a
    /// flash erase).
    pub fn request_within(&mut self, command: Command, timeout_us: u64) -> Result<Reply, ClientError> {
        self.request_timeout(command, timeout_us)
    }

    fn request_timeout(&mut self, command: Command, timeout_us: u64) -> Result<Reply, ClientError> {
        let what = command_name(&command);
        let id = self.send(command, timeout_us)?;
        self.awaited = Some(id);
        let deadline = self.transport.now_us().saturating_add(timeout_us);
        loop {
            if let Some(i) = self.answers.iter().position(|(a, _)| *a == id) {
                let (_, result) = self.answers.remove(i);
                self.awaited = None;
                return result.map_err(|error| ClientError::Refused {
                    device: self.transport.describe(),
                    command: what,
                    error,
                });
            }
            if self.transport.now_us() >= deadline {
                self.awaited = None;
                return Err(ClientError::Timeout {
                    device: self.transport.describe(),
                    what,
                    waited_ms: timeout_us / 1000,
                });
            }
            self.pump(deadline)?;
        }
    }

    /// Queues a command (waiting for room in the link window); returns its request id.
    fn send(&mut self, command: Command, timeout_us: u64) -> Result<u16, ClientError> {
        // Nothing is queued once a stop is asked for: a command behind the stop (a ClearFault,
        // an Arm) would otherwise reach the device after it.
        self.obey_interrupt()?;
        self.next_id = self.next_id.wrapping_add(1);
        let id = self.next_id;
        let deadline = self.transport.now_us().saturating_add(timeout_us);
        let mut msg = HostMsg { id, command };
        loop {
            match self.link.send(msg) {
                Ok(()) => break,
                Err(e) => {
                    msg = e.into_inner();
                    if self.transport.now_us() >= deadline {
                        return Err(ClientError::Timeout {
                            device: self.transport.describe(),
                            what: "room in the link window".into(),
                            waited_ms: timeout_us / 1000,
                        });
                    }
                    self.pump(deadline)?;
                }
            }
        }
        self.last_request_us = self.transport.now_us();
        Ok(id)
    }

    /// A stop asked for ([`Interrupt`]): sent (again, until the device answers one), and the
    /// call fails.
    fn obey_interrupt(&mut self) -> Result<(), ClientError> {
        let Some(stop) = self.interrupt.clone().filter(|i| i.requested()) else { return Ok(()) };
        if !stop.answered() {
            // The stop's own round trip runs with the interrupt set aside (it would recurse).
            self.interrupt = None;
            let answered = self.emergency_stop().is_ok();
            self.interrupt = Some(stop.clone());
            stop.stopped.store(true, Ordering::SeqCst);
            stop.answered.fetch_or(answered, Ordering::SeqCst);
        }
        Err(ClientError::Interrupted { device: self.transport.describe(), answered: stop.answered() })
    }

    /// Moves bytes both ways once, waiting at most until `deadline` for something to arrive.
    fn pump(&mut self, deadline: u64) -> Result<(), ClientError> {
        if let Some(e) = self.pending.take() {
            return Err(e);
        }
        self.obey_interrupt()?;
        let mut out = [0u8; MAX_FRAME];
        let now = self.transport.now_us();
        self.heartbeat(now)?;
        while let Some(n) = self.link.poll_transmit(now, &mut out) {
            let device = self.transport.describe();
            self.transport.send(&out[..n]).map_err(|error| ClientError::Io { device, error })?;
        }
        // A stop may be asked from another thread (the control socket) with no signal to cut
        // the wait short: look at least every STOP_POLL_US.
        let watch = self.interrupt.as_ref().map(|_| now + STOP_POLL_US);
        let wake = [
            Some(deadline),
            self.link.next_deadline(),
            Some(self.last_request_us + self.heartbeat_us),
            watch,
        ]
        .into_iter()
        .flatten()
        .min()
        .unwrap_or(deadline)
        .max(now + 1);
        let mut buf = [0u8; 4096];
        let device = self.transport.describe();
        let n = match self.transport.recv(&mut buf, wake) {
            // A signal (Ctrl-C) cut the wait short: nothing arrived, the device is still there.
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => 0,
            other => other.map_err(|error| ClientError::Io { device, error })?,
        };
        let at = self.transport.now_us();
        let mut got = Vec::new();
        self.link.receive_all(&buf[..n], at, |d| got.push(d));
        for d in got {
            self.deliver(d, at)?;
        }
        if let Some(live) = self.live.as_ref().filter(|_| at >= self.live_at + LIVE_EVERY_US) {
            live.link(self.link.stats(), &self.clock);
            self.live_at = at;
        }
        Ok(())
    }

    /// Keeps the device's watchdog fed, and the clock mapping fresh: a heartbeat is a
    /// `GetClock` whose answer is one more clock sample.
    fn heartbeat(&mut self, now: u64) -> Result<(), ClientError> {
        if self.sample.is_some() || now < self.last_request_us + self.heartbeat_us || self.link.free() == 0 {
            return Ok(());
        }
        self.next_id = self.next_id.wrapping_add(1);
        let id = self.next_id;
        if self.link.send(HostMsg { id, command: Command::GetClock }).is_ok() {
            self.ignored.insert(id);
            self.sample = Some((id, now));
            self.last_request_us = now;
        }
        Ok(())
    }

    fn deliver(&mut self, d: Delivery<DeviceMsg>, at: u64) -> Result<(), ClientError> {
        match d {
            // Any request (a heartbeat most likely) refused for want of a Hello: the device has
            // forgotten us. Waiting on would hang: its events now come from another boot.
            Delivery::Message(DeviceMsg::Response { result: Err(Error::HandshakeRequired), .. })
                if self.open =>
            {
                return Err(ClientError::SessionLost { device: self.transport.describe() });
            }
            Delivery::Message(DeviceMsg::Response { id, result }) if self.rehello == Some(id) => {
                self.rehello = None;
                return self.rehello_answered(result);
            }
            Delivery::Message(DeviceMsg::Response { id, result }) => {
                if let Some((sid, sent)) = self.sample {
                    if sid == id {
                        self.sample = None;
                        if let Ok(Reply::Clock { tick }) = result {
                            self.clock.add(sent, at, tick);
                        }
                    }
                }
                // Anything else answers a request nobody waits for any more: one that timed
                // out, or one of an earlier client's, sent again after a reconnection.
                if !self.ignored.remove(&id) && self.awaited == Some(id) {
                    self.answers.push((id, result));
                }
            }
            Delivery::Message(DeviceMsg::Event { index, event }) => {
                // After a reconnection the device resends what we had not acknowledged.
                if self.last_event.is_some_and(|last| index <= last) {
                    return Ok(());
                }
                self.last_event = Some(index);
                let host_us = event_tick(&event).and_then(|t| self.clock.host_us(t));
                if let Some(live) = &self.live {
                    match &event {
                        Event::Fault { cause, .. } => {
                            live.device(crate::live::DeviceState::Faulted, Some(describe_fault(cause)))
                        }
                        Event::State { state, armed, .. } => live.reported(state, *armed),
                        _ => {}
                    }
                }
                self.events.push_back(EventRecord { index, boot_id: self.info.boot_id, event, host_us });
            }
            Delivery::Message(DeviceMsg::Rejected { seq, reason }) => {
                return Err(self.protocol(format!("the device could not decode our frame {seq}: {reason:?}")));
            }
            Delivery::Incompatible { protocol_version, schema_hash, .. } => {
                self.info.protocol_version = protocol_version;
                self.info.schema_hash = schema_hash;
                return Err(self.incompatible());
            }
            Delivery::Rejected { seq, reason } => {
                return Err(self.protocol(format!("undecodable message {seq} from the device: {reason:?}")));
            }
            // The device sends none; one that came anyway is not acted on.
            Delivery::Datagram(_) => self.link.datagram_dropped(),
            Delivery::Connected { .. } => self.reconnected()?,
        }
        Ok(())
    }

    /// A new link epoch started. Once the handshake is done that is a reconnection under a
    /// running session: a `Resync`, or the sign that a stale `Sync` of an earlier host run
    /// knocked the device's link back to half-open (§4.6.1). The device returns to
    /// `AwaitingHello` at every new epoch and keeps everything else (§6.3), so if it is the
    /// same device run (the same boot nonce, which differs at every device start) this says
    /// Hello again, ahead of every request still queued (they are sent again in the new epoch
    /// and would otherwise be refused for want of it), and the session goes on. Another boot
    /// nonce: the device restarted and has lost the session.
    fn reconnected(&mut self) -> Result<(), ClientError> {
        let Some(boot) = self.boot_nonce else {
            // Still connecting: the Hello in the queue is sent again in the new epoch.
            return Ok(());
        };
        if self.link.peer_boot() != boot {
            return Err(ClientError::SessionLost { device: self.transport.describe() });
        }
        self.next_id = self.next_id.wrapping_add(1);
        let id = self.next_id;
        let (protocol_version, schema_hash) = self.hello;
        let hello = HostMsg { id, command: Command::Hello { protocol_version, schema_hash } };
        if self.link.send_first(hello).is_err() {
            // A full window: the requests queued would reach the device before the Hello and
            // be refused. Only a new connection puts that right.
            return Err(ClientError::SessionLost { device: self.transport.describe() });
        }
        self.rehello = Some(id);
        Ok(())
    }

    /// The answer to the Hello said again after a new link epoch: the same device run, as its
    /// boot nonce said, describes itself as before.
    fn rehello_answered(&mut self, result: Result<Reply, Error>) -> Result<(), ClientError> {
        match result {
            Ok(Reply::Hello(info)) if info.boot_id == self.info.boot_id => Ok(()),
            Ok(Reply::Hello(_)) => Err(ClientError::SessionLost { device: self.transport.describe() }),
            other => Err(self.protocol(format!("Hello (after a new link epoch) answered with {other:?}"))),
        }
    }

    /// Measures the clock mapping with `n` `GetClock` round trips.
    pub fn sync_clock(&mut self, n: usize) -> Result<(), ClientError> {
        for _ in 0..n {
            let sent = self.transport.now_us();
            if let Reply::Clock { tick } = self.request(Command::GetClock)? {
                let got = self.transport.now_us();
                self.clock.add(sent, got, tick);
            }
        }
        Ok(())
    }

    /// The events received and not yet taken, oldest first.
    pub fn queued(&self) -> &VecDeque<EventRecord> {
        &self.events
    }

    /// The host end's link counters (frames, retransmissions, rejected frames).
    pub fn link_stats(&self) -> &lightrig_protocol::link::LinkStats {
        self.link.stats()
    }

    /// Notes that the host cleared the device's latched fault `cause` (for the journal).
    pub fn note_cleared(&mut self, cause: FaultCause) {
        self.cleared.push(cause);
    }

    /// Takes the faults cleared since the last call, oldest first (to journal them).
    pub fn take_cleared(&mut self) -> Vec<FaultCause> {
        std::mem::take(&mut self.cleared)
    }

    /// Takes every event received so far (to journal them).
    pub fn take_events(&mut self) -> Vec<EventRecord> {
        self.events.drain(..).collect()
    }

    /// Runs the link until more than `n` events are queued or `timeout_us` has passed;
    /// returns whether they are.
    pub fn wait_for_events(&mut self, n: usize, timeout_us: u64) -> Result<bool, ClientError> {
        let deadline = self.transport.now_us().saturating_add(timeout_us);
        while self.events.len() <= n && self.transport.now_us() < deadline {
            self.pump(deadline)?;
        }
        Ok(self.events.len() > n)
    }

    /// The next event, waiting up to `timeout_us`.
    pub fn next_event(&mut self, timeout_us: u64) -> Result<Option<EventRecord>, ClientError> {
        let deadline = self.transport.now_us().saturating_add(timeout_us);
        while self.events.is_empty() && self.transport.now_us() < deadline {
            self.pump(deadline)?;
        }
        Ok(self.events.pop_front())
    }

    /// Runs the link for `us` microseconds (events queue up).
    pub fn idle(&mut self, us: u64) -> Result<(), ClientError> {
        let deadline = self.transport.now_us().saturating_add(us);
        while self.transport.now_us() < deadline {
            self.pump(deadline)?;
        }
        Ok(())
    }

    /// Streams `items` as sequence `id`, keeping the device's buffer topped up under its
    /// credit, starts it at `start` once the buffer is full (or everything is loaded), and
    /// hands every event to `on_event` until the sequence is done. A fault ends it with
    /// [`ClientError::Fault`].
    pub fn run_sequence(
        &mut self,
        id: u32,
        items: impl IntoIterator<Item = Item>,
        start: StartAt,
        mut on_event: impl FnMut(&EventRecord),
    ) -> Result<SequenceOutcome, ClientError> {
        let capacity = u32::from(self.info.capabilities.sequence_buffer);
        // A fault from before this sequence (an earlier attempt's, already cleared) may still
        // arrive: it is handed on, not acted upon.
        self.fence()?;
        let mut items = items.into_iter().peekable();
        let (mut sent, mut executed, mut chunk) = (0u32, 0u32, 0u32);
        let mut started = false;
        loop {
            // Credit: what the device has room for, from its last report.
            while items.peek().is_some() && capacity - (sent - executed) >= MAX_CHUNK_ITEMS as u32 {
                let batch: heapless::Vec<Item, MAX_CHUNK_ITEMS> =
                    items.by_ref().take(MAX_CHUNK_ITEMS).collect();
                let n = batch.len() as u32;
                let last = items.peek().is_none();
                let reply =
                    self.request(Command::SequenceLoad(Chunk { sequence: id, chunk, last, items: batch }))?;
                if let Reply::Buffer(b) = reply {
                    executed = executed.max(b.executed);
                }
                sent += n;
                chunk += 1;
            }
            if chunk == 0 {
                // An empty sequence still needs its (empty, last) chunk.
                let empty = Chunk { sequence: id, chunk: 0, last: true, items: heapless::Vec::new() };
                self.request(Command::SequenceLoad(empty))?;
                chunk = 1;
            }
            if !started {
                self.request(Command::SequenceStart { sequence: id, at: start })?;
                started = true;
            }
            let Some(e) = self.next_event(1_000_000)? else { continue };
            on_event(&e);
            match e.event {
                Event::Buffer(b) if b.sequence == id => executed = executed.max(b.executed),
                // Sequence ids repeat across host sessions (step × 1000 + attempt): an earlier
                // session's end of the same id is stamped before the fence.
                Event::SequenceDone { sequence, items, tick }
                    if sequence == id && tick >= self.fence_tick =>
                {
                    return Ok(SequenceOutcome { items, tick });
                }
                Event::Fault { cause, tick } if tick >= self.fence_tick => {
                    return Err(ClientError::Fault { device: self.transport.describe(), cause, tick });
                }
                _ => {}
            }
        }
    }
}

/// Stands in for the device's description until it answers Hello.
fn unknown_info() -> DeviceInfo {
    use lightrig_protocol::session::{BoardId, Capabilities, ResetCause, Version};
    DeviceInfo {
        protocol_version: 0,
        schema_hash: 0,
        firmware: Version { major: 0, minor: 0, patch: 0 },
        board: BoardId::Other(0),
        serial: 0,
        tick_hz: 1,
        reset_cause: ResetCause::Unknown,
        boot_id: 0,
        capabilities: Capabilities {
            galvos: 0,
            lasers: 0,
            steppers: 0,
            filter_wheels: 0,
            voice_coils: 0,
            partials_per_coil: 0,
            cameras: 0,
            sequence_buffer: 0,
            event_queue: 0,
            link_window: 0,
            max_packet: 0,
        },
    }
}

/// The device tick an event carries, if any.
pub fn event_tick(e: &Event) -> Option<u64> {
    Some(match e {
        Event::Trigger(t) => t.tick,
        Event::Exposure { tick, .. }
        | Event::MoveDone { tick, .. }
        | Event::Homed { tick, .. }
        | Event::Switch { tick, .. }
        | Event::LaserReady { tick, .. }
        | Event::Marker { tick, .. }
        | Event::Underrun { tick, .. }
        | Event::SequenceDone { tick, .. }
        | Event::Fault { tick, .. }
        | Event::State { tick, .. }
        | Event::Log { tick, .. } => *tick,
        Event::Buffer(_) => return None,
    })
}

/// A command's name for messages.
fn command_name(c: &Command) -> String {
    let s = format!("{c:?}");
    let end = s.find([' ', '(', '{']).unwrap_or(s.len());
    s[..end].to_string()
}
