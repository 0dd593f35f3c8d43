//! The reliable link: exactly-once, in-order delivery over a lossy byte stream, both ways,
//! within a link epoch (across a reconnection, unacknowledged messages are sent again, so
//! delivery is at-least-once there: requests carry ids and events indices for that).
//!
//! Each packet starts with a [`Header`]. Sequenced `Data` frames carry one message; `Data`,
//! `Ack` and `Nak` frames carry a cumulative `ack` (the next sequence number its sender expects). The sender
//! keeps up to `W` unacknowledged messages and resends all of them (go-back-N) when the oldest
//! has waited `rto` without an ack, or at once when the peer reports a damaged frame (`Nak`).
//! The receiver accepts only the next expected sequence number, so duplicates and reordered
//! frames are dropped (and re-acknowledged), never delivered twice.
//!
//! A link runs in an *epoch* chosen by the initiator (the host) with a three-way handshake:
//! `Sync(epoch, nonce)` → `SyncAck(nonce, boot nonce)` → `Confirm(boot nonce)`. On a new epoch
//! both directions restart at sequence 0 and messages still unacknowledged are sent again,
//! renumbered: nothing queued is lost across a reconnection. The responder sends data only
//! after `Confirm`, so a stale `Sync` reaching a device that just restarted cannot start a
//! stream the host does not know about; the host notices the new boot nonce in the `SyncAck`
//! and starts a new epoch. A responder that receives frames of an epoch it does not know (it
//! restarted) answers `Resync`, and the initiator starts a new epoch too.
//!
//! The link is a plain state machine: bytes in through [`Link::receive`], bytes out through
//! [`Link::poll_transmit`], time passed in as a `u64` in any unit the caller likes (device
//! ticks, host microseconds). It never sleeps and never allocates.

use core::marker::PhantomData;

use heapless::Deque;
use postcard_schema::Schema;
use serde::{Deserialize, Serialize};

use crate::frame::{seal, FrameDecoder, FrameError, CRC_LEN};
use crate::message::Message;
use crate::{MAX_FRAME, MAX_PACKET};

/// The kind of a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub enum FrameKind {
    /// Sequenced message; acknowledged, retransmitted until it is.
    Data,
    /// Acknowledgement only.
    Ack,
    /// "I received a damaged frame": resend unacknowledged data now. Body: [`FrameError`].
    Nak,
    /// Initiator: start epoch `epoch`. Body: the initiator's session nonce (`u32`).
    Sync,
    /// Responder: ready to start epoch `epoch`. Body: [`SyncAckBody`] (the `Sync`'s nonce and
    /// the responder's boot nonce).
    SyncAck,
    /// Responder: "I do not know epoch `epoch`", asking the initiator to sync again.
    Resync,
    /// Unsequenced message, delivered on arrival, never acknowledged or repeated.
    Datagram,
    /// Initiator: epoch `epoch` confirmed. Body: the responder's boot nonce from its `SyncAck`
    /// (`u32`). The responder sends no data in an epoch before this arrives.
    Confirm,
}

/// Body of a `SyncAck` frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct SyncAckBody {
    /// The nonce of the `Sync` this answers.
    pub nonce: u32,
    /// The responder's boot nonce: differs at every device start, so an initiator that sees
    /// a new one knows the device restarted (and answered a stale `Sync`).
    pub boot_nonce: u32,
}

/// The link header at the start of every packet (postcard: kind and epoch one byte each,
/// seq and ack as varints).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct Header {
    /// Frame kind.
    pub kind: FrameKind,
    /// Link epoch the frame belongs to.
    pub epoch: u8,
    /// Sequence number (`Data` only; 0 otherwise).
    pub seq: u16,
    /// Next sequence number the sender expects from the peer (all before it are received).
    pub ack: u16,
}

/// Number of [`FrameKind`]s; a kind byte at or above it is an unknown frame type.
pub const FRAME_KIND_COUNT: u32 = crate::message::variant_count(FrameKind::SCHEMA);

/// Smallest encoded header: four one-byte fields.
pub const HEADER_MIN: usize = 4;
/// Largest encoded header: seq and ack take three varint bytes each.
pub const HEADER_MAX: usize = 8;
/// Largest encoded message a `Data` or `Datagram` frame carries.
pub const MAX_MESSAGE: usize = MAX_PACKET - HEADER_MAX - CRC_LEN;
/// The retransmission timer doubles at each timeout without ack progress, up to
/// `rto << MAX_BACKOFF_SHIFT`, and is back at `rto` once an ack moves the window.
pub const MAX_BACKOFF_SHIFT: u32 = 4;
/// The responder stops retransmitting (data, and `SyncAck` while half-open) after this many
/// timeouts in a row with nothing at all received from the initiator: the host has gone. It
/// starts again at the next intact frame from the initiator.
pub const GIVE_UP_TIMEOUTS: u32 = 12;

/// Largest window any link may use.
pub const SEQ_WINDOW_MAX: u16 = 64;

/// Counters of everything the link did, sent and received; part of the device's status.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, Schema)]
#[cfg_attr(feature = "arbitrary", derive(arbitrary::Arbitrary))]
pub struct LinkStats {
    /// Frames written, all kinds.
    pub frames_sent: u32,
    /// Data frames written again after a timeout or Nak.
    pub retransmits: u32,
    /// Retransmission timeouts.
    pub timeouts: u32,
    /// Intact frames received, all kinds.
    pub frames_received: u32,
    /// Rejected: not valid COBS.
    pub bad_cobs: u32,
    /// Rejected: CRC mismatch.
    pub bad_crc: u32,
    /// Rejected: longer than the largest frame.
    pub too_long: u32,
    /// Rejected: shorter than a header and CRC.
    pub too_short: u32,
    /// Rejected: unknown frame kind or message type.
    pub unknown_type: u32,
    /// Rejected: header or message does not decode.
    pub bad_payload: u32,
    /// Data frames received again (already delivered): dropped.
    pub duplicates: u32,
    /// Data frames ahead of the expected one: dropped, the peer will resend.
    pub out_of_order: u32,
    /// Frames of another epoch: dropped.
    pub stale_epoch: u32,
    /// Naks sent.
    pub naks_sent: u32,
    /// Naks received.
    pub naks_received: u32,
    /// Data frames left unacknowledged for lack of room to answer them (back-pressure).
    pub deferred: u32,
    /// Epochs started (syncs completed).
    pub syncs: u32,
    /// Datagrams dropped: intact ones received and not acted on (a body that does not decode,
    /// also counted by its reason; or a message the receiver takes only sequenced, which its
    /// owner reports with [`Link::datagram_dropped`]: on the device, every `HostMsg` but
    /// `EmergencyStop`), and outgoing ones refused by [`Link::send_datagram`] for a full queue.
    pub datagrams_dropped: u32,
}

impl LinkStats {
    fn count_rejected(&mut self, e: FrameError) {
        let c = match e {
            FrameError::BadCobs => &mut self.bad_cobs,
            FrameError::BadCrc => &mut self.bad_crc,
            FrameError::TooLong => &mut self.too_long,
            FrameError::TooShort => &mut self.too_short,
            FrameError::UnknownType => &mut self.unknown_type,
            FrameError::BadPayload => &mut self.bad_payload,
        };
        *c = c.wrapping_add(1);
    }

    /// Frames rejected for any reason.
    pub fn rejected(&self) -> u32 {
        [self.bad_cobs, self.bad_crc, self.too_long, self.too_short, self.unknown_type, self.bad_payload]
            .into_iter()
            .fold(0u32, u32::wrapping_add)
    }
}

/// Which end of the link this is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// Chooses epochs (the host).
    Initiator,
    /// Follows the initiator's epochs (the device).
    Responder,
}

/// Link timing, in the caller's time unit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LinkConfig {
    /// Retransmission timeout: resend unacknowledged data this long after the last progress.
    /// At least 1 (0 is taken as 1).
    pub rto: u64,
    /// Accept a new data frame only while at least this many send slots are free, so that
    /// every accepted request can be answered (the device uses 1 or more; the host 0).
    /// A frame refused for lack of room is left unacknowledged and the peer sends it again.
    pub rx_reserve: usize,
    /// This end's nonce, different at every start: random when the host program starts (the
    /// initiator's session nonce, sent in `Sync`), random or a persistent counter when the
    /// device boots (the responder's boot nonce, sent in `SyncAck`).
    pub nonce: u32,
}

/// Where the link is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkState {
    /// No epoch yet (responder before the first `Sync`, initiator before `connect`).
    Down,
    /// Initiator: waiting for `SyncAck` (repeating `Sync` every rto). Responder: waiting for
    /// `Confirm` (repeating `SyncAck` every rto).
    Syncing,
    /// Exchanging data.
    Up,
}

/// What [`Link::receive`] hands up.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Delivery<R> {
    /// The next message, exactly once, in order.
    Message(R),
    /// An unsequenced message.
    Datagram(R),
    /// An intact sequenced frame whose message did not decode. It was acknowledged and will
    /// not come again; the receiver should tell its peer (the device sends `Rejected`).
    Rejected {
        /// Its sequence number.
        seq: u16,
        /// Why.
        reason: FrameError,
    },
    /// An intact sequenced frame that this build cannot decode but that starts like an answer
    /// to `Hello`: the peer speaks another protocol version or schema. It was acknowledged.
    Incompatible {
        /// Its sequence number.
        seq: u16,
        /// The peer's protocol version.
        protocol_version: u16,
        /// The peer's schema hash.
        schema_hash: u64,
    },
    /// A new epoch started: the peer (re)connected. Unacknowledged outgoing messages will be
    /// sent again in it.
    Connected {
        /// The epoch.
        epoch: u8,
    },
}

/// Why [`Link::send`] refused a message (it is handed back).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SendError<T> {
    /// `W` messages are waiting for acknowledgement; try after the peer acks.
    WindowFull(T),
    /// The message encodes to more than [`MAX_MESSAGE`] bytes.
    TooLarge(T),
}

impl<T> SendError<T> {
    /// The refused message.
    pub fn into_inner(self) -> T {
        match self {
            SendError::WindowFull(m) | SendError::TooLarge(m) => m,
        }
    }
}

/// One end of a reliable link carrying `T` out and `R` in, with `W` messages in flight.
pub struct Link<T: Message, R: Message, const W: usize> {
    role: Role,
    config: LinkConfig,
    state: LinkState,
    epoch: u8,
    /// The initiator's session nonce of the current epoch (the responder learns it from `Sync`).
    session: u32,
    /// Initiator: the responder's boot nonce learnt from its `SyncAck`.
    peer_boot: u32,
    // Transmit side. `queue[i]` has sequence number `base + i`, `base = next_seq - len`.
    queue: Deque<T, W>,
    next_seq: u16,
    /// Queue entries before this index have been sent (since the last go-back).
    unsent_from: usize,
    /// Queue entries before this index have been sent at least once in this epoch.
    sent_max: usize,
    rto_deadline: Option<u64>,
    sync_deadline: Option<u64>,
    /// Timeouts since the last ack progress: the timer is `rto << min(backoff, MAX_BACKOFF_SHIFT)`.
    backoff: u32,
    /// Timeouts in a row with nothing received from the peer.
    silent: u32,
    /// The responder has stopped retransmitting to a silent initiator.
    given_up: bool,
    /// Times the responder gave up.
    give_ups: u32,
    datagrams: Deque<T, 2>,
    send_sync_ack: bool,
    send_confirm: bool,
    send_resync: Option<u8>,
    send_nak: Option<FrameError>,
    // Receive side.
    expected: u16,
    need_ack: bool,
    decoder: FrameDecoder,
    last_rx: Option<u64>,
    stats: LinkStats,
    _rx: PhantomData<R>,
}

impl<T: Message, R: Message, const W: usize> Link<T, R, W> {
    const WINDOW_OK: () = assert!(W >= 1 && W <= SEQ_WINDOW_MAX as usize);

    /// A link in state `Down`.
    pub fn new(role: Role, config: LinkConfig) -> Self {
        #[allow(clippy::let_unit_value)]
        let () = Self::WINDOW_OK;
        let config = LinkConfig { rto: config.rto.max(1), ..config };
        Self {
            role,
            config,
            state: LinkState::Down,
            epoch: 0,
            session: 0,
            peer_boot: 0,
            queue: Deque::new(),
            next_seq: 0,
            unsent_from: 0,
            sent_max: 0,
            rto_deadline: None,
            sync_deadline: None,
            backoff: 0,
            silent: 0,
            given_up: false,
            give_ups: 0,
            datagrams: Deque::new(),
            send_sync_ack: false,
            send_confirm: false,
            send_resync: None,
            send_nak: None,
            expected: 0,
            need_ack: false,
            decoder: FrameDecoder::new(),
            last_rx: None,
            stats: LinkStats::default(),
            _rx: PhantomData,
        }
    }

    /// Current state.
    pub fn state(&self) -> LinkState {
        self.state
    }

    /// Current epoch.
    pub fn epoch(&self) -> u8 {
        self.epoch
    }

    /// Counters.
    pub fn stats(&self) -> &LinkStats {
        &self.stats
    }

    /// Counts a datagram [`Link::receive`] handed up that its owner drops unread (a message
    /// it acts on only when it comes sequenced): `datagrams_dropped`.
    pub fn datagram_dropped(&mut self) {
        self.stats.datagrams_dropped = self.stats.datagrams_dropped.wrapping_add(1);
    }

    /// Initiator: the responder's boot nonce, from the `SyncAck` that started the current
    /// epoch (0 before the first). It differs at every device start, so an initiator that
    /// sees it unchanged across a new epoch knows the device kept running.
    pub fn peer_boot(&self) -> u32 {
        self.peer_boot
    }

    /// Messages queued and not yet acknowledged.
    pub fn unacked(&self) -> usize {
        self.queue.len()
    }

    /// Room for more messages before [`Link::send`] refuses.
    pub fn free(&self) -> usize {
        W - self.queue.len()
    }

    /// Times this (responder) link stopped retransmitting to an initiator that had gone
    /// silent for [`GIVE_UP_TIMEOUTS`] timeouts.
    pub fn give_ups(&self) -> u32 {
        self.give_ups
    }

    /// The retransmission timer's current length: `rto`, doubled at each timeout without ack
    /// progress, at most `rto << MAX_BACKOFF_SHIFT`.
    pub fn current_rto(&self) -> u64 {
        self.config.rto << self.backoff.min(MAX_BACKOFF_SHIFT)
    }

    /// A timer ran out: back off, and count it as silent unless something came meanwhile.
    /// Returns whether to retransmit (a responder facing a silent initiator stops).
    fn timed_out(&mut self) -> bool {
        self.backoff = self.backoff.saturating_add(1);
        self.silent = self.silent.saturating_add(1);
        if self.role == Role::Responder && self.silent >= GIVE_UP_TIMEOUTS {
            if !self.given_up {
                self.give_ups = self.give_ups.wrapping_add(1);
            }
            self.given_up = true;
            return false;
        }
        true
    }

    /// When the last intact frame arrived (any kind), if any.
    pub fn last_received(&self) -> Option<u64> {
        self.last_rx
    }

    /// Initiator: start the next epoch (each `connect` moves to epoch + 1; the responder
    /// ignores a `Sync` of an older epoch of the same session, so stale copies cannot pull it
    /// back). Queued messages are kept and sent in the new epoch once it is up.
    pub fn connect(&mut self, now: u64) {
        self.epoch = self.epoch.wrapping_add(1);
        self.session = self.config.nonce;
        self.state = LinkState::Syncing;
        // A Confirm still pending belongs to the epoch being left.
        self.send_confirm = false;
        self.sync_deadline = Some(now);
        self.decoder.reset();
    }

    /// Queues a message for reliable delivery.
    pub fn send(&mut self, msg: T) -> Result<(), SendError<T>> {
        if !fits(&msg) {
            return Err(SendError::TooLarge(msg));
        }
        self.queue.push_back(msg).map_err(SendError::WindowFull)?;
        self.next_seq = self.next_seq.wrapping_add(1);
        Ok(())
    }

    /// Queues a message for reliable delivery ahead of every message queued: it is the first
    /// of them the peer receives. Only while none of them has been sent in this epoch (as when
    /// [`Delivery::Connected`] has just been handed up, before the next
    /// [`Link::poll_transmit`]); otherwise, or with the window full or the message too
    /// large, it is handed back.
    pub fn send_first(&mut self, msg: T) -> Result<(), T> {
        let started = self.state == LinkState::Up && self.sent_max > 0;
        if started || !fits(&msg) {
            return Err(msg);
        }
        // Nothing queued has been sent under its number: all of them move up by one.
        self.queue.push_front(msg)?;
        self.next_seq = self.next_seq.wrapping_add(1);
        Ok(())
    }

    /// Queues an unsequenced message (sent once, not acknowledged). For urgent, idempotent
    /// messages such as an emergency stop, sent alongside the reliable copy. Refused with the
    /// datagram queue full (two waiting to be sent): counted in `datagrams_dropped`.
    pub fn send_datagram(&mut self, msg: T) -> Result<(), SendError<T>> {
        if !fits(&msg) {
            return Err(SendError::TooLarge(msg));
        }
        self.datagrams.push_back(msg).map_err(|m| {
            self.stats.datagrams_dropped = self.stats.datagrams_dropped.wrapping_add(1);
            SendError::WindowFull(m)
        })
    }

    /// The next time [`Link::poll_transmit`] has something to do even if nothing arrives.
    pub fn next_deadline(&self) -> Option<u64> {
        let rto = if self.state == LinkState::Up { self.rto_deadline } else { None };
        let sync = if self.state == LinkState::Syncing { self.sync_deadline } else { None };
        match (rto, sync) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// Feeds received bytes until one delivery is ready. Returns how many bytes of `data` were
    /// consumed and the delivery, if any; call again with the rest. Handing up one delivery at
    /// a time lets the caller queue its answer before the next request is accepted.
    pub fn receive(&mut self, data: &[u8], now: u64) -> (usize, Option<Delivery<R>>) {
        for (i, &byte) in data.iter().enumerate() {
            let delivery = match self.decoder.push(byte) {
                Some(Ok(len)) => {
                    // Copy the packet out so the decoder's buffer is free for the next frame
                    // while this one is handled (one copy per frame, not per byte).
                    let mut buf = [0u8; MAX_PACKET];
                    match buf.get_mut(..len) {
                        Some(packet) => {
                            packet.copy_from_slice(self.decoder.packet(len));
                            self.on_packet(packet, now)
                        }
                        None => {
                            self.reject(FrameError::TooLong);
                            None
                        }
                    }
                }
                Some(Err(e)) => {
                    self.reject(e);
                    None
                }
                None => None,
            };
            if delivery.is_some() {
                return (i + 1, delivery);
            }
        }
        (data.len(), None)
    }

    /// Feeds all of `data`, handing every delivery to `on_delivery`.
    pub fn receive_all(&mut self, mut data: &[u8], now: u64, mut on_delivery: impl FnMut(Delivery<R>)) {
        while !data.is_empty() {
            let (used, delivery) = self.receive(data, now);
            if let Some(d) = delivery {
                on_delivery(d);
            }
            data = &data[used..];
        }
    }

    fn reject(&mut self, e: FrameError) {
        self.stats.count_rejected(e);
        if self.state == LinkState::Up {
            self.send_nak = Some(e);
        }
    }

    fn on_packet(&mut self, packet: &[u8], now: u64) -> Option<Delivery<R>> {
        let (header, body) = match postcard::take_from_bytes::<Header>(packet) {
            Ok(v) => v,
            Err(_) => {
                // postcard does not say which field failed: look at the kind byte ourselves.
                let known = packet.first().is_some_and(|&k| u32::from(k) < FRAME_KIND_COUNT);
                self.reject(if known { FrameError::BadPayload } else { FrameError::UnknownType });
                return None;
            }
        };
        // Control frames carry exactly one canonical body; Ack and Resync none.
        let control = match header.kind {
            FrameKind::Sync | FrameKind::Confirm => {
                exact::<u32>(body).map(|n| SyncAckBody { nonce: n, boot_nonce: n })
            }
            FrameKind::SyncAck => exact::<SyncAckBody>(body),
            FrameKind::Ack | FrameKind::Resync => {
                body.is_empty().then_some(SyncAckBody { nonce: 0, boot_nonce: 0 })
            }
            _ => Some(SyncAckBody { nonce: 0, boot_nonce: 0 }),
        };
        let Some(control) = control else {
            self.reject(FrameError::BadPayload);
            return None;
        };
        self.stats.frames_received = self.stats.frames_received.wrapping_add(1);
        self.last_rx = Some(now);
        self.silent = 0;
        if core::mem::take(&mut self.given_up) {
            // The peer is back: send again what it has not acknowledged, and ask again.
            self.backoff = 0;
            self.go_back();
            if self.state == LinkState::Syncing {
                self.sync_deadline = Some(now);
            }
        }
        let this_epoch = header.epoch == self.epoch;

        match (header.kind, self.role) {
            (FrameKind::Datagram, _) => match decode::<R>(body) {
                Ok(msg) => return Some(Delivery::Datagram(msg)),
                Err(e) => {
                    self.stats.count_rejected(e);
                    self.datagram_dropped();
                }
            },
            (FrameKind::Sync, Role::Responder) => {
                // Within one host session (same nonce) epochs only move forward: a Sync of the
                // current epoch is a repeat (answer it, keep the stream), one of an older epoch
                // is a stale copy (ignore it). A newer epoch or another session starts a new
                // stream, which becomes Up only when the initiator confirms it knows our boot
                // nonce: a stale Sync reaching a freshly started device never leads to data.
                let ahead = header.epoch.wrapping_sub(self.epoch);
                let fresh = self.state == LinkState::Down || control.nonce != self.session;
                if fresh || (1..0x80).contains(&ahead) {
                    self.session = control.nonce;
                    self.start_epoch(header.epoch);
                    self.state = LinkState::Syncing;
                    // Repeat the SyncAck every rto until Confirm arrives: an idle host whose
                    // Confirm was lost would otherwise never be asked again.
                    self.sync_deadline = Some(now + self.config.rto);
                } else if ahead != 0 {
                    self.stats.stale_epoch = self.stats.stale_epoch.wrapping_add(1);
                    return None;
                }
                self.send_sync_ack = true;
            }
            (FrameKind::Confirm, Role::Responder)
                if self.state == LinkState::Syncing && this_epoch && control.nonce == self.config.nonce =>
            {
                self.state = LinkState::Up;
                self.backoff = 0;
                return Some(Delivery::Connected { epoch: header.epoch });
            }
            (FrameKind::SyncAck, Role::Initiator) if this_epoch && control.nonce == self.session => {
                match self.state {
                    LinkState::Syncing => {
                        self.peer_boot = control.boot_nonce;
                        self.start_epoch(header.epoch);
                        self.state = LinkState::Up;
                        self.send_confirm = true;
                        return Some(Delivery::Connected { epoch: header.epoch });
                    }
                    // The responder still waits for our Confirm (it was lost): send it again.
                    LinkState::Up if control.boot_nonce == self.peer_boot => self.send_confirm = true,
                    // Another boot nonce: the device restarted and answered a stale copy of our
                    // Sync. Start a new epoch; its SyncAck will carry the new boot nonce.
                    LinkState::Up => self.connect(now),
                    LinkState::Down => {}
                }
            }
            // Our epoch, another session's nonce, while we are up: a stale `Sync` of an earlier
            // host run knocked the responder back to half-open in that session, and it answers
            // our data with this. It will take none of it until we start a new epoch.
            (FrameKind::SyncAck, Role::Initiator) if this_epoch && self.state == LinkState::Up => {
                self.stats.stale_epoch = self.stats.stale_epoch.wrapping_add(1);
                self.connect(now);
            }
            (FrameKind::Resync, Role::Initiator) if self.state == LinkState::Up && this_epoch => {
                self.connect(now);
            }
            (FrameKind::Data | FrameKind::Ack | FrameKind::Nak, _) => {
                if !this_epoch || self.state != LinkState::Up {
                    self.stats.stale_epoch = self.stats.stale_epoch.wrapping_add(1);
                    match (self.role, self.state) {
                        // The initiator is Up and sends in our new epoch: our SyncAck or its
                        // Confirm was lost. Ask again; the frame comes again later.
                        (Role::Responder, LinkState::Syncing) if this_epoch => self.send_sync_ack = true,
                        (Role::Responder, _) => self.send_resync = Some(header.epoch),
                        // The initiator drops frames of other epochs (or of an epoch it is
                        // still syncing: the responder sends none before Confirm).
                        (Role::Initiator, _) => {}
                    }
                    return None;
                }
                self.on_ack(header.ack, now);
                match header.kind {
                    FrameKind::Data => return self.on_data(header.seq, body),
                    FrameKind::Nak => {
                        self.stats.naks_received = self.stats.naks_received.wrapping_add(1);
                        self.backoff = 0;
                        self.go_back();
                    }
                    _ => {}
                }
            }
            // A frame meant for the other role (a Sync sent to the host), or a SyncAck/Resync
            // of another epoch: ignore it.
            _ => {}
        }
        None
    }

    /// Resets both directions for a new epoch; the caller sets the state.
    fn start_epoch(&mut self, epoch: u8) {
        self.epoch = epoch;
        self.sync_deadline = None;
        self.expected = 0;
        self.need_ack = false;
        // Renumber what is still unacknowledged from 0 and send it all again.
        self.next_seq = self.queue.len() as u16;
        self.unsent_from = 0;
        self.sent_max = 0;
        self.rto_deadline = None;
        self.backoff = 0;
        self.silent = 0;
        self.given_up = false;
        self.send_nak = None;
        self.stats.syncs = self.stats.syncs.wrapping_add(1);
    }

    fn base(&self) -> u16 {
        self.next_seq.wrapping_sub(self.queue.len() as u16)
    }

    fn on_ack(&mut self, ack: u16, now: u64) {
        let acked = usize::from(ack.wrapping_sub(self.base()));
        if acked == 0 || acked > self.sent_max {
            return; // old or bogus: acknowledges nothing we have sent
        }
        for _ in 0..acked {
            self.queue.pop_front();
        }
        self.sent_max -= acked;
        self.unsent_from = self.unsent_from.saturating_sub(acked);
        self.backoff = 0;
        self.rto_deadline = if self.sent_max > 0 { Some(now + self.config.rto) } else { None };
    }

    fn on_data(&mut self, seq: u16, body: &[u8]) -> Option<Delivery<R>> {
        if seq != self.expected {
            self.need_ack = true;
            let behind = self.expected.wrapping_sub(seq);
            if behind != 0 && behind <= 0x8000 {
                self.stats.duplicates = self.stats.duplicates.wrapping_add(1);
            } else {
                self.stats.out_of_order = self.stats.out_of_order.wrapping_add(1);
            }
            return None;
        }
        if self.free() < self.config.rx_reserve {
            // No room to answer: leave it unacknowledged, the peer resends after its timeout.
            self.stats.deferred = self.stats.deferred.wrapping_add(1);
            return None;
        }
        self.need_ack = true;
        self.expected = self.expected.wrapping_add(1);
        Some(match decode::<R>(body) {
            Ok(msg) => Delivery::Message(msg),
            Err(reason) => {
                self.stats.count_rejected(reason);
                match R::handshake_prefix(body) {
                    Some((protocol_version, schema_hash)) => {
                        Delivery::Incompatible { seq, protocol_version, schema_hash }
                    }
                    None => Delivery::Rejected { seq, reason },
                }
            }
        })
    }

    fn go_back(&mut self) {
        self.unsent_from = 0;
    }

    /// Writes the next frame due into `out` and returns its length, or `None` if nothing is
    /// due now. Call until it returns `None`, and again by [`Link::next_deadline`].
    pub fn poll_transmit(&mut self, now: u64, out: &mut [u8; MAX_FRAME]) -> Option<usize> {
        let n = self.next_frame(now, out)?;
        self.stats.frames_sent = self.stats.frames_sent.wrapping_add(1);
        Some(n)
    }

    fn next_frame(&mut self, now: u64, out: &mut [u8; MAX_FRAME]) -> Option<usize> {
        let epoch = self.epoch;
        let header = |kind, seq, ack| Header { kind, epoch, seq, ack };
        if self.state == LinkState::Syncing && self.sync_deadline.is_some_and(|d| now >= d) {
            match self.role {
                Role::Initiator => {
                    self.sync_deadline = Some(now + self.config.rto);
                    return Some(write(&header(FrameKind::Sync, 0, 0), Some(&self.session), out));
                }
                // A half-open responder asks for `Confirm` again, less and less often, and
                // not at all once the initiator has been silent for long.
                Role::Responder => {
                    let again = self.timed_out();
                    self.sync_deadline = again.then(|| now + self.current_rto());
                    self.send_sync_ack |= again;
                }
            }
        }
        if core::mem::take(&mut self.send_sync_ack) {
            let body = SyncAckBody { nonce: self.session, boot_nonce: self.config.nonce };
            return Some(write(&header(FrameKind::SyncAck, 0, 0), Some(&body), out));
        }
        if core::mem::take(&mut self.send_confirm) {
            return Some(write(&header(FrameKind::Confirm, 0, 0), Some(&self.peer_boot), out));
        }
        if let Some(epoch) = self.send_resync.take() {
            let h = Header { kind: FrameKind::Resync, epoch, seq: 0, ack: 0 };
            return Some(write::<T>(&h, None, out));
        }
        if let Some(msg) = self.datagrams.pop_front() {
            return Some(write(&header(FrameKind::Datagram, 0, 0), Some(&msg), out));
        }
        if self.state != LinkState::Up {
            return None;
        }
        if let Some(reason) = self.send_nak.take() {
            self.stats.naks_sent = self.stats.naks_sent.wrapping_add(1);
            return Some(write(&header(FrameKind::Nak, 0, self.expected), Some(&reason), out));
        }
        if self.rto_deadline.is_some_and(|d| now >= d) {
            self.stats.timeouts = self.stats.timeouts.wrapping_add(1);
            self.rto_deadline = None;
            if !self.timed_out() {
                // Given up: nothing more until the peer speaks (or new data is queued).
                return self.ack_only(now, out);
            }
            self.go_back();
        }
        if let Some(msg) = self.queue.iter().nth(self.unsent_from) {
            let seq = self.base().wrapping_add(self.unsent_from as u16);
            let n = write(&header(FrameKind::Data, seq, self.expected), Some(msg), out);
            if self.unsent_from < self.sent_max {
                self.stats.retransmits = self.stats.retransmits.wrapping_add(1);
            }
            self.unsent_from += 1;
            self.sent_max = self.sent_max.max(self.unsent_from);
            self.need_ack = false;
            let rto = self.current_rto();
            self.rto_deadline.get_or_insert(now + rto);
            return Some(n);
        }
        self.ack_only(now, out)
    }

    /// A pending `Ack`, if any.
    fn ack_only(&mut self, _now: u64, out: &mut [u8; MAX_FRAME]) -> Option<usize> {
        if core::mem::take(&mut self.need_ack) {
            let h = Header { kind: FrameKind::Ack, epoch: self.epoch, seq: 0, ack: self.expected };
            return Some(write::<T>(&h, None, out));
        }
        None
    }
}

/// Decodes a body that must be exactly one canonical `B`.
fn exact<B: Serialize + for<'de> Deserialize<'de>>(body: &[u8]) -> Option<B> {
    match postcard::take_from_bytes::<B>(body) {
        Ok((b, [])) if postcard::experimental::serialized_size(&b).ok() == Some(body.len()) => Some(b),
        _ => None,
    }
}

fn fits<T: Serialize>(msg: &T) -> bool {
    postcard::experimental::serialized_size(msg).is_ok_and(|n| n <= MAX_MESSAGE)
}

/// Decodes a whole message body; trailing bytes are an error.
pub fn decode<R: Message>(body: &[u8]) -> Result<R, FrameError> {
    match postcard::take_from_bytes::<R>(body) {
        Ok((msg, [])) => Ok(msg),
        Ok(_) => Err(FrameError::BadPayload),
        Err(_) if R::unknown_tag(body) => Err(FrameError::UnknownType),
        Err(_) => Err(FrameError::BadPayload),
    }
}

/// Encodes a frame: header, optional body, CRC, COBS, delimiter. Returns its length, or 0
/// (nothing written) if the body does not fit a packet.
///
/// The link checks bodies against [`MAX_MESSAGE`] when they are queued, so its own frames
/// always fit.
pub fn write<B: Serialize>(header: &Header, body: Option<&B>, out: &mut [u8; MAX_FRAME]) -> usize {
    let mut buf = [0u8; MAX_PACKET];
    let Ok(h) = postcard::to_slice(header, &mut buf[..HEADER_MAX]) else { return 0 };
    let mut len = h.len();
    if let Some(body) = body {
        let room = &mut buf[len..MAX_PACKET - CRC_LEN];
        let Ok(b) = postcard::to_slice(body, room) else { return 0 };
        len += b.len();
    }
    seal(&mut buf, len, out)
}
