//! What a session directory holds: the manifest and the journal's records.

use lightrig_protocol::session::{BoardId, Capabilities, DeviceInfo, ResetCause, Version};
use lightrig_protocol::Event;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use super::pairing::ExtraReason;
use super::{fsutil, FORMAT_VERSION};

/// A step of the plan, as the session knows it.
pub type StepId = u32;

/// `manifest.json`: written once when the session is created.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// [`FORMAT_VERSION`] of the writer.
    pub format: u32,
    /// Unique id of the session (also in the journal's `SessionStarted`).
    pub session_id: String,
    /// When the session was created, RFC 3339 UTC.
    pub created: String,
    /// Version of the lightrig host that created it.
    pub host_version: String,
    /// The rig file, verbatim.
    pub rig: String,
    /// The device the session was planned for.
    pub device: DeviceSummary,
    /// What the session acquires.
    pub plan: PlanSummary,
}

impl Manifest {
    /// A manifest for a new session: a fresh id, created now, this host's version.
    pub fn new(rig: impl Into<String>, device: &DeviceInfo, plan: PlanSummary) -> Self {
        Manifest {
            format: FORMAT_VERSION,
            session_id: new_session_id(),
            created: fsutil::now_rfc3339(),
            host_version: env!("CARGO_PKG_VERSION").to_string(),
            rig: rig.into(),
            device: DeviceSummary::from(device),
            plan,
        }
    }

    /// The plan step with id `step`.
    pub fn step(&self, step: StepId) -> Option<&PlanStep> {
        self.plan.steps.iter().find(|s| s.id == step)
    }
}

/// A session id: `YYYYMMDDTHHMMSSZ-xxxxxxxx` (creation time and 32 random bits).
pub fn new_session_id() -> String {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u128(
        std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default().as_nanos(),
    );
    h.write_u32(std::process::id());
    let t: String = fsutil::now_rfc3339().chars().filter(|c| c.is_ascii_alphanumeric()).collect();
    // 20250301T123456789Z -> 20250301T123456Z
    let stamp = format!("{}Z", &t[..15]);
    format!("{stamp}-{:08x}", h.finish() as u32)
}

/// What the device said about itself, minus what changes at every start.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct DeviceSummary {
    /// Firmware version.
    pub firmware: Version,
    /// Board.
    pub board: BoardId,
    /// Board serial, `"0x"` and 16 hex digits.
    #[serde(with = "hex64")]
    pub serial: u64,
    /// Device ticks per second.
    pub tick_hz: u32,
    /// Wire protocol version.
    pub protocol_version: u16,
    /// Message schema hash, `"0x"` and 16 hex digits.
    #[serde(with = "hex64")]
    pub schema_hash: u64,
    /// What the device drives.
    pub capabilities: Capabilities,
}

impl From<&DeviceInfo> for DeviceSummary {
    fn from(d: &DeviceInfo) -> Self {
        DeviceSummary {
            firmware: d.firmware,
            board: d.board,
            serial: d.serial,
            tick_hz: d.tick_hz,
            protocol_version: d.protocol_version,
            schema_hash: d.schema_hash,
            capabilities: d.capabilities,
        }
    }
}

/// The plan, as far as the session needs it.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PlanSummary {
    /// The steps, in acquisition order. Ids are unique.
    pub steps: Vec<PlanStep>,
    /// Anything else the planner wants to keep (opaque to the session).
    #[serde(default, skip_serializing_if = "Value::is_null")]
    pub extra: Value,
}

/// One step: a sequence run on the device, acquired (and re-acquired) as a whole.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PlanStep {
    /// Unique id.
    pub id: StepId,
    /// Name for people.
    pub name: String,
    /// Triggers the step fires, per camera: frames `0..count` of each.
    pub triggers: Vec<CameraTriggers>,
    /// Anything else the planner wants to keep (opaque to the session).
    #[serde(default, skip_serializing_if = "Value::is_null")]
    pub extra: Value,
}

impl PlanStep {
    /// Expected triggers on `camera` (0 if the step does not use it).
    pub fn expected(&self, camera: u8) -> u32 {
        self.triggers.iter().filter(|t| t.camera == camera).map(|t| t.count).sum()
    }

    /// Expected triggers on all cameras.
    pub fn total(&self) -> u32 {
        self.triggers.iter().map(|t| t.count).sum()
    }
}

/// Expected triggers on one camera.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct CameraTriggers {
    /// Camera output.
    pub camera: u8,
    /// Number of triggers (frame numbers `0..count`).
    pub count: u32,
}

/// A frame paired with its trigger.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameRecord {
    /// Step.
    pub step: StepId,
    /// Attempt of the step.
    pub attempt: u32,
    /// Camera.
    pub camera: u8,
    /// Frame number on the camera within the step's sequence (the trigger's `frame`).
    pub frame: u32,
    /// Sequence id of the trigger.
    pub sequence: u32,
    /// Item index of the trigger in its sequence.
    pub item: u32,
    /// Device tick of the trigger.
    pub tick: u64,
    /// Host time of the trigger, µs.
    pub trigger_us: Option<f64>,
    /// Host time the frame arrived, µs.
    pub arrived_us: f64,
    /// The frame arrived later than the pairing tolerance.
    pub late: bool,
    /// The image file, relative to the session directory, `/`-separated.
    pub file: String,
    /// Its size in bytes.
    pub bytes: u64,
    /// CRC-32/ISO-HDLC of its content, 8 lowercase hex digits.
    #[serde(with = "hex32")]
    pub crc32: u32,
    /// The camera's own frame id and timestamp, for a camera that gives them (GenICam);
    /// absent otherwise (format 3 readers without it ignore it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera_stamp: Option<CameraStamp>,
}

/// What a camera says about a frame itself.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct CameraStamp {
    /// The camera's frame id (GigE Vision block id, USB3 Vision frame id).
    pub id: u64,
    /// The camera's timestamp of the frame, ns on the camera's clock.
    pub time_ns: u64,
}

/// A trigger whose frame never came.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MissingRecord {
    /// Step.
    pub step: StepId,
    /// Attempt of the step.
    pub attempt: u32,
    /// Camera.
    pub camera: u8,
    /// Frame number the camera should have produced.
    pub frame: u32,
    /// Sequence id of the trigger.
    pub sequence: u32,
    /// Item index of the trigger.
    pub item: u32,
    /// Device tick of the trigger.
    pub tick: u64,
    /// Host time of the trigger, µs.
    pub trigger_us: Option<f64>,
    /// Why, in words.
    pub reason: String,
}

/// A frame no trigger accounts for, kept for inspection.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ExtraRecord {
    /// Step.
    pub step: StepId,
    /// Attempt of the step.
    pub attempt: u32,
    /// Camera.
    pub camera: u8,
    /// Its frame number (reported by the source, or its arrival order).
    pub frame: u32,
    /// Host time it arrived, µs.
    pub arrived_us: f64,
    /// Why it is extra.
    pub reason: ExtraReason,
    /// The image file, relative to the session directory.
    pub file: String,
    /// Its size in bytes.
    pub bytes: u64,
    /// CRC-32/ISO-HDLC of its content.
    #[serde(with = "hex32")]
    pub crc32: u32,
}

/// One line of `journal.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type")]
pub enum Record {
    /// First record: the session began.
    SessionStarted {
        /// Same as the manifest's.
        session_id: String,
        /// Wall clock, RFC 3339 UTC.
        host_time: String,
    },
    /// The session was opened again after the process ended (normally or not).
    Resumed {
        /// 1 for the first resume, then 2, …
        attempt: u32,
        /// Wall clock.
        host_time: String,
        /// Bytes of torn or damaged journal tail dropped when opening.
        dropped_bytes: u64,
    },
    /// A device was connected (at the start, after an unplug, after a device restart).
    DeviceConnected {
        /// The device's boot id: events carry it.
        boot_id: u32,
        /// Why the device last started.
        reset_cause: ResetCause,
        /// The device.
        device: DeviceSummary,
        /// Wall clock.
        host_time: String,
    },
    /// The host cleared a fault the device had latched, found by asking its status: one
    /// latched while no host was there, or whose `Fault` event an earlier host took (format 3).
    FaultCleared {
        /// Boot id of the device.
        boot_id: u32,
        /// The fault.
        cause: lightrig_protocol::event::FaultCause,
        /// `automatic` (a fault that needs no person's word) or `confirmed` (an opened
        /// interlock: a person said the beam path was clear, or `--yes` took it as so).
        by: String,
        /// Wall clock.
        host_time: String,
    },
    /// An attempt at a step began.
    StepStarted {
        /// Step.
        step: StepId,
        /// 1 for the first attempt, then 2, …
        attempt: u32,
        /// The device sequence id the attempt runs as.
        sequence_id: u32,
        /// Wall clock.
        host_time: String,
    },
    /// What the step asked of the host before its sequence ran was done: a person's action
    /// (`meta.operator`) and the host-driven instruments' settings (`meta.host`).
    StepPrepared {
        /// Step.
        step: StepId,
        /// Attempt.
        attempt: u32,
        /// Who did it: `operator` (confirmed at the prompt), `assumed` (`--yes`: the rig was
        /// set up beforehand) or `virtual` (the virtual rig's instruments).
        by: String,
        /// Each request, in words.
        actions: Vec<String>,
        /// Wall clock.
        host_time: String,
    },
    /// A device event, as it arrived. `(boot_id, index)` is unique in the journal.
    Event {
        /// Boot id of the device that sent it.
        boot_id: u32,
        /// The device's event number.
        index: u32,
        /// Host time of the event's tick, µs (null if it has none or the clock was not mapped).
        host_us: Option<f64>,
        /// The event.
        event: Event,
    },
    /// A frame paired with its trigger.
    Frame(FrameRecord),
    /// A trigger without a frame.
    FrameMissing(MissingRecord),
    /// A frame without a trigger.
    FrameExtra(ExtraRecord),
    /// The attempt completed: every trigger has its `Frame` or `FrameMissing`.
    StepDone {
        /// Step.
        step: StepId,
        /// Attempt.
        attempt: u32,
        /// Triggers (= frames + missing = the plan's count).
        triggers: u32,
        /// `Frame` records of the attempt.
        frames: u32,
        /// `FrameMissing` records of the attempt.
        missing: u32,
        /// `FrameExtra` records of the attempt.
        extra: u32,
        /// Wall clock.
        host_time: String,
    },
    /// The attempt ended without completing; its records are superseded.
    StepAbandoned {
        /// Step.
        step: StepId,
        /// Attempt.
        attempt: u32,
        /// Why, in words.
        reason: String,
        /// Wall clock.
        host_time: String,
    },
    /// A completed attempt is taken back so the step is acquired again (format 4): the retake
    /// of a finished session's missing frames (`lightrig resume --retake-missing`). The attempt
    /// counts as superseded from here on; the record may follow `SessionDone`, which it undoes.
    StepReopened {
        /// Step.
        step: StepId,
        /// The completed attempt taken back.
        attempt: u32,
        /// Why, in words.
        reason: String,
        /// Wall clock.
        host_time: String,
    },
    /// Every step is done; nothing follows but a `StepReopened`.
    SessionDone {
        /// Wall clock.
        host_time: String,
    },
}

impl Record {
    /// The record's `type`.
    pub fn kind(&self) -> &'static str {
        match self {
            Record::SessionStarted { .. } => "SessionStarted",
            Record::Resumed { .. } => "Resumed",
            Record::DeviceConnected { .. } => "DeviceConnected",
            Record::FaultCleared { .. } => "FaultCleared",
            Record::StepStarted { .. } => "StepStarted",
            Record::StepPrepared { .. } => "StepPrepared",
            Record::Event { .. } => "Event",
            Record::Frame(_) => "Frame",
            Record::FrameMissing(_) => "FrameMissing",
            Record::FrameExtra(_) => "FrameExtra",
            Record::StepDone { .. } => "StepDone",
            Record::StepAbandoned { .. } => "StepAbandoned",
            Record::StepReopened { .. } => "StepReopened",
            Record::SessionDone { .. } => "SessionDone",
        }
    }
}

/// `u64` as `"0x"` and 16 lowercase hex digits (JSON numbers above 2^53 lose precision in many
/// readers).
mod hex64 {
    use serde::{de::Error, Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(v: &u64, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&format!("0x{v:016x}"))
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<u64, D::Error> {
        let s = String::deserialize(d)?;
        let hex = s.strip_prefix("0x").ok_or_else(|| D::Error::custom("expected \"0x\" and hex digits"))?;
        u64::from_str_radix(hex, 16).map_err(D::Error::custom)
    }
}

/// `u32` as 8 lowercase hex digits.
mod hex32 {
    use serde::{de::Error, Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(v: &u32, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&format!("{v:08x}"))
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<u32, D::Error> {
        let s = String::deserialize(d)?;
        if s.len() != 8 {
            return Err(D::Error::custom("expected 8 hex digits"));
        }
        u32::from_str_radix(&s, 16).map_err(D::Error::custom)
    }
}
