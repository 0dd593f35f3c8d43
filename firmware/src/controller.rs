//! The device endpoint: link, handshake gate, request dispatch, and the event stream. The
//! behaviour behind the commands is the [`Rig`]'s.
//!
//! A board's run loop, in outline:
//! ```text
//! loop {
//!     wait until controller.next_deadline(), a received byte or an input edge;
//!     controller.receive(bytes);            // requests are handled at once
//!     controller.poll();                    // due work, then events into the link
//!     while let Some(n) = controller.poll_transmit(&mut frame) { uart.write(&frame[..n]) }
//! }
//! ```

use heapless::Deque;
use lightrig_protocol::event::DeviceState;
use lightrig_protocol::link::{Delivery, Link, LinkConfig, Role};
use lightrig_protocol::message::Status;
use lightrig_protocol::session::DeviceInfo;
use lightrig_protocol::update::{UpdateCommand, UpdateError};
use lightrig_protocol::{
    Command, DeviceMsg, Error, HostMsg, Reply, MAX_FRAME, PROTOCOL_VERSION, SCHEMA_HASH,
};

use crate::hal::Board;
use crate::rig::Rig;
use crate::update::Updater;

/// Frames in flight per direction.
pub const LINK_WINDOW: usize = 8;

/// Seconds a swapped-in firmware has to be confirmed by a host (`Update(Confirm)`) before the
/// device resets itself, and the bootloader swaps the old image back.
pub const CONFIRM_WINDOW_S: u64 = 60;

/// The device's free-running 64-bit tick counter.
pub trait Clock {
    /// Ticks since start, at `DeviceInfo::tick_hz`.
    fn now(&self) -> u64;
}

/// The controller's clock from embassy-time (feature `embassy`): `DeviceInfo::tick_hz` must be
/// embassy-time's tick rate. A run loop sleeps with
/// `embassy_time::Timer::at(Instant::from_ticks(controller.next_deadline()))`.
#[cfg(feature = "embassy")]
#[derive(Debug, Clone, Copy, Default)]
pub struct EmbassyClock;

#[cfg(feature = "embassy")]
impl Clock for EmbassyClock {
    fn now(&self) -> u64 {
        embassy_time::Instant::now().as_ticks()
    }
}

/// The controller: owns the link and the rig, answers the host, streams events.
pub struct Controller<C: Clock, B: Board> {
    clock: C,
    info: DeviceInfo,
    link: Link<DeviceMsg, HostMsg, LINK_WINDOW>,
    /// Answers produced but not yet accepted by the link (its window was full).
    outbox: Deque<DeviceMsg, 4>,
    session: Session,
    rig: Rig<B>,
    /// Number of the next event (`DeviceMsg::Event::index`).
    event_index: u32,
    last_heartbeat: u64,
    /// Datagrams dropped for carrying anything but `EmergencyStop`.
    ignored_datagrams: u32,
    /// Firmware update in progress.
    update: Updater,
    /// Tick by which a swapped-in firmware must be confirmed.
    confirm_by: Option<u64>,
    /// A swapped-in firmware was not confirmed in time: the board should reset (rollback).
    rollback_requested: bool,
}

/// Where the host session stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Session {
    /// No Hello since the link (re)connected.
    AwaitingHello,
    /// The last Hello did not match; commands are refused with this error.
    Refused(Error),
    /// Handshake done.
    Open,
}

impl<C: Clock, B: Board> Controller<C, B> {
    /// A controller for `board` that describes itself with `info` (its `protocol_version`,
    /// `schema_hash`, link window, buffer and queue sizes are overwritten with this build's).
    /// `rto` is in ticks.
    pub fn new(clock: C, board: B, mut info: DeviceInfo, rto: u64) -> Self {
        info.protocol_version = PROTOCOL_VERSION;
        info.schema_hash = SCHEMA_HASH;
        info.capabilities.link_window = LINK_WINDOW as u8;
        info.capabilities.sequence_buffer = crate::rig::SEQUENCE_BUFFER as u16;
        info.capabilities.event_queue = crate::rig::EVENT_QUEUE as u16;
        // Keep one send slot free per request in flight so every request can be answered. The
        // boot id doubles as the link's boot nonce: it must differ at every start.
        let link = Link::new(Role::Responder, LinkConfig { rto, rx_reserve: 1, nonce: info.boot_id });
        let last_heartbeat = clock.now();
        let mut rig = Rig::new(board, info.capabilities, info.tick_hz);
        let unconfirmed = rig.board_mut().unconfirmed().unwrap_or(false);
        let window = CONFIRM_WINDOW_S.saturating_mul(u64::from(info.tick_hz));
        let confirm_by = unconfirmed.then(|| last_heartbeat.saturating_add(window));
        Self {
            clock,
            info,
            link,
            outbox: Deque::new(),
            session: Session::AwaitingHello,
            rig,
            event_index: 0,
            last_heartbeat,
            ignored_datagrams: 0,
            update: Updater::default(),
            confirm_by,
            rollback_requested: false,
        }
    }

    /// Current state: a latched fault first, then the session, then the rig.
    pub fn state(&self) -> DeviceState {
        match (self.rig.fault(), self.session) {
            (Some(cause), _) => DeviceState::Faulted(cause),
            (None, Session::Open) => self.rig.state(),
            (None, _) => DeviceState::AwaitingHello,
        }
    }

    /// The rig behind the protocol.
    pub fn rig(&self) -> &Rig<B> {
        &self.rig
    }

    /// The rig, mutably (simulations change inputs through its board).
    pub fn rig_mut(&mut self) -> &mut Rig<B> {
        &mut self.rig
    }

    /// Does the rig's work due by now and moves its events into the link.
    pub fn poll(&mut self) {
        let now = self.clock.now();
        self.rig.poll(now);
        if self.confirm_by.is_some_and(|t| now >= t) {
            self.confirm_by = None;
            // Nobody confirmed the new firmware: back to the old one.
            if self.rig.board_mut().unconfirmed().unwrap_or(false) {
                self.rollback_requested = true;
            }
        }
        self.pump_events();
    }

    /// Whether the board should reset now: an update is ready to be swapped in (and the host
    /// has the answer that says so), or a swapped-in firmware was not confirmed in time. The
    /// board's run loop resets the MCU; the bootloader does the rest.
    pub fn wants_reset(&self) -> bool {
        // Derived from the updater, not latched: a `Cancel` that reaches the device before it
        // resets unmarks the image, and then nothing is left to reset for.
        (self.update.ready() || self.rollback_requested) && self.link.unacked() == 0
    }

    /// Tick of the last command from the host.
    pub fn last_heartbeat(&self) -> u64 {
        self.last_heartbeat
    }

    /// Datagrams dropped unanswered for carrying anything but `EmergencyStop` (also counted,
    /// with undecodable ones, in the link's `datagrams_dropped`, which `GetStatus` reports).
    pub fn ignored_datagrams(&self) -> u32 {
        self.ignored_datagrams
    }

    /// The link, for its counters.
    pub fn link(&self) -> &Link<DeviceMsg, HostMsg, LINK_WINDOW> {
        &self.link
    }

    /// Feeds bytes received from the host.
    pub fn receive(&mut self, mut data: &[u8]) {
        while !data.is_empty() {
            self.flush_outbox();
            let now = self.clock.now();
            let (used, delivery) = self.link.receive(data, now);
            data = &data[used..];
            match delivery {
                Some(Delivery::Message(msg)) => {
                    let result = self.handle(&msg.command);
                    self.answer(DeviceMsg::Response { id: msg.id, result });
                }
                Some(Delivery::Datagram(msg)) => {
                    // Only an emergency stop may arrive unsequenced (it must act even while the
                    // reliable queue is stalled); anything else as a datagram could be a replay
                    // (a CRC-valid frame needs no link state) and is dropped unanswered.
                    if msg.command == Command::EmergencyStop {
                        let _ = self.handle(&msg.command);
                    } else {
                        // Counted where the host sees it too (`Status.link.datagrams_dropped`).
                        self.ignored_datagrams = self.ignored_datagrams.wrapping_add(1);
                        self.link.datagram_dropped();
                    }
                }
                Some(Delivery::Rejected { seq, reason }) => {
                    self.answer(DeviceMsg::Rejected { seq, reason });
                }
                Some(Delivery::Incompatible { seq, .. }) => {
                    // Host messages have no handshake prefix; treat it as undecodable.
                    let reason = lightrig_protocol::frame::FrameError::BadPayload;
                    self.answer(DeviceMsg::Rejected { seq, reason });
                }
                Some(Delivery::Connected { .. }) => {
                    // A new host session must say Hello again (a latched fault stays).
                    self.session = Session::AwaitingHello;
                }
                None => {}
            }
        }
    }

    /// Writes the next frame for the host into `out`; `None` when nothing is due.
    pub fn poll_transmit(&mut self, out: &mut [u8; MAX_FRAME]) -> Option<usize> {
        self.pump_events();
        self.link.poll_transmit(self.clock.now(), out)
    }

    /// When `poll` / `poll_transmit` next have work even if nothing arrives.
    pub fn next_deadline(&self) -> Option<u64> {
        [self.link.next_deadline(), self.rig.next_due(), self.confirm_by].into_iter().flatten().min()
    }

    /// Moves rig events into the link while it has room, keeping the slot that answers the
    /// next request (`rx_reserve`). Events wait in the rig's queue meanwhile; the rig faults
    /// with `EventOverflow` if the host stops acknowledging for that long.
    fn pump_events(&mut self) {
        self.flush_outbox();
        while self.outbox.is_empty() && self.link.free() > 1 {
            let Some((dropped, event)) = self.rig.pop_event_after_gap() else { break };
            // Events the rig had to drop use up their numbers: the host sees the gap.
            self.event_index = self.event_index.wrapping_add(dropped);
            let index = self.event_index;
            self.event_index = self.event_index.wrapping_add(1);
            if let Err(e) = self.link.send(DeviceMsg::Event { index, event }) {
                let _ = self.outbox.push_back(e.into_inner());
            }
        }
    }

    fn answer(&mut self, msg: DeviceMsg) {
        if let Err(e) = self.link.send(msg) {
            // `rx_reserve` guarantees room for one answer per accepted request, so the outbox
            // only ever holds answers that raced with queued events.
            let _ = self.outbox.push_back(e.into_inner());
        }
    }

    fn flush_outbox(&mut self) {
        while let Some(msg) = self.outbox.pop_front() {
            if let Err(e) = self.link.send(msg) {
                let _ = self.outbox.push_front(e.into_inner());
                break;
            }
        }
    }

    fn handle(&mut self, command: &Command) -> Result<Reply, Error> {
        let now = self.clock.now();
        // Commands act at `now`: first catch up with everything due before it.
        self.rig.poll(now);
        match *command {
            Command::Hello { protocol_version, schema_hash } => {
                // Always describe ourselves (the answer's prefix is frozen, so a host of any
                // version can read it and explain a mismatch); open the session only when
                // both sides speak the same protocol.
                self.session = if protocol_version != PROTOCOL_VERSION {
                    Session::Refused(Error::VersionMismatch {
                        device: PROTOCOL_VERSION,
                        host: protocol_version,
                    })
                } else if schema_hash != SCHEMA_HASH {
                    Session::Refused(Error::SchemaMismatch { device: SCHEMA_HASH, host: schema_hash })
                } else {
                    Session::Open
                };
                self.last_heartbeat = now;
                if self.session == Session::Open {
                    self.rig.host_seen(now, true);
                }
                return Ok(Reply::Hello(self.info));
            }
            // Safety commands act whatever the session state.
            Command::EmergencyStop => {
                self.rig.emergency_stop(now);
                return Ok(Reply::Done);
            }
            Command::Disarm => {
                self.rig.disarm(now);
                return Ok(Reply::Done);
            }
            _ => {}
        }
        match (self.session, command) {
            (Session::AwaitingHello, _) => return Err(Error::HandshakeRequired),
            // A host of another version may still update the firmware (the update path's
            // encoding is frozen).
            (Session::Refused(_), Command::Update(cmd)) => {
                // Heard from, but not watched: this host runs no acquisition.
                self.last_heartbeat = now;
                self.rig.host_seen(now, false);
                return self.update(cmd, now);
            }
            (Session::Refused(e), _) => return Err(e),
            (Session::Open, _) => {}
        }
        self.last_heartbeat = now;
        self.rig.host_seen(now, true);
        let moves_or_lights = matches!(
            command,
            Command::Arm { .. }
                | Command::Home(_)
                | Command::Immediate(_)
                | Command::SequenceLoad(_)
                | Command::SequenceStart { .. }
        );
        if moves_or_lights && self.update.in_progress() {
            return Err(Error::Update(UpdateError::InProgress));
        }
        let rig = &mut self.rig;
        match command {
            Command::GetClock => Ok(Reply::Clock { tick: now }),
            Command::Heartbeat => Ok(Reply::Done),
            Command::GetStatus => Ok(Reply::Status(Status {
                state: self.state(),
                armed: self.rig.armed(),
                lasers_on: self.rig.lasers_on(),
                tick: now,
                buffer: self.rig.buffer(),
                unacked: self.link.unacked() as u16,
                link: *self.link.stats(),
            })),
            Command::ClearFault => rig.clear_fault(now).map(|()| Reply::Done),
            Command::Configure(item) => {
                item.validate(&self.info).map_err(Error::InvalidConfig)?;
                rig.configure(item, now).map(|()| Reply::Done)
            }
            Command::Arm { lasers } => rig.arm(*lasers, now).map(|()| Reply::Done),
            Command::Home(axis) => rig.home(*axis, now).map(|()| Reply::Done),
            Command::Immediate(action) => rig.immediate(action, now).map(|()| Reply::Done),
            Command::SequenceLoad(chunk) => rig.load(chunk).map(Reply::Buffer),
            Command::SequenceStart { sequence, at } => rig.start(*sequence, *at, now).map(|()| Reply::Done),
            Command::SequenceAbort { sequence } => rig.abort(*sequence, now).map(|()| Reply::Done),
            Command::Update(cmd) => self.update(cmd, now),
            // Answered above, before the session check.
            Command::Hello { .. } | Command::EmergencyStop | Command::Disarm => Ok(Reply::Done),
        }
    }

    /// A firmware update command. An update begins only with no sequence running; it disarms
    /// the lasers and stops the motors: nothing moves or lights until it ends (a reset, or
    /// `Cancel`).
    fn update(&mut self, cmd: &UpdateCommand, now: u64) -> Result<Reply, Error> {
        let board = self.info.board;
        if let UpdateCommand::Begin(image) = cmd {
            if let state @ DeviceState::Running { .. } = self.rig.state() {
                return Err(Error::InvalidState(state));
            }
            // An image this board cannot take changes nothing; one it can stops the rig first.
            Updater::check_begin(image, self.rig.board(), board).map_err(Error::Update)?;
            self.rig.disarm(now);
            self.rig.stop_motion(now);
        }
        let status = self.update.handle(cmd, self.rig.board_mut(), board).map_err(Error::Update)?;
        // A Ready image is swapped in at the reset that follows the answer (`wants_reset`).
        if let UpdateCommand::Confirm = cmd {
            self.confirm_by = None;
        }
        Ok(Reply::Update(status))
    }

    /// The device's self-description.
    pub fn info(&self) -> &DeviceInfo {
        &self.info
    }
}
