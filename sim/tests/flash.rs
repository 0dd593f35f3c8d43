//! Firmware update of the virtual device over its link: the image sent, the device reset into
//! embassy-boot's swap, the new firmware confirmed, or rolled back when nobody confirms it;
//! nothing lights or moves during an update; a host of another schema can still update.

mod common;

use lightrig_firmware::sim::{virtual_device_info, SimBoard};
use lightrig_host::client::{Client, ClientError};
use lightrig_host::flash::{self, FlashError};
use lightrig_protocol::session::{ResetCause, Version};
use lightrig_protocol::update::{UpdateCommand, UpdateError, UpdatePhase};
use lightrig_protocol::{Command, Error};
use lightrig_sim::flash::virtual_image;
use lightrig_sim::transport::VirtualTransport;

fn v(minor: u16) -> Version {
    Version { major: 0, minor, patch: 0 }
}

fn device() -> Client<VirtualTransport> {
    Client::connect(VirtualTransport::new(virtual_device_info(), SimBoard::default()), 1).unwrap()
}

fn refused_for_update(e: ClientError) -> UpdateError {
    match e {
        ClientError::Refused { error: Error::Update(u), .. } => u,
        other => panic!("{other}"),
    }
}

/// Sends v0.2.0 and waits for the reset: the client of the new firmware.
fn update_to_v2(mut c: Client<VirtualTransport>) -> Client<VirtualTransport> {
    let mut seen = Vec::new();
    let st = flash::send(&mut c, &virtual_image(v(2)), |sent, total| seen.push((sent, total))).unwrap();
    assert_eq!(st.phase, UpdatePhase::Ready { image: virtual_image(v(2)).info });
    let total = virtual_image(v(2)).signed.len() as u32;
    assert_eq!(seen.first(), Some(&(0, total)));
    assert_eq!(seen.last(), Some(&(total, total)));
    let t = flash::await_reset(c, 5_000_000).unwrap();
    Client::connect(t, 2).unwrap()
}

#[test]
fn an_update_is_swapped_in_at_the_reset_and_kept_once_confirmed() {
    let mut c = device();
    assert_eq!(c.info().firmware, v(1));
    let st = flash::update(&mut c, UpdateCommand::Status).unwrap();
    assert_eq!((st.phase, st.running.map(|i| i.version), st.fallback), (UpdatePhase::Idle, Some(v(1)), None));
    let old_boot = c.info().boot_id;
    let mut c = update_to_v2(c);
    assert_ne!(c.info().boot_id, old_boot);
    assert_eq!((c.info().firmware, c.info().reset_cause), (v(2), ResetCause::Software));
    let st = flash::update(&mut c, UpdateCommand::Status).unwrap();
    assert_eq!(st.phase, UpdatePhase::Unconfirmed);
    assert_eq!((st.running.map(|i| i.version), st.fallback.map(|i| i.version)), (Some(v(2)), Some(v(1))));
    assert_eq!(flash::confirm(&mut c).unwrap().phase, UpdatePhase::Idle);
    // Confirmed: it stays past the confirmation window, through a reset.
    c.idle(61_000_000).unwrap();
    assert_eq!(flash::update(&mut c, UpdateCommand::Status).unwrap().running.map(|i| i.version), Some(v(2)));
    c.transport_mut().reset_at(0);
    let t = flash::await_reset(c, 5_000_000).unwrap_or_else(|e| panic!("{e}"));
    let c = Client::connect(t, 3).unwrap();
    assert_eq!(c.info().firmware, v(2));
}

#[test]
fn a_firmware_nobody_confirms_is_rolled_back_after_the_confirmation_window() {
    let mut c = update_to_v2(device());
    assert_eq!(c.info().firmware, v(2));
    // The host says nothing about the update for 60 s: the device resets, the bootloader
    // swaps the old firmware back.
    let gone = c.idle(61_000_000).err();
    assert!(gone.is_some(), "the device reset under the host");
    let t = c.into_transport();
    let mut c = Client::connect(t, 3).unwrap();
    assert_eq!((c.info().firmware, c.info().reset_cause), (v(1), ResetCause::Software));
    let st = flash::update(&mut c, UpdateCommand::Status).unwrap();
    assert_eq!((st.phase, st.running.map(|i| i.version)), (UpdatePhase::Idle, Some(v(1))));
}

#[test]
fn an_update_stops_what_lights_or_moves_and_nothing_starts_until_it_ends() {
    // Lasers configured and armed.
    let mut c = common::setup(device());
    assert_ne!(c.transport().device().rig().armed(), 0);
    // Stepper 0 on a long move (80 000 steps at 16 000 steps/s: 5 s).
    use lightrig_protocol::sequence::{Action, Profile};
    let far = Action::StepperMove { axis: 0, target: 40_000, profile: Profile { max_speed: 0, accel: 0 } };
    c.request(Command::Immediate(far)).unwrap();
    c.idle(500_000).unwrap();
    let img = virtual_image(v(2));
    flash::update(&mut c, UpdateCommand::Begin(img.info)).unwrap();
    assert_eq!(c.transport().device().rig().armed(), 0, "lasers disarmed by Begin");
    // The motor decelerates to a stop (0.1 s at 160 000 steps/s²), far from its target.
    let at_begin = c.transport().device().rig().board().steppers[0].position;
    c.idle(1_000_000).unwrap();
    let stopped = c.transport().device().rig().board().steppers[0].position;
    c.idle(1_000_000).unwrap();
    assert_eq!(c.transport().device().rig().board().steppers[0].position, stopped, "at rest");
    assert!(stopped - at_begin < 1_000 && stopped < 20_000, "{at_begin} → {stopped}");
    let e = c.request(Command::Arm { lasers: 0b1 }).unwrap_err();
    assert_eq!(refused_for_update(e), UpdateError::InProgress);
    flash::update(&mut c, UpdateCommand::Cancel).unwrap();
    c.request(Command::Arm { lasers: 0b1 }).unwrap();
    // An image for another board: refused, nothing begun.
    let other = lightrig_host::flash::Image::sign(
        &[0; 100],
        lightrig_protocol::session::BoardId::NucleoG474re,
        v(2),
        0,
        &lightrig_sim::flash::virtual_key(),
    );
    let e = flash::send(&mut c, &other, |_, _| {}).unwrap_err();
    let FlashError::Client(e) = e else { panic!("{e}") };
    assert!(matches!(refused_for_update(e), UpdateError::WrongBoard { .. }));
    assert_ne!(c.transport().device().rig().armed(), 0, "a refused image changes nothing");
    c.request(Command::Arm { lasers: 0b1 }).unwrap();
}

#[test]
fn a_host_of_another_schema_updates_the_device_all_the_same() {
    let t = VirtualTransport::new(virtual_device_info(), SimBoard::default());
    let (mut c, compatible) =
        Client::connect_for_update_as(t, 1, lightrig_protocol::PROTOCOL_VERSION, 0xdead_beef).unwrap();
    assert!(!compatible);
    // Its ordinary commands are refused; the update path is not.
    assert!(c.request(Command::GetStatus).is_err());
    let st = flash::send(&mut c, &virtual_image(v(3)), |_, _| {}).unwrap();
    assert!(matches!(st.phase, UpdatePhase::Ready { .. }));
    let t = flash::await_reset(c, 5_000_000).unwrap();
    let (mut c, _) = Client::connect_for_update(t, 2).unwrap();
    assert_eq!(c.info().firmware, v(3));
    flash::confirm(&mut c).unwrap();
}

#[test]
fn an_update_is_refused_while_a_sequence_runs() {
    use lightrig_protocol::sequence::{Action, Chunk, Item, StartAt};
    let mut c = common::setup(device());
    // One trigger a second from now: the sequence runs meanwhile.
    let mut items = heapless::Vec::new();
    items.push(Item { delta: 1_000_000, action: Action::Trigger { camera: 0, exposure: 0 } }).unwrap();
    c.request(Command::SequenceLoad(Chunk { sequence: 9, chunk: 0, last: true, items })).unwrap();
    c.request(Command::SequenceStart { sequence: 9, at: StartAt::Now }).unwrap();
    let e = flash::update(&mut c, UpdateCommand::Begin(virtual_image(v(2)).info)).unwrap_err();
    let FlashError::Client(ClientError::Refused { error: Error::InvalidState(s), .. }) = e else {
        panic!("{e}")
    };
    assert!(matches!(s, lightrig_protocol::event::DeviceState::Running { sequence: 9 }), "{s:?}");
    // Nothing was begun: the sequence goes on and may still be aborted as usual.
    assert_eq!(flash::update(&mut c, UpdateCommand::Status).unwrap().phase, UpdatePhase::Idle);
    c.request(Command::SequenceAbort { sequence: 9 }).unwrap();
    flash::update(&mut c, UpdateCommand::Begin(virtual_image(v(2)).info)).unwrap();
}

#[test]
fn a_transfer_cut_half_way_goes_on_where_the_device_stands() {
    use lightrig_protocol::update::UPDATE_CHUNK;
    let mut c = device();
    let img = virtual_image(v(2));
    // Begin and ten chunks, then the host is gone (a crash, the cable pulled).
    flash::update(&mut c, UpdateCommand::Begin(img.info)).unwrap();
    for k in 0..10 {
        let data = heapless::Vec::from_slice(&img.signed[k * UPDATE_CHUNK..(k + 1) * UPDATE_CHUNK]).unwrap();
        flash::update(&mut c, UpdateCommand::Write { offset: (k * UPDATE_CHUNK) as u32, data }).unwrap();
    }
    let t = c.into_transport();
    // A new host, the same image: the device says where it stands and the rest follows.
    let mut c = Client::connect(t, 5).unwrap();
    let mut first = None;
    let st = flash::send(&mut c, &img, |s, _| {
        first.get_or_insert(s);
    })
    .unwrap();
    assert_eq!(first, Some(10 * UPDATE_CHUNK as u32), "resumed after the ten chunks it had");
    assert_eq!(st.phase, UpdatePhase::Ready { image: img.info });
    let t = flash::await_reset(c, 5_000_000).unwrap();
    let mut c = Client::connect(t, 6).unwrap();
    assert_eq!(c.info().firmware, v(2));
    flash::confirm(&mut c).unwrap();
}

#[test]
fn a_cancel_right_after_finish_unmarks_the_image_and_the_device_does_not_reset() {
    let mut c = device();
    let boot = c.info().boot_id;
    let img = virtual_image(v(2));
    // The Cancel rides on the frame that acknowledges Finish's answer: the device sees it
    // before the reset that answer asked for.
    assert_eq!(flash::send(&mut c, &img, |_, _| {}).unwrap().phase, UpdatePhase::Ready { image: img.info });
    assert_eq!(flash::update(&mut c, UpdateCommand::Cancel).unwrap().phase, UpdatePhase::Idle);
    c.idle(2_000_000).unwrap();
    let st = flash::update(&mut c, UpdateCommand::Status).unwrap();
    assert_eq!((st.phase, st.running.map(|i| i.version)), (UpdatePhase::Idle, Some(v(1))));
    assert_eq!(c.transport().device().info().boot_id, boot, "no reset");
    assert!(!c.transport().device().wants_reset());
}

#[test]
fn the_development_public_key_is_the_virtual_secrets() {
    assert_eq!(
        lightrig_sim::flash::virtual_key().verifying_key().to_bytes(),
        lightrig_firmware::boards::DEVELOPMENT_PUBLIC_KEY
    );
}
