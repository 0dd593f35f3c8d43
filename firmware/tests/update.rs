//! Firmware update over the link against embassy-boot's slots in memory: a good update swaps in
//! and is kept once confirmed; an unconfirmed one is swapped back; images for another board,
//! too large, altered or signed with another key are refused and leave the running image; a
//! transfer cut half-way resumes; the power cut at every flash write of the swap and of the
//! rollback leaves a whole image, old or new.

use ed25519_dalek::{Signer, SigningKey};
use lightrig_firmware::boot::BootSlots;
use lightrig_firmware::hal::FirmwareSlots;
use lightrig_firmware::memflash::MemFlash;
use lightrig_firmware::update::Updater;
use lightrig_protocol::session::{BoardId, Version};
use lightrig_protocol::update::{
    ImageInfo, Signature, UpdateCommand, UpdateError, UpdatePhase, UpdateStatus, UPDATE_CHUNK,
};
use sha2::{Digest, Sha512};

/// 1 KiB pages, 8-byte writes: an 8 KiB active slot, a 9 KiB update slot, a 1 KiB state page.
type Flash = MemFlash<1024, 8>;
const ACTIVE: usize = 8 * 1024;
const BOARD: BoardId = BoardId::Virtual;

/// One chip: its three partitions share its power.
#[derive(Clone)]
struct Chip {
    active: Flash,
    dfu: Flash,
    state: Flash,
}

impl Chip {
    fn new() -> Chip {
        let active = Flash::new(ACTIVE);
        let dfu = active.on_same_chip(ACTIVE + 1024);
        let state = active.on_same_chip(1024);
        Chip { active, dfu, state }
    }

    /// The slots as the firmware sees them after a reset (the same flash).
    fn slots(&self) -> BootSlots<Flash, Flash, Flash> {
        BootSlots::new(
            self.active.clone(),
            self.dfu.clone(),
            self.state.clone(),
            key().verifying_key().to_bytes(),
        )
    }

    /// A blank board flashed through its probe with `image`.
    fn factory(image: &[u8]) -> Chip {
        let chip = Chip::new();
        chip.active.program(0, image);
        chip
    }

    /// The image the active slot holds, compared byte for byte with the candidates.
    fn running(&self, candidates: &[&[u8]]) -> Option<usize> {
        let active = self.active.contents();
        candidates.iter().position(|c| active[..c.len()] == **c)
    }
}

fn key() -> SigningKey {
    SigningKey::from_bytes(&[7; 32])
}

fn info(major: u16, code_len: u32) -> ImageInfo {
    ImageInfo { board: BOARD, version: Version { major, minor: 0, patch: 0 }, schema_hash: 0x5eed, code_len }
}

/// Code (a pattern that differs per version), padding, trailer.
fn image(i: &ImageInfo) -> Vec<u8> {
    let mut out: Vec<u8> =
        (0..i.code_len).map(|k| (k as u8).wrapping_mul(31).wrapping_add(i.version.major as u8)).collect();
    out.resize(i.trailer_at() as usize, 0xFF);
    out.extend_from_slice(&i.trailer());
    out
}

fn sign_with(k: &SigningKey, bytes: &[u8]) -> Signature {
    Signature::from_bytes(&k.sign(&Sha512::digest(bytes)).to_bytes())
}

fn sign(bytes: &[u8]) -> Signature {
    sign_with(&key(), bytes)
}

fn write(
    u: &mut Updater,
    s: &mut impl FirmwareSlots,
    offset: usize,
    bytes: &[u8],
) -> Result<UpdateStatus, UpdateError> {
    let data = heapless::Vec::from_slice(bytes).unwrap();
    u.handle(&UpdateCommand::Write { offset: offset as u32, data }, s, BOARD)
}

/// Begin, every chunk in order, Finish.
fn send(
    u: &mut Updater,
    s: &mut impl FirmwareSlots,
    i: &ImageInfo,
    bytes: &[u8],
    sig: Signature,
) -> Result<UpdateStatus, UpdateError> {
    u.handle(&UpdateCommand::Begin(*i), s, BOARD)?;
    for (k, c) in bytes.chunks(UPDATE_CHUNK).enumerate() {
        write(u, s, k * UPDATE_CHUNK, c)?;
    }
    u.handle(&UpdateCommand::Finish(sig), s, BOARD)
}

fn status(u: &Updater, s: &mut impl FirmwareSlots) -> UpdateStatus {
    u.status(s)
}

#[test]
fn a_signed_update_is_swapped_in_at_reset_and_kept_once_confirmed() {
    let (v1, v2) = (info(1, 5000), info(2, 6100));
    let (old, new) = (image(&v1), image(&v2));
    let chip = Chip::factory(&old);
    let mut slots = chip.slots();
    let mut u = Updater::default();
    let st = status(&u, &mut slots);
    assert_eq!(
        (st.phase, st.running, st.fallback, st.slot),
        (UpdatePhase::Idle, Some(v1), None, ACTIVE as u32)
    );
    let st = send(&mut u, &mut slots, &v2, &new, sign(&new)).unwrap();
    assert_eq!(st.phase, UpdatePhase::Ready { image: v2 });
    assert_eq!(chip.running(&[&old, &new]), Some(0), "nothing swapped before the reset");
    // Reset: the bootloader swaps, the new firmware starts unconfirmed with the old as fallback.
    assert!(slots.boot().is_ok());
    assert_eq!(chip.running(&[&old, &new]), Some(1));
    let mut slots = chip.slots();
    let mut u = Updater::default();
    let st = status(&u, &mut slots);
    assert_eq!((st.phase, st.running, st.fallback), (UpdatePhase::Unconfirmed, Some(v2), Some(v1)));
    // No new update before this one is confirmed.
    let v3 = info(3, 100);
    assert_eq!(u.handle(&UpdateCommand::Begin(v3), &mut slots, BOARD), Err(UpdateError::Unconfirmed));
    let st = u.handle(&UpdateCommand::Confirm, &mut slots, BOARD).unwrap();
    assert_eq!(st.phase, UpdatePhase::Idle);
    assert_eq!(u.handle(&UpdateCommand::Confirm, &mut slots, BOARD), Err(UpdateError::NothingToConfirm));
    // Confirmed: the next resets keep it.
    slots.boot().unwrap();
    slots.boot().unwrap();
    assert_eq!(chip.running(&[&old, &new]), Some(1));
}

#[test]
fn an_update_never_confirmed_is_swapped_back_at_the_next_reset() {
    let (v1, v2) = (info(1, 7000), info(2, 3000));
    let (old, new) = (image(&v1), image(&v2));
    let chip = Chip::factory(&old);
    let mut slots = chip.slots();
    send(&mut Updater::default(), &mut slots, &v2, &new, sign(&new)).unwrap();
    slots.boot().unwrap();
    assert_eq!(chip.running(&[&old, &new]), Some(1));
    // It hangs, or never hears from the host: the watchdog resets it unconfirmed.
    slots.boot().unwrap();
    assert_eq!(chip.running(&[&old, &new]), Some(0), "rolled back");
    let mut slots = chip.slots();
    let st = status(&Updater::default(), &mut slots);
    assert_eq!((st.phase, st.running), (UpdatePhase::Idle, Some(v1)));
}

#[test]
fn images_for_another_board_too_large_altered_or_signed_by_another_key_are_refused() {
    let v1 = info(1, 4000);
    let old = image(&v1);
    let chip = Chip::factory(&old);
    let mut slots = chip.slots();
    let mut u = Updater::default();
    // Another board, or larger than the slot: refused before anything is written.
    let ops = chip.active.ops();
    let other = ImageInfo { board: BoardId::NucleoG474re, ..info(2, 100) };
    let e = u.handle(&UpdateCommand::Begin(other), &mut slots, BOARD);
    assert_eq!(e, Err(UpdateError::WrongBoard { image: BoardId::NucleoG474re, device: BOARD }));
    let big = info(2, ACTIVE as u32);
    assert_eq!(
        u.handle(&UpdateCommand::Begin(big), &mut slots, BOARD),
        Err(UpdateError::TooLarge { image: ACTIVE as u32 + 64, slot: ACTIVE as u32 })
    );
    assert_eq!(chip.active.ops(), ops, "no flash touched");
    assert!(!u.in_progress());

    let v2 = info(2, 3000);
    let new = image(&v2);
    // Signed with another key.
    let e = send(&mut u, &mut slots, &v2, &new, sign_with(&SigningKey::from_bytes(&[9; 32]), &new));
    assert_eq!(e, Err(UpdateError::BadSignature));
    // One byte altered on the way (the signature is the genuine one).
    let mut bent = new.clone();
    bent[1234] ^= 0x10;
    assert_eq!(send(&mut u, &mut slots, &v2, &bent, sign(&new)), Err(UpdateError::BadSignature));
    // A trailer other than the one announced (a signed image of another version).
    let v3 = info(3, 3000);
    let third = image(&v3);
    assert_eq!(send(&mut u, &mut slots, &v2, &third, sign(&third)), Err(UpdateError::TrailerMismatch));
    // Whatever was refused, the reset keeps the old image.
    slots.boot().unwrap();
    assert_eq!(chip.running(&[&old]), Some(0));
    // A refused image ends the update; one begun and cancelled too.
    assert!(!u.in_progress());
    u.handle(&UpdateCommand::Begin(v2), &mut slots, BOARD).unwrap();
    assert!(u.in_progress());
    u.handle(&UpdateCommand::Cancel, &mut slots, BOARD).unwrap();
    assert!(!u.in_progress());
    assert_eq!(u.handle(&UpdateCommand::Cancel, &mut slots, BOARD), Err(UpdateError::NotBegun));
}

#[test]
fn writes_go_in_order_a_repeat_is_acknowledged_and_a_cut_transfer_resumes() {
    let (v1, v2) = (info(1, 2000), info(2, 5000));
    let (old, new) = (image(&v1), image(&v2));
    let chip = Chip::factory(&old);
    let mut slots = chip.slots();
    let mut u = Updater::default();
    assert_eq!(write(&mut u, &mut slots, 0, &new[..UPDATE_CHUNK]), Err(UpdateError::NotBegun));
    u.handle(&UpdateCommand::Begin(v2), &mut slots, BOARD).unwrap();
    let chunk = |k: usize| &new[k * UPDATE_CHUNK..((k + 1) * UPDATE_CHUNK).min(new.len())];
    for k in 0..8 {
        write(&mut u, &mut slots, k * UPDATE_CHUNK, chunk(k)).unwrap();
    }
    // A chunk ahead, a short one, one past the end: refused, naming where the device stands.
    let at = 8 * UPDATE_CHUNK;
    assert_eq!(
        write(&mut u, &mut slots, at + UPDATE_CHUNK, chunk(9)),
        Err(UpdateError::OutOfOrder { expected: at as u32 })
    );
    assert_eq!(
        write(&mut u, &mut slots, at, &chunk(8)[..100]),
        Err(UpdateError::OutOfOrder { expected: at as u32 })
    );
    // A repeat (its answer was lost): acknowledged, nothing written again.
    let ops = chip.active.ops();
    let st = write(&mut u, &mut slots, 7 * UPDATE_CHUNK, chunk(7)).unwrap();
    assert_eq!(st.phase, UpdatePhase::Receiving { image: v2, received: at as u32 });
    assert_eq!(chip.active.ops(), ops);
    assert_eq!(
        u.handle(&UpdateCommand::Finish(sign(&new)), &mut slots, BOARD),
        Err(UpdateError::Incomplete { received: at as u32 })
    );
    // The host is unplugged and comes back: Begin of the same image says where to go on.
    let st = u.handle(&UpdateCommand::Begin(v2), &mut slots, BOARD).unwrap();
    assert_eq!(st.phase, UpdatePhase::Receiving { image: v2, received: at as u32 });
    for k in 8..new.len().div_ceil(UPDATE_CHUNK) {
        write(&mut u, &mut slots, k * UPDATE_CHUNK, chunk(k)).unwrap();
    }
    let end = new.len() as u32;
    assert_eq!(
        write(&mut u, &mut slots, new.len(), &[0; 64]),
        Err(UpdateError::OutOfOrder { expected: end })
    );
    assert_eq!(
        u.handle(&UpdateCommand::Finish(sign(&new)), &mut slots, BOARD).unwrap().phase,
        UpdatePhase::Ready { image: v2 }
    );
    slots.boot().unwrap();
    assert_eq!(chip.running(&[&old, &new]), Some(1));
}

/// A chip with `old` running and `new` marked for the swap.
fn ready(old: &[u8], v2: &ImageInfo, new: &[u8]) -> Chip {
    let chip = Chip::factory(old);
    send(&mut Updater::default(), &mut chip.slots(), v2, new, sign(new)).unwrap();
    chip
}

#[test]
fn the_power_cut_at_any_write_of_the_swap_or_the_rollback_leaves_a_whole_image() {
    let (v1, v2) = (info(1, 8000), info(2, 7500));
    let (old, new) = (image(&v1), image(&v2));
    // How many writes and erases a swap and a rollback take, uncut.
    let chip = ready(&old, &v2, &new);
    let before = chip.active.ops();
    chip.slots().boot().unwrap();
    let swap_ops = chip.active.ops() - before;
    chip.slots().boot().unwrap();
    let rollback_ops = chip.active.ops() - before - swap_ops;
    assert!(swap_ops > 100 && rollback_ops > 100, "{swap_ops} {rollback_ops}");
    for cut in 0..swap_ops {
        let chip = ready(&old, &v2, &new);
        chip.active.cut_after(Some(cut));
        assert!(chip.slots().boot().is_err(), "cut after {cut} of {swap_ops}");
        chip.active.cut_after(None);
        // Power back: the bootloader finishes the swap; the new image runs, unconfirmed.
        chip.slots().boot().unwrap();
        assert_eq!(chip.running(&[&old, &new]), Some(1), "swap cut after {cut} of {swap_ops}");
        assert!(chip.slots().unconfirmed().unwrap());
    }
    for cut in 0..rollback_ops {
        let chip = ready(&old, &v2, &new);
        chip.slots().boot().unwrap();
        chip.active.cut_after(Some(cut));
        assert!(chip.slots().boot().is_err());
        chip.active.cut_after(None);
        chip.slots().boot().unwrap();
        assert_eq!(chip.running(&[&old, &new]), Some(0), "rollback cut after {cut} of {rollback_ops}");
        assert!(!chip.slots().unconfirmed().unwrap());
    }
}
