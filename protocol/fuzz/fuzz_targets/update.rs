//! `update`: the firmware's update logic (`lightrig_firmware::update::Updater`) over
//! embassy-boot's slots in memory, under arbitrary update commands, resets and power cuts. It
//! must never panic, and the board must always hold a whole image that was either flashed at
//! the factory or sent, signed, in full.
//!
//! The input is a script read with `arbitrary::Unstructured`: op bytes (`% 8`) and their
//! arguments until the input runs out or `MAX_OPS` ops have run:
//! 0 an arbitrary `UpdateCommand`; 1 `Begin` of a friendly image (this board, a length that
//! fits, one of three versions); 2 `Write` of the next chunk of the image begun (its true bytes,
//! or with one byte changed); 3 `Finish` with the true signature of the image begun, or an
//! arbitrary one; 4 `Confirm`; 5 `Cancel`; 6 a reset (the bootloader runs; the update in RAM is
//! lost); 7 a reset with the power cut after an arbitrary number of flash writes, then a
//! reset with the power on.
//!
//! Invariants, after every op:
//! - `Receiving { received }` never passes the image's signed length;
//! - the active slot always holds, byte for byte, the factory image or one of the images the
//!   script sent in full with their true signature (the running trailer names it);
//! - `Ready` only after a `Finish` with the true signature of exactly what was written.
//!
//! The seed `seeds/update/swap_confirm_cut` sends two small images, swaps and confirms one and
//! cuts the power in the other's swap; `UPDATE_FUZZ_TRACE=1` prints each image marked.

#![no_main]

use arbitrary::{Arbitrary, Unstructured};
use ed25519_dalek::{Signer, SigningKey};
use libfuzzer_sys::fuzz_target;
use lightrig_firmware::boot::BootSlots;
use lightrig_firmware::memflash::MemFlash;
use lightrig_firmware::update::Updater;
use lightrig_protocol::session::{BoardId, Version};
use lightrig_protocol::update::{ImageInfo, Signature, UpdateCommand, UpdatePhase, UPDATE_CHUNK};
use sha2::{Digest, Sha512};

type Flash = MemFlash<1024, 8>;
const ACTIVE: usize = 8 * 1024;
const BOARD: BoardId = BoardId::Virtual;
const MAX_OPS: usize = 200;

fn key() -> SigningKey {
    SigningKey::from_bytes(&[7; 32])
}

fn image(version: u16, code_len: u32) -> (ImageInfo, Vec<u8>) {
    let info = ImageInfo { board: BOARD, version: Version { major: version, minor: 0, patch: 0 }, schema_hash: 1, code_len };
    let mut out: Vec<u8> = (0..code_len).map(|k| (k as u8) ^ (version as u8).wrapping_mul(37)).collect();
    out.resize(info.trailer_at() as usize, 0xFF);
    out.extend_from_slice(&info.trailer());
    (info, out)
}

fn sign(bytes: &[u8]) -> Signature {
    Signature::from_bytes(&key().sign(&Sha512::digest(bytes)).to_bytes())
}

struct Chip {
    active: Flash,
    dfu: Flash,
    state: Flash,
}

impl Chip {
    fn slots(&self) -> BootSlots<Flash, Flash, Flash> {
        BootSlots::new(self.active.clone(), self.dfu.clone(), self.state.clone(), key().verifying_key().to_bytes())
    }
}

fuzz_target!(|data: &[u8]| {
    let mut u = Unstructured::new(data);
    let active = Flash::new(ACTIVE);
    let chip = Chip { dfu: active.on_same_chip(ACTIVE + 1024), state: active.on_same_chip(1024), active };
    let factory = image(1, 3000).1;
    chip.active.program(0, &factory);
    // Images that may legitimately run: the factory's and those sent whole with a true signature.
    let mut allowed: Vec<Vec<u8>> = vec![factory];
    let mut slots = chip.slots();
    let mut up = Updater::default();
    // The image begun by a friendly Begin, and what was written of it.
    let mut begun: Option<(ImageInfo, Vec<u8>)> = None;
    let mut written: Vec<u8> = Vec::new();
    // Bytes the device took, from the image's start: what a `Write` wrote (never a repeat).
    let received = |up: &Updater, slots: &mut BootSlots<Flash, Flash, Flash>| match up.status(slots).phase {
        UpdatePhase::Receiving { received, .. } => Some(received as usize),
        _ => None,
    };
    let took = |written: &mut Vec<u8>, before: Option<usize>, after: Option<usize>, data: &[u8]| {
        if let (Some(b), Some(a)) = (before, after) {
            if a > b {
                written.truncate(b);
                written.extend_from_slice(data);
            }
        }
    };
    for _ in 0..MAX_OPS {
        let Ok(op) = u.arbitrary::<u8>() else { break };
        match op % 8 {
            0 => {
                let Ok(cmd) = UpdateCommand::arbitrary(&mut u) else { break };
                if let UpdateCommand::Begin(i) = &cmd {
                    if begun.as_ref().is_none_or(|(b, _)| b != i) {
                        begun = None;
                    }
                }
                let before = received(&up, &mut slots);
                let _ = up.handle(&cmd, &mut slots, BOARD);
                if let UpdateCommand::Write { data, .. } = &cmd {
                    let after = received(&up, &mut slots);
                    took(&mut written, before, after, data);
                }
            }
            1 => {
                let version = 2 + u.int_in_range(0..=2u16).unwrap_or(0);
                let len = u.int_in_range(1..=(ACTIVE as u32 - 64)).unwrap_or(1);
                let (info, bytes) = image(version, len);
                if up.handle(&UpdateCommand::Begin(info), &mut slots, BOARD).is_ok() {
                    begun = Some((info, bytes));
                }
            }
            2 => {
                let Some((info, bytes)) = &begun else { continue };
                let Some(at) = received(&up, &mut slots) else { continue };
                let end = (at + UPDATE_CHUNK).min(bytes.len());
                if at >= end {
                    continue;
                }
                let mut chunk = bytes[at..end].to_vec();
                if u.ratio(1, 8).unwrap_or(false) {
                    let k = u.choose_index(chunk.len()).unwrap_or(0);
                    chunk[k] ^= 0x5a;
                }
                let data = heapless::Vec::from_slice(&chunk).unwrap();
                let _ = up.handle(&UpdateCommand::Write { offset: at as u32, data }, &mut slots, BOARD);
                let after = received(&up, &mut slots);
                took(&mut written, Some(at), after, &chunk);
                let _ = info;
            }
            3 => {
                let sig = match &begun {
                    Some((_, bytes)) if u.ratio(3, 4).unwrap_or(true) => sign(bytes),
                    _ => match Signature::arbitrary(&mut u) {
                        Ok(s) => s,
                        Err(_) => break,
                    },
                };
                let ok = up.handle(&UpdateCommand::Finish(sig), &mut slots, BOARD).is_ok();
                if ok {
                    if std::env::var_os("UPDATE_FUZZ_TRACE").is_some() {
                        eprintln!("update fuzz: marked an image");
                    }
                    // Marked only for exactly the bytes the signature covers.
                    let (_, bytes) = begun.as_ref().expect("Ready needs a friendly Begin: arbitrary ones never fit a true signature");
                    assert_eq!(&written, bytes, "an image marked that is not the one signed");
                    assert_eq!(sig, sign(bytes));
                    allowed.push(bytes.clone());
                }
            }
            4 => {
                let _ = up.handle(&UpdateCommand::Confirm, &mut slots, BOARD);
            }
            5 => {
                let _ = up.handle(&UpdateCommand::Cancel, &mut slots, BOARD);
            }
            6 => {
                let _ = slots.boot();
                slots = chip.slots();
                up = Updater::default();
            }
            _ => {
                let cut = u.int_in_range(0..=600u64).unwrap_or(0);
                chip.active.cut_after(Some(cut));
                let _ = slots.boot();
                chip.active.cut_after(None);
                slots.boot().expect("with the power back the bootloader finishes");
                slots = chip.slots();
                up = Updater::default();
            }
        }
        let st = up.status(&mut slots);
        match st.phase {
            UpdatePhase::Receiving { received: 0, .. } | UpdatePhase::Idle | UpdatePhase::Unconfirmed => written.clear(),
            _ => {}
        }
        if let UpdatePhase::Receiving { image, received } = st.phase {
            assert!(received <= image.signed_len(), "{received} of {}", image.signed_len());
        }
        let running = chip.active.contents();
        assert!(
            allowed.iter().any(|a| running[..a.len()] == a[..]),
            "the active slot holds no whole image that may run"
        );
        let info = st.running.expect("the running image has its trailer");
        assert!(allowed.iter().any(|a| ImageInfo::from_trailer(&a[a.len() - 64..]) == Some(info)));
    }
});
