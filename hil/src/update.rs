//! `lightrig-hil update`: firmware updates of the emulated board over its protocol UART, whole
//! images: QEMU starts the board's bootloader (boards/qemu-mps2-an386-bootloader), which runs
//! embassy-boot's swap on the board's flash, a file that survives resets and restarts of QEMU
//! (`flash=PATH`), then copies the active slot's firmware into the code RAM and starts it. The
//! images are the firmware itself, built for the slot (feature `slot`) as two versions that
//! differ only in the version they report, so the version the board says is the code it runs.
//! The power is cut by ending QEMU in the middle of the swap (`cut=N`).

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use lightrig_firmware::boards::qemu_flash::{ACTIVE, FILE_LEN};
use lightrig_host::client::Client;
use lightrig_host::flash::{self, FlashError, Image};
use lightrig_host::transport::{SerialTransport, Transport};
use lightrig_protocol::session::{BoardId, ResetCause, Version};
use lightrig_protocol::update::{UpdateCommand, UpdateError, UpdatePhase, UPDATE_CHUNK};
use lightrig_protocol::{Error, SCHEMA_HASH};

use crate::qemu::{repo_root, Options, Qemu};

type Dyn = Box<dyn Transport>;

fn v(minor: u16) -> Version {
    Version { major: 0, minor, patch: 0 }
}

fn cargo() -> Command {
    let mut c = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()));
    // The board workspaces have their own target directories and flags.
    c.env_remove("CARGO_TARGET_DIR").env_remove("RUSTFLAGS").env_remove("CARGO_BUILD_TARGET");
    c
}

fn run_ok(mut c: Command, what: &str) -> Result<(), String> {
    let status = c.status().map_err(|e| format!("{what}: {e}"))?;
    if status.success() {
        Ok(())
    } else {
        Err(format!("{what} failed ({status})"))
    }
}

/// The bootloader's ELF and the firmware built for the slot as `version`, as a raw binary
/// (linked at `APP_BASE`: what the slot holds).
struct Builds {
    bootloader: PathBuf,
    firmware: Vec<(Version, Vec<u8>)>,
}

impl Builds {
    fn make(logs: &Path) -> Result<Self, String> {
        let root = repo_root();
        let boot_dir = root.join("boards/qemu-mps2-an386-bootloader");
        let mut c = cargo();
        c.args(["build", "--release", "--locked"]).current_dir(&boot_dir);
        run_ok(c, "building the bootloader")?;
        let bootloader = boot_dir.join("target/thumbv7em-none-eabihf/release/lightrig-qemu-bootloader");
        let board = root.join("boards/qemu-mps2-an386");
        let mut firmware = Vec::new();
        for version in [v(1), v(2)] {
            let text = format!("{}.{}.{}", version.major, version.minor, version.patch);
            let mut c = cargo();
            c.args(["build", "--release", "--locked", "--features", "slot", "--target-dir", "target/slot"])
                .env("LIGHTRIG_FIRMWARE_VERSION", &text)
                .current_dir(&board);
            run_ok(c, &format!("building the firmware {text} for the slot"))?;
            let elf = board.join("target/slot/thumbv7em-none-eabihf/release/lightrig-qemu");
            let bin = logs.join(format!("firmware-{text}.bin"));
            let mut c = Command::new("arm-none-eabi-objcopy");
            c.args(["-O", "binary"]).arg(&elf).arg(&bin);
            run_ok(c, "arm-none-eabi-objcopy (bash hil/install-tools.sh installs it)")?;
            let code = std::fs::read(&bin).map_err(|e| format!("{}: {e}", bin.display()))?;
            if code.len() + 128 > ACTIVE.1 as usize {
                return Err(format!(
                    "the firmware ({} bytes) outgrew the active slot ({})",
                    code.len(),
                    ACTIVE.1
                ));
            }
            firmware.push((version, code));
        }
        Ok(Self { bootloader, firmware })
    }

    /// The firmware built as `version`, signed with the development key; a version never built
    /// (an image that must be refused before it runs) has 0.2.0's code.
    fn image(&self, version: Version) -> Image {
        let code = self.firmware.iter().find(|(v, _)| *v == version).unwrap_or(&self.firmware[1]).1.clone();
        Image::sign(&code, BoardId::QemuMps2An386, version, SCHEMA_HASH, &lightrig_sim::flash::virtual_key())
    }

    /// A new flash file as the factory leaves it: `version` in the active partition, the rest
    /// erased.
    fn factory(&self, path: &Path, version: Version) -> Result<(), String> {
        let mut bytes = vec![0xFFu8; FILE_LEN as usize];
        let signed = self.image(version).signed;
        bytes[ACTIVE.0 as usize..ACTIVE.0 as usize + signed.len()].copy_from_slice(&signed);
        std::fs::write(path, bytes).map_err(|e| format!("{}: {e}", path.display()))
    }
}

struct Board {
    builds: Builds,
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
        Qemu::start(&Options {
            elf: self.builds.bootloader.clone(),
            shift: self.shift,
            args,
            log_dir: self.logs.clone(),
        })
    }

    /// Says Hello, again until the board answers: after a start its bootloader may still be
    /// swapping (seconds in QEMU on a loaded machine).
    fn connect(&mut self, q: &Qemu) -> Result<Client<Dyn>, String> {
        let deadline = std::time::Instant::now() + Duration::from_secs(120);
        loop {
            self.nonce = self.nonce.wrapping_add(0x10);
            let t: Dyn = Box::new(SerialTransport::open(&q.uart0, 115_200).map_err(|e| e.to_string())?);
            match Client::connect(t, self.nonce) {
                Ok(c) => return Ok(c),
                Err(e) if std::time::Instant::now() >= deadline => return Err(format!("Hello: {e}")),
                Err(_) => {}
            }
        }
    }

    /// Waits for the board to reset after marking an image and says Hello to the new start.
    fn after_reset(&mut self, c: Client<Dyn>, q: &Qemu) -> Result<Client<Dyn>, String> {
        drop(flash::await_reset(c, 30_000_000).map_err(|e| e.to_string())?);
        // The same pty: the emulated MCU reset, QEMU and its UART stayed.
        self.connect(q)
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
    b.builds.factory(&b.flash, v(1))?;
    let q = b.start(None)?;
    let mut c = b.connect(&q)?;
    expect("factory version", c.info().firmware == v(1), c.info().firmware)?;
    let st = flash::send(&mut c, &b.builds.image(v(2)), |_, _| {}).map_err(|e| e.to_string())?;
    expect("marked", matches!(st.phase, UpdatePhase::Ready { .. }), st.phase)?;
    let mut c = b.after_reset(c, &q)?;
    expect("new version after the swap", c.info().firmware == v(2), c.info().firmware)?;
    expect("software reset", c.info().reset_cause == ResetCause::Software, c.info().reset_cause)?;
    let st = status(&mut c)?;
    expect("unconfirmed until the host says so", st.phase == UpdatePhase::Unconfirmed, st.phase)?;
    expect("fallback", st.fallback.map(|i| i.version) == Some(v(1)), st.fallback)?;
    flash::confirm(&mut c).map_err(|e| e.to_string())?;

    // A byte changed after signing, a foreign key, another board: refused, nothing swapped.
    let mut corrupted = b.builds.image(v(3));
    corrupted.signed[100] ^= 0x01;
    let foreign = ed25519_dalek::SigningKey::from_bytes(&[7; 32]);
    let code = b.builds.firmware[1].1.clone();
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
    let img = b.builds.image(v(3));
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

/// The flash file with 0.2.0 sent, checked and marked, the power cut at the swap's first
/// operation: what the board's flash holds between the marking and the swap.
fn marked_update(b: &mut Board) -> Result<Vec<u8>, String> {
    b.builds.factory(&b.flash, v(1))?;
    let mut q = b.start(Some(1))?;
    let mut c = b.connect(&q)?;
    let st = flash::send(&mut c, &b.builds.image(v(2)), |_, _| {}).map_err(|e| e.to_string())?;
    expect("marked", matches!(st.phase, UpdatePhase::Ready { .. }), st.phase)?;
    let _ = flash::await_reset(c, 30_000_000);
    expect("QEMU ended at the swap's first operation", q.wait_exit(Duration::from_secs(20)).is_some(), 1)?;
    drop(q);
    std::fs::read(&b.flash).map_err(|e| format!("{}: {e}", b.flash.display()))
}

/// An image swapped in and never confirmed: the next start swaps the old one back.
fn unconfirmed_is_rolled_back(b: &mut Board, marked: &[u8]) -> Result<(), String> {
    std::fs::write(&b.flash, marked).map_err(|e| e.to_string())?;
    let q = b.start(None)?;
    let c = b.connect(&q)?;
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
/// stopped (embassy-boot's progress marks), and the board runs the new firmware.
fn power_cut_in_the_swap(b: &mut Board, marked: &[u8], cut: u32) -> Result<(), String> {
    std::fs::write(&b.flash, marked).map_err(|e| e.to_string())?;
    let mut q = b.start(Some(cut))?;
    let ended = q.wait_exit(Duration::from_secs(30));
    expect("QEMU ended at the cut", ended.is_some(), cut)?;
    drop(q);
    let q = b.start(None)?;
    let mut c = b.connect(&q)?;
    let running = c.info().firmware;
    expect("the new firmware runs after the cut", running == v(2), running)?;
    let st = status(&mut c)?;
    expect("the new firmware waits for its confirmation", st.phase == UpdatePhase::Unconfirmed, st.phase)?;
    flash::confirm(&mut c).map_err(|e| e.to_string())?;
    drop(c);
    drop(q);
    let q = b.start(None)?;
    let c = b.connect(&q)?;
    expect("kept once confirmed", c.info().firmware == v(2), c.info().firmware)
}

/// Builds the bootloader and the two firmware versions, then runs the update checks; the number
/// that failed.
pub fn run(shift: u8, logs: &Path) -> Result<usize, String> {
    std::fs::create_dir_all(logs).map_err(|e| format!("{}: {e}", logs.display()))?;
    let mut b = Board {
        builds: Builds::make(logs)?,
        shift,
        logs: logs.to_path_buf(),
        flash: logs.join("flash.img"),
        nonce: crate::boot_nonce(),
    };
    let mut failed = 0;
    // Each check's seconds, as the suite prints them: QEMU's share of the hil stage.
    let mut since = std::time::Instant::now();
    let mut check = |name: String, r: Result<(), String>| {
        let s = since.elapsed().as_secs_f64();
        since = std::time::Instant::now();
        match &r {
            Ok(()) => println!("  ok    {name} ({s:.1} s)"),
            Err(e) => {
                println!("  FAIL  {name} ({s:.1} s): {e}");
                failed += 1;
            }
        }
    };
    let t0 = std::time::Instant::now();
    check("update_swapped_in_confirmed_and_bad_images_refused".into(), good_and_bad_updates(&mut b));
    match marked_update(&mut b) {
        Ok(marked) => {
            check(
                "update_never_confirmed_is_rolled_back".into(),
                unconfirmed_is_rolled_back(&mut b, &marked),
            );
            // Cuts spread over the swap (80 pages, each erased in 256-byte and written in 64-byte
            // pieces: about 13 000 operations).
            for cut in [2, 70, 700, 5_000, 11_000] {
                check(
                    format!("update_power_cut_at_swap_operation_{cut}"),
                    power_cut_in_the_swap(&mut b, &marked, cut),
                );
            }
        }
        Err(e) => check("update_marked_for_the_swap".into(), Err(e)),
    }
    println!("lightrig-hil update: {failed} failed, {:.1} s", t0.elapsed().as_secs_f64());
    Ok(failed)
}
