//! Messages: round trips of arbitrary values, decoding of arbitrary bytes, configuration
//! validation that names the refused field, and the frozen handshake prefix.

use arbitrary::{Arbitrary, Unstructured};
use lightrig_protocol::config::*;
use lightrig_protocol::frame::{FrameDecoder, FrameError};
use lightrig_protocol::link::{self, FrameKind, Header, MAX_MESSAGE};
use lightrig_protocol::session::*;
use lightrig_protocol::*;
use proptest::prelude::*;

mod common;

fn frame_roundtrip<M: lightrig_protocol::message::Message + PartialEq>(msg: &M) {
    let header = Header { kind: FrameKind::Data, epoch: 3, seq: 65535, ack: 65535 };
    let mut out = [0u8; MAX_FRAME];
    let n = link::write(&header, Some(msg), &mut out);
    assert!(n <= MAX_FRAME);
    let mut dec = FrameDecoder::new();
    let mut got = None;
    dec.feed(&out[..n], |p| {
        let (h, body) = postcard::take_from_bytes::<Header>(p.unwrap()).unwrap();
        assert_eq!(h, header);
        got = Some(link::decode::<M>(body).unwrap());
    });
    assert_eq!(got.as_ref(), Some(msg));
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, .. ProptestConfig::default() })]

    #[test]
    fn arbitrary_messages_round_trip_through_a_frame(bytes in prop::collection::vec(any::<u8>(), 0..2048)) {
        let mut u = Unstructured::new(&bytes);
        if let Ok(m) = HostMsg::arbitrary(&mut u) {
            if postcard::experimental::serialized_size(&m).unwrap() <= MAX_MESSAGE {
                frame_roundtrip(&m);
            }
        }
        if let Ok(m) = DeviceMsg::arbitrary(&mut u) {
            if postcard::experimental::serialized_size(&m).unwrap() <= MAX_MESSAGE {
                frame_roundtrip(&m);
            }
        }
    }

    #[test]
    fn arbitrary_bytes_decode_to_a_message_or_a_typed_error(bytes in prop::collection::vec(any::<u8>(), 0..600)) {
        for r in [link::decode::<HostMsg>(&bytes).err(), link::decode::<DeviceMsg>(&bytes).err()].into_iter().flatten() {
            prop_assert!(matches!(r, FrameError::UnknownType | FrameError::BadPayload));
        }
        let mut dec = FrameDecoder::new();
        dec.feed(&bytes, |_| {});
    }
}

fn info() -> DeviceInfo {
    common::device_info()
}

fn laser() -> LaserConfig {
    LaserConfig {
        channel: 0,
        wavelength_nm: 532,
        warmup_ticks: 1000,
        max_on_ticks: 10_000_000,
        enable: Polarity::ActiveHigh,
        interlock: Input::Unused,
    }
}

fn stepper() -> StepperConfig {
    StepperConfig {
        axis: 1,
        kind: AxisKind::Linear,
        steps_per_unit: Ratio { num: 400, den: 1 },
        max_speed: 10_000,
        accel: 20_000,
        limits: Some(StepRange { min: 0, max: 120_000 }),
        homing: Homing { mode: HomingMode::ToMinLimit, speed: 1000, backoff: 200, position: 0 },
        invert_dir: false,
        enable: Polarity::ActiveLow,
        limit_min: Input::Wired(Polarity::ActiveLow),
        limit_max: Input::Wired(Polarity::ActiveLow),
        index: Input::Unused,
    }
}

fn refused(item: ConfigItem) -> (ConfigField, u8, InvalidReason) {
    let e = item.validate(&info()).expect_err("must be refused");
    (e.field, e.index, e.reason)
}

#[test]
fn valid_configuration_is_accepted() {
    assert_eq!(ConfigItem::Laser(laser()).validate(&info()), Ok(()));
    assert_eq!(ConfigItem::Stepper(stepper()).validate(&info()), Ok(()));
}

#[test]
fn each_refusal_names_field_index_and_reason() {
    use ConfigField as F;
    use InvalidReason as R;
    let l = laser();
    assert_eq!(
        refused(ConfigItem::Laser(LaserConfig { channel: 3, ..l })),
        (F::LaserChannel, 3, R::NoSuchPeripheral { count: 3 })
    );
    assert_eq!(
        refused(ConfigItem::Laser(LaserConfig { max_on_ticks: 0, ..l })),
        (F::LaserMaxOnTicks, 0, R::Zero)
    );
    assert_eq!(
        refused(ConfigItem::Laser(LaserConfig { wavelength_nm: 100, ..l })),
        (F::LaserWavelength, 0, R::TooSmall { min: 200 })
    );
    assert_eq!(
        refused(ConfigItem::Laser(LaserConfig { warmup_ticks: 20_000_000, ..l })),
        (F::LaserWarmupTicks, 0, R::TooLarge { max: 10_000_000 })
    );
    let s = stepper();
    assert_eq!(
        refused(ConfigItem::Stepper(StepperConfig { limits: None, ..s })),
        (F::StepperLimits, 1, R::Required)
    );
    assert_eq!(
        refused(ConfigItem::Stepper(StepperConfig { limits: Some(StepRange { min: 5, max: 5 }), ..s })),
        (F::StepperLimits, 1, R::EmptyRange)
    );
    assert_eq!(
        refused(ConfigItem::Stepper(StepperConfig { limit_min: Input::Unused, ..s })),
        (F::StepperHomingMode, 1, R::NeedsInput)
    );
    assert_eq!(
        refused(ConfigItem::Stepper(StepperConfig { max_speed: 600_000, ..s })),
        (F::StepperMaxSpeed, 1, R::TooLarge { max: 500_000 })
    );
    assert_eq!(
        refused(ConfigItem::Stepper(StepperConfig { steps_per_unit: Ratio { num: 1, den: 0 }, ..s })),
        (F::StepperStepsPerUnit, 1, R::Zero)
    );
    let axis = GalvoAxis { min_code: 100, max_code: 4000, zero_code: 2048, nanorad_per_code: 1 };
    let g = GalvoConfig {
        galvo: 0,
        dac: DacKind::McuDac,
        x: axis,
        y: axis,
        park: Xy { x: 2048, y: 2048 },
        settle_ticks: 10,
    };
    assert_eq!(ConfigItem::Galvo(g).validate(&info()), Ok(()));
    assert_eq!(
        refused(ConfigItem::Galvo(GalvoConfig { y: GalvoAxis { max_code: 5000, ..axis }, ..g })),
        (F::GalvoYMaxCode, 0, R::TooLarge { max: 4095 })
    );
    assert_eq!(
        refused(ConfigItem::Galvo(GalvoConfig { park: Xy { x: 2048, y: 50 }, ..g })),
        (F::GalvoParkY, 0, R::OutsideRange { min: 100, max: 4000 })
    );
    let v = VoiceCoilConfig { channel: 0, sample_rate_hz: 44_100, max_amplitude: 1 };
    assert_eq!(refused(ConfigItem::VoiceCoil(v)), (F::VoiceCoilSampleRate, 0, R::TooSmall { min: 48_000 }));
    let w = FilterWheelConfig {
        wheel: 0,
        slots: 6,
        steps_per_rev: 3200,
        max_speed: 1000,
        accel: 1000,
        index: Input::Unused,
        index_offset: 0,
        invert_dir: false,
        enable: Polarity::ActiveLow,
    };
    assert_eq!(refused(ConfigItem::FilterWheel(w)), (F::FilterWheelIndexSensor, 0, R::Required));
    let k = CameraConfig {
        camera: 0,
        pulse_ticks: 0,
        polarity: Polarity::ActiveHigh,
        exposure_input: Input::Unused,
        min_interval_ticks: 0,
    };
    assert_eq!(refused(ConfigItem::Camera(k)), (F::CameraPulseTicks, 0, R::Zero));
    // 5 ms at 1 MHz is below the 10 ms floor.
    let s = SafetyConfig { heartbeat_timeout_ticks: 5_000 };
    assert_eq!(refused(ConfigItem::Safety(s)), (F::SafetyHeartbeatTimeout, 0, R::TooSmall { min: 10_000 }));
}

#[test]
fn config_error_reads_like_the_rig_file() {
    let e = ConfigError { field: ConfigField::GalvoXMinCode, index: 1, reason: InvalidReason::EmptyRange };
    assert_eq!(e.to_string(), "galvo.x.min_code[1]: min must be below max");
}

/// What any protocol version can read from a `Hello` answer: the first fields only.
#[derive(serde::Deserialize, Debug, PartialEq)]
struct HelloPrefix {
    variant: u8,
    id: u16,
    ok: u8,
    reply: u8,
    protocol_version: u16,
    schema_hash: u64,
}

#[test]
fn handshake_prefix_is_frozen() {
    // Command::Hello is variant 0 right after the id.
    let hello = HostMsg { id: 1, command: Command::Hello { protocol_version: 1, schema_hash: 2 } };
    assert_eq!(postcard::to_allocvec(&hello).unwrap(), vec![0x01, 0x00, 0x01, 0x02]);
    let answer = DeviceMsg::Response { id: 300, result: Ok(Reply::Hello(info())) };
    let bytes = postcard::to_allocvec(&answer).unwrap();
    let (prefix, _rest) = postcard::take_from_bytes::<HelloPrefix>(&bytes).unwrap();
    assert_eq!(
        prefix,
        HelloPrefix {
            variant: 0,
            id: 300,
            ok: 0,
            reply: 0,
            protocol_version: PROTOCOL_VERSION,
            schema_hash: SCHEMA_HASH
        }
    );
}

#[test]
fn an_incompatible_hello_answer_still_yields_version_and_hash() {
    use lightrig_protocol::link::{Delivery, Link, LinkConfig, Role};
    use lightrig_protocol::message::Message;
    // A future device whose DeviceInfo grew a field: this build cannot decode the answer.
    let mut body = postcard::to_allocvec(&DeviceMsg::Response {
        id: 1,
        result: Ok(Reply::Hello(DeviceInfo { protocol_version: 2, schema_hash: 0xfeed, ..info() })),
    })
    .unwrap();
    body.push(0x2a);
    assert_eq!(link::decode::<DeviceMsg>(&body), Err(FrameError::BadPayload));
    assert_eq!(DeviceMsg::handshake_prefix(&body), Some((2, 0xfeed)));
    // Through the link, the host gets `Incompatible` rather than a bare rejection.
    let mut host: Link<HostMsg, DeviceMsg, 8> =
        Link::new(Role::Initiator, LinkConfig { rto: 10, rx_reserve: 0, nonce: 9 });
    host.connect(0);
    let mut out = [0u8; MAX_FRAME];
    let ack = link::SyncAckBody { nonce: 9, boot_nonce: 77 };
    let n = link::write(&Header { kind: FrameKind::SyncAck, epoch: 1, seq: 0, ack: 0 }, Some(&ack), &mut out);
    host.receive_all(&out[..n], 0, |_| {});
    let mut packet = [0u8; MAX_PACKET];
    let hdr = postcard::to_slice(&Header { kind: FrameKind::Data, epoch: 1, seq: 0, ack: 0 }, &mut packet)
        .unwrap()
        .len();
    packet[hdr..hdr + body.len()].copy_from_slice(&body);
    let n = lightrig_protocol::frame::seal(&mut packet, hdr + body.len(), &mut out);
    let mut got = Vec::new();
    host.receive_all(&out[..n], 1, |d| got.push(d));
    assert_eq!(got, vec![Delivery::Incompatible { seq: 0, protocol_version: 2, schema_hash: 0xfeed }]);
}

#[test]
fn unknown_message_types_are_told_from_bad_payloads() {
    // id 7, command variant 99.
    assert_eq!(link::decode::<HostMsg>(&[7, 99]), Err(FrameError::UnknownType));
    // GetClock with a trailing byte.
    assert_eq!(link::decode::<HostMsg>(&[7, 1, 0]), Err(FrameError::BadPayload));
    // Configure(Laser) cut short.
    assert_eq!(link::decode::<HostMsg>(&[7, 4, 1, 0]), Err(FrameError::BadPayload));
    assert_eq!(link::decode::<DeviceMsg>(&[3]), Err(FrameError::UnknownType));
    // Too short to hold a tag: damaged, not of an unknown type.
    assert_eq!(link::decode::<HostMsg>(&[]), Err(FrameError::BadPayload));
    assert_eq!(link::decode::<HostMsg>(&[7]), Err(FrameError::BadPayload));
    assert_eq!(link::decode::<DeviceMsg>(&[]), Err(FrameError::BadPayload));
    assert_eq!(link::decode::<HostMsg>(&[7, 1]), Ok(HostMsg { id: 7, command: Command::GetClock }));
}

#[test]
fn write_refuses_a_body_that_does_not_fit() {
    let mut out = [0u8; MAX_FRAME];
    let header = Header { kind: FrameKind::Datagram, epoch: 1, seq: 0, ack: 0 };
    assert_eq!(link::write(&header, Some(&&[0xAAu8; MAX_PACKET][..]), &mut out), 0);
    assert!(link::write(&header, Some(&&[0xAAu8; 100][..]), &mut out) > 0);
}

#[test]
fn largest_messages_fit_a_packet() {
    use lightrig_protocol::event::*;
    use lightrig_protocol::sequence::*;
    // The largest fixed-size message: a log line of full length.
    let text: heapless::String<LOG_TEXT_LEN> = core::iter::repeat_n('é', LOG_TEXT_LEN / 2).collect();
    let log = DeviceMsg::Event {
        index: u32::MAX,
        event: Event::Log { level: LogLevel::Debug, tick: u64::MAX, text },
    };
    assert!(postcard::experimental::serialized_size(&log).unwrap() <= MAX_MESSAGE);
    // A trigger event with every array full and every number at its widest.
    let snapshot = Snapshot {
        galvos: core::iter::repeat_n(Xy { x: u16::MAX, y: u16::MAX }, MAX_GALVOS).collect(),
        axes: core::iter::repeat_n(i32::MIN, MAX_STEPPERS).collect(),
        filters: core::iter::repeat_n(Some(u8::MAX), MAX_FILTER_WHEELS).collect(),
        lasers: u8::MAX,
    };
    let t = TriggerEvent {
        sequence: u32::MAX,
        item: u32::MAX,
        frame: u32::MAX,
        camera: 255,
        tick: u64::MAX,
        width: u32::MAX,
        snapshot,
    };
    let ev = DeviceMsg::Event { index: u32::MAX, event: Event::Trigger(t) };
    assert!(postcard::experimental::serialized_size(&ev).unwrap() <= MAX_MESSAGE);
    // A voice-coil item with all partials at their widest fits a chunk with room to spare.
    let partials = core::iter::repeat_n(
        Partial { freq_mhz: u32::MAX, amplitude: u16::MAX, phase: u16::MAX },
        MAX_PARTIALS,
    )
    .collect();
    let item = Item { delta: u32::MAX, action: Action::VoiceCoil { channel: 255, ramp: u32::MAX, partials } };
    assert!(postcard::experimental::serialized_size(&item).unwrap() * 4 < MAX_MESSAGE);
}

/// The update path is frozen across protocol versions (a host of any version updates a device
/// of any other): `Command::Update` is variant 14, `Reply::Update` 5, `Error::Update` 17, and
/// the update types keep their layout. A change here needs a new path, not an edit.
#[test]
fn the_update_path_keeps_its_variant_numbers() {
    use lightrig_protocol::update::{UpdateCommand, UpdateError, UpdatePhase, UpdateStatus};
    let host =
        postcard::to_allocvec(&HostMsg { id: 1, command: Command::Update(UpdateCommand::Status) }).unwrap();
    assert_eq!(host, [1, 14, 0]);
    let status = UpdateStatus { phase: UpdatePhase::Idle, running: None, fallback: None, slot: 0 };
    let ok = DeviceMsg::Response { id: 2, result: Ok(Reply::Update(status)) };
    assert_eq!(postcard::to_allocvec(&ok).unwrap(), [0, 2, 0, 5, 0, 0, 0, 0]);
    let err = DeviceMsg::Response { id: 3, result: Err(Error::Update(UpdateError::Unsupported)) };
    assert_eq!(postcard::to_allocvec(&err).unwrap(), [0, 3, 1, 17, 0]);
}
