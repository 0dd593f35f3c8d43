//! The device endpoint: link, handshake gate, request dispatch.

use heapless::Deque;
use lightrig_protocol::event::{DeviceState, FaultCause};
use lightrig_protocol::link::{Delivery, Link, LinkConfig, Role};
use lightrig_protocol::message::Status;
use lightrig_protocol::session::DeviceInfo;
use lightrig_protocol::{
    Command, DeviceMsg, Error, HostMsg, Reply, MAX_FRAME, PROTOCOL_VERSION, SCHEMA_HASH,
};

/// Frames in flight per direction.
pub const LINK_WINDOW: usize = 8;

/// The device's free-running 64-bit tick counter.
pub trait Clock {
    /// Ticks since start, at `DeviceInfo::tick_hz`.
    fn now(&self) -> u64;
}

/// The controller: owns the link and answers the host.
pub struct Controller<C: Clock> {
    clock: C,
    info: DeviceInfo,
    link: Link<DeviceMsg, HostMsg, LINK_WINDOW>,
    /// Answers produced but not yet accepted by the link (its window was full).
    outbox: Deque<DeviceMsg, 4>,
    session: Session,
    /// A latched fault; survives reconnections until `ClearFault`.
    fault: Option<FaultCause>,
    last_heartbeat: u64,
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

impl<C: Clock> Controller<C> {
    /// A controller that describes itself with `info` (its `protocol_version` and
    /// `schema_hash` are overwritten with this build's). `rto` is in ticks.
    pub fn new(clock: C, mut info: DeviceInfo, rto: u64) -> Self {
        info.protocol_version = PROTOCOL_VERSION;
        info.schema_hash = SCHEMA_HASH;
        info.capabilities.link_window = LINK_WINDOW as u8;
        // Keep one send slot free per request in flight so every request can be answered. The
        // boot id doubles as the link's boot nonce: it must differ at every start.
        let link = Link::new(Role::Responder, LinkConfig { rto, rx_reserve: 1, nonce: info.boot_id });
        let last_heartbeat = clock.now();
        Self {
            clock,
            info,
            link,
            outbox: Deque::new(),
            session: Session::AwaitingHello,
            fault: None,
            last_heartbeat,
        }
    }

    /// Current state: a latched fault first, then the session.
    pub fn state(&self) -> DeviceState {
        match (self.fault, self.session) {
            (Some(cause), _) => DeviceState::Faulted(cause),
            (None, Session::Open) => DeviceState::Ready,
            (None, _) => DeviceState::AwaitingHello,
        }
    }

    /// Tick of the last command from the host.
    pub fn last_heartbeat(&self) -> u64 {
        self.last_heartbeat
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
                    // Datagrams carry urgent, idempotent commands; they get no answer.
                    let _ = self.handle(&msg.command);
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
        self.flush_outbox();
        self.link.poll_transmit(self.clock.now(), out)
    }

    /// When the link next needs `poll_transmit` even if nothing arrives.
    pub fn next_deadline(&self) -> Option<u64> {
        self.link.next_deadline()
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
                return Ok(Reply::Hello(self.info));
            }
            // Safety commands act whatever the session state.
            Command::EmergencyStop => {
                self.fault = Some(FaultCause::EmergencyStop);
                return Ok(Reply::Done);
            }
            _ => {}
        }
        match self.session {
            Session::AwaitingHello => return Err(Error::HandshakeRequired),
            Session::Refused(e) => return Err(e),
            Session::Open => {}
        }
        self.last_heartbeat = now;
        match command {
            Command::GetClock => Ok(Reply::Clock { tick: now }),
            Command::Heartbeat => Ok(Reply::Done),
            Command::GetStatus => Ok(Reply::Status(Status {
                state: self.state(),
                armed: 0,
                lasers_on: 0,
                tick: now,
                buffer: None,
                unacked: self.link.unacked() as u16,
                link: *self.link.stats(),
            })),
            Command::ClearFault => {
                self.fault = None;
                Ok(Reply::Done)
            }
            Command::Configure(item) => {
                item.validate(&self.info).map_err(Error::InvalidConfig)?;
                Err(Error::Unsupported)
            }
            // The rest moves hardware: refused while a fault is latched, and not implemented by
            // this firmware slice otherwise.
            _ => Err(self.fault.map_or(Error::Unsupported, Error::Faulted)),
        }
    }

    /// The device's self-description.
    pub fn info(&self) -> &DeviceInfo {
        &self.info
    }
}
