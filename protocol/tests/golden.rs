//! Golden vectors: representative frames and their exact bytes, checked both ways.
//!
//! `protocol/golden/frames.txt` is the normative list: one frame per line,
//! `name | value (Rust Debug) | frame bytes (hex)`. Any change to the wire format changes a
//! line and shows up in review. After an intended change, regenerate it with
//! `LIGHTRIG_BLESS=1 cargo test -p lightrig-protocol --test golden` and bump
//! `PROTOCOL_VERSION` if old peers can no longer talk to new ones.

use heapless::Vec as HVec;
use lightrig_protocol::config::*;
use lightrig_protocol::error::Peripheral;
use lightrig_protocol::event::*;
use lightrig_protocol::frame::{FrameDecoder, FrameError};
use lightrig_protocol::link::{self, FrameKind, Header, LinkStats};
use lightrig_protocol::message::Status;
use lightrig_protocol::sequence::*;
use lightrig_protocol::session::{BoardId, Version};
use lightrig_protocol::update::{self, ImageInfo, UpdateCommand, UpdateError, UpdatePhase, UpdateStatus};
use lightrig_protocol::*;

mod common;
use common::device_info;

const PATH: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/golden/frames.txt");

#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq)]
enum Body {
    None,
    Host(HostMsg),
    Device(DeviceMsg),
    Nak(FrameError),
    Nonce(u32),
    SyncAck(link::SyncAckBody),
}

struct Vector {
    name: &'static str,
    header: Header,
    body: Body,
}

fn data(seq: u16, ack: u16) -> Header {
    Header { kind: FrameKind::Data, epoch: 1, seq, ack }
}

fn host(name: &'static str, seq: u16, id: u16, command: Command) -> Vector {
    Vector { name, header: data(seq, 0), body: Body::Host(HostMsg { id, command }) }
}

fn device(name: &'static str, seq: u16, msg: DeviceMsg) -> Vector {
    Vector { name, header: data(seq, 1), body: Body::Device(msg) }
}

fn ok(id: u16, reply: Reply) -> DeviceMsg {
    DeviceMsg::Response { id, result: Ok(reply) }
}

fn event(index: u32, event: Event) -> DeviceMsg {
    DeviceMsg::Event { index, event }
}

fn image() -> ImageInfo {
    ImageInfo {
        board: BoardId::NucleoG474re,
        version: Version { major: 1, minor: 2, patch: 3 },
        schema_hash: 0x0123_4567_89ab_cdef,
        code_len: 100_000,
    }
}

fn vectors() -> Vec<Vector> {
    let ctl =
        |name, kind, seq, ack| Vector { name, header: Header { kind, epoch: 1, seq, ack }, body: Body::None };
    let sync = |name, kind, nonce| Vector {
        name,
        header: Header { kind, epoch: 1, seq: 0, ack: 0 },
        body: Body::Nonce(nonce),
    };
    let galvo = GalvoConfig {
        galvo: 0,
        dac: DacKind::Dac8563,
        x: GalvoAxis { min_code: 1000, max_code: 64535, zero_code: 32768, nanorad_per_code: 5326 },
        y: GalvoAxis { min_code: 1000, max_code: 64535, zero_code: 32768, nanorad_per_code: -5326 },
        park: Xy { x: 32768, y: 32768 },
        settle_ticks: 300,
    };
    let stepper = StepperConfig {
        axis: 0,
        kind: AxisKind::Rotary,
        steps_per_unit: Ratio { num: 6400, den: 9 },
        max_speed: 20_000,
        accel: 40_000,
        limits: None,
        homing: Homing { mode: HomingMode::ToIndex, speed: 2_000, backoff: 100, position: 0 },
        invert_dir: false,
        enable: Polarity::ActiveLow,
        limit_min: Input::Unused,
        limit_max: Input::Unused,
        index: Input::Wired(Polarity::ActiveLow),
    };
    let partials: HVec<Partial, MAX_PARTIALS> = [
        Partial { freq_mhz: 20_000, amplitude: 20_000, phase: 0 },
        Partial { freq_mhz: 30_000, amplitude: 12_000, phase: 16_384 },
    ]
    .into_iter()
    .collect();
    let items: HVec<Item, MAX_CHUNK_ITEMS> = [
        Item { delta: 0, action: Action::GalvoPoint { galvo: 0, to: Xy { x: 30000, y: 31000 } } },
        Item { delta: 300, action: Action::Laser { channel: 0, on: true } },
        Item { delta: 50, action: Action::Trigger { camera: 0, exposure: 0 } },
        Item { delta: 20_000, action: Action::Laser { channel: 0, on: false } },
        Item {
            delta: 10,
            action: Action::GalvoLine {
                galvo: 0,
                to: Xy { x: 34000, y: 31000 },
                duration: 1_000,
                steps: 100,
            },
        },
        Item {
            delta: 0,
            action: Action::StepperMove { axis: 0, target: -6400, profile: Profile::default() },
        },
        Item {
            delta: 0,
            action: Action::Wait { until: WaitFor::MoveDone(AxisRef::Stepper(0)), timeout: 5_000_000 },
        },
        Item { delta: 0, action: Action::FilterWheel { wheel: 0, slot: 3 } },
        Item { delta: 0, action: Action::VoiceCoil { channel: 1, ramp: 4_800, partials } },
        Item { delta: 0, action: Action::Marker { id: 42 } },
    ]
    .into_iter()
    .collect();
    let snapshot = Snapshot {
        galvos: [Xy { x: 30000, y: 31000 }].into_iter().collect(),
        axes: [-6400, 1200].into_iter().collect(),
        filters: [Some(3)].into_iter().collect(),
        lasers: 0b001,
    };
    vec![
        sync("link.sync", FrameKind::Sync, 0xC0FF_EE42),
        Vector {
            name: "link.sync_ack",
            header: Header { kind: FrameKind::SyncAck, epoch: 1, seq: 0, ack: 0 },
            body: Body::SyncAck(link::SyncAckBody { nonce: 0xC0FF_EE42, boot_nonce: 0x5eed_0001 }),
        },
        sync("link.confirm", FrameKind::Confirm, 0x5eed_0001),
        ctl("link.ack", FrameKind::Ack, 0, 5),
        ctl("link.resync", FrameKind::Resync, 0, 0),
        Vector {
            name: "link.nak",
            header: Header { kind: FrameKind::Nak, epoch: 1, seq: 0, ack: 3 },
            body: Body::Nak(FrameError::BadCrc),
        },
        host(
            "host.hello",
            0,
            1,
            Command::Hello { protocol_version: PROTOCOL_VERSION, schema_hash: SCHEMA_HASH },
        ),
        host("host.get_clock", 1, 2, Command::GetClock),
        host("host.get_status", 2, 3, Command::GetStatus),
        host("host.heartbeat", 300, 300, Command::Heartbeat),
        host("host.configure.galvo", 3, 4, Command::Configure(ConfigItem::Galvo(galvo))),
        host(
            "host.configure.laser",
            4,
            5,
            Command::Configure(ConfigItem::Laser(LaserConfig {
                channel: 0,
                wavelength_nm: 635,
                warmup_ticks: 50_000,
                max_on_ticks: 60_000_000,
                enable: Polarity::ActiveHigh,
                interlock: Input::Wired(Polarity::ActiveHigh),
            })),
        ),
        host("host.configure.stepper", 5, 6, Command::Configure(ConfigItem::Stepper(stepper))),
        host(
            "host.configure.filter_wheel",
            6,
            7,
            Command::Configure(ConfigItem::FilterWheel(FilterWheelConfig {
                wheel: 0,
                slots: 6,
                steps_per_rev: 3200,
                max_speed: 4000,
                accel: 16000,
                index: Input::Wired(Polarity::ActiveLow),
                index_offset: -40,
                invert_dir: true,
                enable: Polarity::ActiveLow,
            })),
        ),
        host(
            "host.configure.voice_coil",
            7,
            8,
            Command::Configure(ConfigItem::VoiceCoil(VoiceCoilConfig {
                channel: 1,
                sample_rate_hz: 48_000,
                max_amplitude: 60_000,
            })),
        ),
        host(
            "host.configure.camera",
            8,
            9,
            Command::Configure(ConfigItem::Camera(CameraConfig {
                camera: 0,
                pulse_ticks: 100,
                polarity: Polarity::ActiveHigh,
                exposure_input: Input::Wired(Polarity::ActiveHigh),
                min_interval_ticks: 16_667,
            })),
        ),
        host(
            "host.configure.safety",
            9,
            10,
            Command::Configure(ConfigItem::Safety(SafetyConfig { heartbeat_timeout_ticks: 500_000 })),
        ),
        host("host.arm", 10, 11, Command::Arm { lasers: 0b111 }),
        host("host.disarm", 11, 12, Command::Disarm),
        host("host.clear_fault", 12, 13, Command::ClearFault),
        host("host.home", 13, 14, Command::Home(AxisRef::FilterWheel(0))),
        host(
            "host.immediate",
            14,
            15,
            Command::Immediate(Action::GalvoPoint { galvo: 0, to: Xy { x: 32768, y: 32768 } }),
        ),
        host(
            "host.sequence_load",
            15,
            16,
            Command::SequenceLoad(Chunk { sequence: 7, chunk: 0, last: false, items }),
        ),
        host(
            "host.sequence_start",
            16,
            17,
            Command::SequenceStart { sequence: 7, at: StartAt::Tick(123_456_789) },
        ),
        host("host.sequence_abort", 17, 18, Command::SequenceAbort { sequence: 7 }),
        host("host.update.status", 20, 21, Command::Update(UpdateCommand::Status)),
        host("host.update.begin", 21, 22, Command::Update(UpdateCommand::Begin(image()))),
        host(
            "host.update.write",
            22,
            23,
            Command::Update(UpdateCommand::Write {
                offset: 256,
                data: HVec::from_slice(&[0xde, 0xad, 0xbe, 0xef]).unwrap(),
            }),
        ),
        host(
            "host.update.finish",
            23,
            24,
            Command::Update(UpdateCommand::Finish(update::Signature { r: [0x11; 32], s: [0x22; 32] })),
        ),
        host("host.update.confirm", 24, 25, Command::Update(UpdateCommand::Confirm)),
        Vector {
            name: "host.emergency_stop.datagram",
            header: Header { kind: FrameKind::Datagram, epoch: 1, seq: 0, ack: 0 },
            body: Body::Host(HostMsg { id: 19, command: Command::EmergencyStop }),
        },
        device("device.hello", 0, ok(1, Reply::Hello(device_info()))),
        device("device.clock", 1, ok(2, Reply::Clock { tick: 987_654_321_012 })),
        device(
            "device.status",
            2,
            ok(
                3,
                Reply::Status(Status {
                    state: DeviceState::Ready,
                    armed: 0,
                    lasers_on: 0,
                    tick: 5_000_000,
                    buffer: None,
                    unacked: 0,
                    link: LinkStats {
                        frames_sent: 10,
                        frames_received: 12,
                        bad_crc: 1,
                        ..Default::default()
                    },
                }),
            ),
        ),
        device("device.done", 3, ok(4, Reply::Done)),
        device(
            "device.buffer",
            4,
            ok(
                16,
                Reply::Buffer(BufferStatus {
                    sequence: 7,
                    capacity: 256,
                    free: 246,
                    next_chunk: 1,
                    executed: 0,
                }),
            ),
        ),
        device(
            "device.err.invalid_config",
            5,
            DeviceMsg::Response {
                id: 5,
                result: Err(Error::InvalidConfig(ConfigError {
                    field: ConfigField::LaserMaxOnTicks,
                    index: 0,
                    reason: InvalidReason::Zero,
                })),
            },
        ),
        device(
            "device.err.schema_mismatch",
            6,
            DeviceMsg::Response {
                id: 1,
                result: Err(Error::SchemaMismatch { device: SCHEMA_HASH, host: 0x0123_4567_89ab_cdef }),
            },
        ),
        device(
            "device.err.no_such_peripheral",
            7,
            DeviceMsg::Response {
                id: 9,
                result: Err(Error::NoSuchPeripheral { kind: Peripheral::Camera, index: 2, count: 1 }),
            },
        ),
        device(
            "device.update.receiving",
            17,
            ok(
                25,
                Reply::Update(UpdateStatus {
                    phase: UpdatePhase::Receiving { image: image(), received: 4096 },
                    running: Some(ImageInfo { version: Version { major: 0, minor: 9, patch: 0 }, ..image() }),
                    fallback: None,
                    slot: 0x3_0000,
                }),
            ),
        ),
        device(
            "device.err.update.wrong_board",
            18,
            DeviceMsg::Response {
                id: 26,
                result: Err(Error::Update(UpdateError::WrongBoard {
                    image: BoardId::QemuMps2An386,
                    device: BoardId::NucleoG474re,
                })),
            },
        ),
        device("device.rejected", 8, DeviceMsg::Rejected { seq: 20, reason: FrameError::BadPayload }),
        device(
            "device.event.trigger",
            9,
            event(
                100,
                Event::Trigger(TriggerEvent {
                    sequence: 7,
                    item: 2,
                    frame: 0,
                    camera: 0,
                    tick: 1_000_350,
                    width: 100,
                    snapshot,
                }),
            ),
        ),
        device(
            "device.event.exposure",
            10,
            event(101, Event::Exposure { camera: 0, active: true, tick: 1_000_362 }),
        ),
        device(
            "device.event.move_done",
            11,
            event(102, Event::MoveDone { axis: AxisRef::Stepper(0), position: -6400, tick: 2_000_000 }),
        ),
        device(
            "device.event.homed",
            12,
            event(103, Event::Homed { axis: AxisRef::FilterWheel(0), position: 0, tick: 2_100_000 }),
        ),
        device(
            "device.event.switch",
            13,
            event(
                104,
                Event::Switch {
                    axis: AxisRef::Stepper(1),
                    switch: Switch::Max,
                    position: 52_000,
                    tick: 2_200_000,
                },
            ),
        ),
        device("device.event.laser_ready", 14, event(105, Event::LaserReady { channel: 0, tick: 1_050_000 })),
        device(
            "device.event.marker",
            15,
            event(106, Event::Marker { sequence: 7, item: 9, id: 42, tick: 2_300_000 }),
        ),
        device(
            "device.event.buffer",
            16,
            event(
                107,
                Event::Buffer(BufferStatus {
                    sequence: 7,
                    capacity: 256,
                    free: 128,
                    next_chunk: 12,
                    executed: 300,
                }),
            ),
        ),
        device(
            "device.event.underrun",
            17,
            event(108, Event::Underrun { sequence: 7, item: 310, tick: 3_000_000 }),
        ),
        device(
            "device.event.sequence_done",
            18,
            event(109, Event::SequenceDone { sequence: 7, items: 400, tick: 4_000_000 }),
        ),
        device(
            "device.event.fault",
            19,
            event(110, Event::Fault { cause: FaultCause::LaserOnTime { channel: 2 }, tick: 4_100_000 }),
        ),
        device(
            "device.event.state",
            20,
            event(
                111,
                Event::State {
                    state: DeviceState::Faulted(FaultCause::HeartbeatLost),
                    armed: 0,
                    tick: 4_200_000,
                },
            ),
        ),
        device(
            "device.event.log",
            21,
            event(
                112,
                Event::Log {
                    level: LogLevel::Warn,
                    tick: 4_300_000,
                    text: heapless::String::try_from("interlock open on laser 2").unwrap(),
                },
            ),
        ),
    ]
}

fn encode(v: &Vector) -> Vec<u8> {
    let mut out = [0u8; MAX_FRAME];
    let n = match &v.body {
        Body::None => link::write::<()>(&v.header, None, &mut out),
        Body::Host(m) => link::write(&v.header, Some(m), &mut out),
        Body::Device(m) => link::write(&v.header, Some(m), &mut out),
        Body::Nak(e) => link::write(&v.header, Some(e), &mut out),
        Body::Nonce(n) => link::write(&v.header, Some(n), &mut out),
        Body::SyncAck(b) => link::write(&v.header, Some(b), &mut out),
    };
    out[..n].to_vec()
}

fn describe(v: &Vector) -> String {
    let body = match &v.body {
        Body::None => String::new(),
        Body::Host(m) => format!(" {m:?}"),
        Body::Device(m) => format!(" {m:?}"),
        Body::Nak(e) => format!(" {e:?}"),
        Body::Nonce(n) => format!(" nonce 0x{n:08x}"),
        Body::SyncAck(b) => format!(" {b:?}"),
    };
    format!("{:?}{body}", v.header)
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect::<Vec<_>>().join(" ")
}

fn unhex(s: &str) -> Vec<u8> {
    s.split_whitespace().map(|h| u8::from_str_radix(h, 16).expect("hex byte")).collect()
}

fn render() -> String {
    let mut s = String::new();
    s.push_str(
        "# lightrig protocol golden frames. Generated by protocol/tests/golden.rs; see docs/protocol.md.\n",
    );
    s.push_str(&format!("# protocol_version = {PROTOCOL_VERSION}\n# schema_hash = 0x{SCHEMA_HASH:016x}\n"));
    s.push_str("# name | value | frame (hex, COBS-encoded, ends with the 00 delimiter)\n");
    for v in vectors() {
        s.push_str(&format!("{} | {} | {}\n", v.name, describe(&v), hex(&encode(&v))));
    }
    s
}

/// Decodes one golden frame back into header and body.
fn decode(frame: &[u8], like: &Body) -> (Header, Body) {
    let mut dec = FrameDecoder::new();
    let mut packets = Vec::new();
    dec.feed(frame, |r| packets.push(r.expect("golden frame must decode").to_vec()));
    assert_eq!(packets.len(), 1, "one frame per line");
    let (header, body) = postcard::take_from_bytes::<Header>(&packets[0]).expect("header");
    let body = match like {
        Body::None => {
            assert!(body.is_empty());
            Body::None
        }
        Body::Host(_) => Body::Host(link::decode(body).expect("host message")),
        Body::Device(_) => Body::Device(link::decode(body).expect("device message")),
        Body::Nak(_) => Body::Nak(postcard::from_bytes(body).expect("nak reason")),
        Body::Nonce(_) => Body::Nonce(postcard::from_bytes(body).expect("nonce")),
        Body::SyncAck(_) => Body::SyncAck(postcard::from_bytes(body).expect("sync ack")),
    };
    (header, body)
}

#[test]
fn golden_frames_match_the_file_both_ways() {
    let expected = render();
    if std::env::var_os("LIGHTRIG_BLESS").is_some() {
        std::fs::write(PATH, &expected).expect("write golden file");
    }
    let file = std::fs::read_to_string(PATH).expect("protocol/golden/frames.txt exists");
    // Encoding: every line as generated from the values.
    for (want, got) in file.lines().zip(expected.lines()) {
        assert_eq!(got, want, "wire format changed; if intended, rerun with LIGHTRIG_BLESS=1");
    }
    assert_eq!(file.lines().count(), expected.lines().count(), "number of golden lines");
    // Decoding: the file's bytes give back the values.
    let vectors = vectors();
    let lines: Vec<&str> = file.lines().filter(|l| !l.starts_with('#')).collect();
    assert_eq!(lines.len(), vectors.len());
    for (line, v) in lines.iter().zip(&vectors) {
        let mut cols = line.splitn(3, " | ");
        let (name, _, bytes) = (cols.next().unwrap(), cols.next().unwrap(), cols.next().unwrap());
        assert_eq!(name, v.name);
        let (header, body) = decode(&unhex(bytes), &v.body);
        assert_eq!(header, v.header, "{name}");
        assert_eq!(body, v.body, "{name}");
    }
}

#[test]
fn every_golden_frame_fits_and_sample_config_is_valid() {
    for v in vectors() {
        assert!(encode(&v).len() <= MAX_FRAME, "{}", v.name);
        if let Body::Host(HostMsg { command: Command::Configure(item), .. }) = &v.body {
            assert_eq!(item.validate(&device_info()), Ok(()), "{}", v.name);
        }
    }
}

#[test]
fn exact_bytes_of_a_sync_frame() {
    // Header {Sync=3, epoch 1, seq 0, ack 0} = 03 01 00 00, nonce 0xC0FFEE42 as a varint,
    // then CRC-32 LE, COBS, 00 — built by hand here, independently of the encoder.
    let mut raw = vec![0x03, 0x01, 0x00, 0x00, 0xc2, 0xdc, 0xff, 0x87, 0x0c];
    let crc = lightrig_protocol::frame::CRC32.checksum(&raw).to_le_bytes();
    raw.extend_from_slice(&crc);
    let mut cobs = Vec::new();
    for block in raw.split(|&b| b == 0) {
        cobs.push(block.len() as u8 + 1);
        cobs.extend_from_slice(block);
    }
    cobs.push(0);
    assert_eq!(encode(&vectors()[0]), cobs);
}
