//! `lightrig-hil update`: firmware updates of the emulated board over its protocol UART, with
//! its flash in a file that survives resets and restarts of QEMU (`flash=PATH`), the real
//! firmware's update code and embassy-boot's swap running on the emulated Cortex-M4, and the
//! power cut by ending QEMU in the middle of the swap (`cut=N`).
//!
//! The emulator runs the firmware's ELF whatever its active slot holds; the version the board
//! reports is the one its active slot's signed image carries.

use std::path::{Path, PathBuf};
use std::time::Duration;

use lightrig_firmware::boards::qemu_flash::{ACTIVE, FILE_LEN};
use lightrig_host::client::Client;
use lightrig_host::flash::{self, FlashError, Image};
use lightrig_host::transport::{SerialTransport, Transport};
use lightrig_protocol::session::{BoardId, ResetCause, Version};
use lightrig_protocol::update::{UpdateCommand, UpdateError, UpdatePhase, UPDATE_CHUNK};
use lightrig_protocol::{Error, SCHEMA_HASH};

use crate::qemu::{Options, Qemu};

type Dyn = Box<dyn Transport>;

fn v(minor: u16) -> Version {
    Version { major: 0, minor, patch: 0 }
}

/// An image for the emulated board signed with the development key (stand-in code, 20 KB).
fn image(version: Version) -> Image {
    let code = lightrig_sim::flash::virtual_code(version, 20_000);
    Image::sign(&code, BoardId::QemuMps2An386, version, SCHEMA_HASH, &lightrig_sim::flash::virtual_key())
}

/// A new flash file as the factory leaves it: `version`'s image in the active partition, the
/// rest erased.
fn factory(path: &Path, version: Version) -> Result<(), String> {
    let mut bytes = vec![0xFFu8; FILE_LEN as usize];
    let signed = image(version).signed;
    bytes[ACTIVE.0 as usize..ACTIVE.0 as usize + signed.len()].copy_from_slice(&signed);
    std::fs::write(path, bytes).map_err(|e| format!("{}: {e}", path.display()))
}

struct Board {
    elf: PathBuf,
    shift: u8,
    logs: PathBuf,
    flash: PathBuf,
    nonce: u32,
}

impl Board {
    fn start(&self, cut: Option<u32>) -> Result<Qemu, String> {
        let mut args = vec![format!("boot={:#x}", self.nonce), "idle=spin".into()];
        args.push(format!("flash={}", self.flash.display()));
        if let Some(n) = cut {
            args.push(format!("cut={n}"));
        }
        Qemu::start(&Options { elf: self.elf.clone(), shift: self.shift, args, log_dir: self.logs.clone() })
    }

    fn connect(&mut self, q: &Qemu) -> Result<Client<Dyn>, String> {
        self.nonce = self.nonce.wrapping_add(0x10);
        let t: Dyn = Box::new(SerialTransport::open(&q.uart0, 115_200).map_err(|e| e.to_string())?);
        Client::connect(t, self.nonce).map_err(|e| format!("Hello: {e}"))
    }

    /// Waits for the board to reset after marking an image and says Hello to the new start.
    fn after_reset(&mut self, c: Client<Dyn>) -> Result<Client<Dyn>, String> {
        let t = flash::await_reset(c, 30_000_000).map_err(|e| e.to_string())?;
        self.nonce = self.nonce.wrapping_add(0x10);
        // The same pty: the emulated MCU reset, QEMU and its UART stayed.
        std::thread::sleep(Duration::from_millis(200));
        Client::connect(t, self.nonce).map_err(|e| format!("Hello after the reset: {e}"))
    }
}

fn status(c: &mut Client<Dyn>) -> Result<lightrig_protocol::update::UpdateStatus, String> {
    flash::update(c, UpdateCommand::Status).map_err(|e| e.to_string())
}

fn expect(what: &str, ok: bool, detail: impl std::fmt::Debug) -> Result<(), String> {
    if ok {
        Ok(())
    } else {
        Err(format!("{what}: {detail:?}"))
    }
}

fn refused(e: FlashError) -> Option<UpdateError> {
    match e {
        FlashError::Client(lightrig_host::client::ClientError::Refused {
            error: Error::Update(u), ..
        }) => Some(u),
        _ => None,
    }
}

/// A good update swapped in and confirmed; bad images refused before any swap; a transfer cut
/// half-way leaves the board answering with its firmware.
fn good_and_bad_updates(b: &mut Board) -> Result<(), String> {
    factory(&b.flash, v(1))?;
    let q = b.start(None)?;
    let mut c = b.connect(&q)?;
    expect("factory version", c.info().firmware == v(1), c.info().firmware)?;
    let st = flash::send(&mut c, &image(v(2)), |_, _| {}).map_err(|e| e.to_string())?;
    expect("marked", matches!(st.phase, UpdatePhase::Ready { .. }), st.phase)?;
    let mut c = b.after_reset(c)?;
    expect("new version after the swap", c.info().firmware == v(2), c.info().firmware)?;
    expect("software reset", c.info().reset_cause == ResetCause::Software, c.info().reset_cause)?;
    let st = status(&mut c)?;
    expect("unconfirmed until the host says so", st.phase == UpdatePhase::Unconfirmed, st.phase)?;
    expect("fallback", st.fallback.map(|i| i.version) == Some(v(1)), st.fallback)?;
    flash::confirm(&mut c).map_err(|e| e.to_string())?;

    // A byte changed after signing, a foreign key, another board: refused, nothing swapped.
    let mut corrupted = image(v(3));
    corrupted.signed[100] ^= 0x01;
    let foreign = ed25519_dalek::SigningKey::from_bytes(&[7; 32]);
    let code = lightrig_sim::flash::virtual_code(v(3), 20_000);
    let other_key = Image::sign(&code, BoardId::QemuMps2An386, v(3), SCHEMA_HASH, &foreign);
    let other_board =
        Image::sign(&code, BoardId::NucleoG474re, v(3), SCHEMA_HASH, &lightrig_sim::flash::virtual_key());
    for (name, img, want) in [
        ("corrupted", &corrupted, UpdateError::BadSignature),
        ("foreign key", &other_key, UpdateError::BadSignature),
        (
            "other board",
            &other_board,
            UpdateError::WrongBoard { image: BoardId::NucleoG474re, device: BoardId::QemuMps2An386 },
        ),
    ] {
        let e = flash::send(&mut c, img, |_, _| {}).expect_err(name);
        let got = refused(e);
        expect(name, got == Some(want), got)?;
        let st = status(&mut c)?;
        expect("still the confirmed firmware", st.running.map(|i| i.version) == Some(v(2)), st.running)?;
    }

    // A transfer cut half-way: the host goes, a new one finds the board answering.
    let img = image(v(3));
    flash::update(&mut c, UpdateCommand::Begin(img.info)).map_err(|e| e.to_string())?;
    for (k, chunk) in img.signed.chunks(UPDATE_CHUNK).take(30).enumerate() {
        let data = heapless::Vec::from_slice(chunk).map_err(|_| "chunk")?;
        flash::update(&mut c, UpdateCommand::Write { offset: (k * UPDATE_CHUNK) as u32, data })
            .map_err(|e| e.to_string())?;
    }
    drop(c);
    let mut c = b.connect(&q)?;
    expect("answers after a cut transfer", c.info().firmware == v(2), c.info().firmware)?;
    let st = status(&mut c)?;
    expect("the transfer waits", matches!(st.phase, UpdatePhase::Receiving { .. }), st.phase)?;
    flash::update(&mut c, UpdateCommand::Cancel).map_err(|e| e.to_string())?;
    drop(c);
    drop(q);
    // Power off and on: the confirmed firmware stays.
    let q = b.start(None)?;
    let c = b.connect(&q)?;
    expect("confirmed firmware after a power cycle", c.info().firmware == v(2), c.info().firmware)?;
    expect("power-on", c.info().reset_cause == ResetCause::PowerOn, c.info().reset_cause)
}

/// An image swapped in and never confirmed: the next start swaps the old one back.
fn unconfirmed_is_rolled_back(b: &mut Board) -> Result<(), String> {
    factory(&b.flash, v(1))?;
    let q = b.start(None)?;
    let mut c = b.connect(&q)?;
    flash::send(&mut c, &image(v(2)), |_, _| {}).map_err(|e| e.to_string())?;
    let c = b.after_reset(c)?;
    expect("swapped in", c.info().firmware == v(2), c.info().firmware)?;
    drop(c);
    drop(q);
    let q = b.start(None)?;
    let mut c = b.connect(&q)?;
    expect("rolled back at the next start", c.info().firmware == v(1), c.info().firmware)?;
    let st = status(&mut c)?;
    expect("nothing unconfirmed", st.phase == UpdatePhase::Idle, st.phase)
}

/// The power cut at flash operation `cut` of the swap: the next start goes on with it where it
/// stopped (embassy-boot's progress marks), and the board answers with the new firmware.
fn power_cut_in_the_swap(b: &mut Board, cut: u32) -> Result<(), String> {
    factory(&b.flash, v(1))?;
    let mut q = b.start(Some(cut))?;
    let mut c = b.connect(&q)?;
    flash::send(&mut c, &image(v(2)), |_, _| {}).map_err(|e| e.to_string())?;
    // The board resets into the swap and QEMU ends at the cut.
    let _ = flash::await_reset(c, 30_000_000);
    let ended = q.wait_exit(Duration::from_secs(20));
    expect("QEMU ended at the cut", ended.is_some(), cut)?;
    drop(q);
    let q = b.start(None)?;
    let mut c = b.connect(&q)?;
    let running = c.info().firmware;
    expect("a whole image after the cut", running == v(2), running)?;
    let st = status(&mut c)?;
    expect("the new image waits for its confirmation", st.phase == UpdatePhase::Unconfirmed, st.phase)?;
    flash::confirm(&mut c).map_err(|e| e.to_string())?;
    drop(c);
    drop(q);
    let q = b.start(None)?;
    let c = b.connect(&q)?;
    expect("kept once confirmed", c.info().firmware == v(2), c.info().firmware)
}

/// Runs the update checks; the number that failed.
pub fn run(elf: &Path, shift: u8, logs: &Path) -> Result<usize, String> {
    std::fs::create_dir_all(logs).map_err(|e| format!("{}: {e}", logs.display()))?;
    let mut b = Board {
        elf: elf.to_path_buf(),
        shift,
        logs: logs.to_path_buf(),
        flash: logs.join("flash.img"),
        nonce: crate::boot_nonce(),
    };
    let mut failed = 0;
    let mut check = |name: String, r: Result<(), String>| match &r {
        Ok(()) => println!("  ok    {name}"),
        Err(e) => {
            println!("  FAIL  {name}: {e}");
            failed += 1;
        }
    };
    let t0 = std::time::Instant::now();
    check("update_swapped_in_confirmed_and_bad_images_refused".into(), good_and_bad_updates(&mut b));
    check("update_never_confirmed_is_rolled_back".into(), unconfirmed_is_rolled_back(&mut b));
    // Cuts spread over the swap (16 pages, each erased in 256-byte and written in 64-byte
    // pieces: about 2 600 operations).
    for cut in [1, 2, 70, 700, 1_500, 2_200] {
        check(format!("update_power_cut_at_swap_operation_{cut}"), power_cut_in_the_swap(&mut b, cut));
    }
    println!("lightrig-hil update: {failed} failed, {:.1} s", t0.elapsed().as_secs_f64());
    Ok(failed)
}
