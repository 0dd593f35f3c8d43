//! `lightrig flash`: firmware updates over the rig's own link, and the keys and signed images
//! they need.
//!
//! - `lightrig flash keygen NAME`: a new signing key pair, `NAME.key` (secret) and `NAME.pub`.
//! - `lightrig flash sign CODE --key NAME.key --board B --version X.Y.Z -o IMAGE`: a signed
//!   image (`--virtual-key` signs with the virtual board's public development key).
//! - `lightrig flash IMAGE --connect SPEC`: sends it, waits for the device to reset into the
//!   bootloader's swap, checks the new firmware answers with the image's version, confirms it.
//! - `lightrig flash --probe FIRMWARE.elf [--bootloader BOOT.elf]`: the first flash of a blank
//!   board through its SWD probe (`flash_probe.rs`).

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use lightrig_host::client::{fresh_nonce, Client};
use lightrig_host::flash::{self, Image};
use lightrig_host::transport::{Connect, Transport};
use lightrig_protocol::session::{BoardId, Version};
use lightrig_protocol::update::{ImageInfo, UpdateError, UpdatePhase};
use lightrig_protocol::{Error, SCHEMA_HASH};

use crate::error::{err, CliError, DEVICE, FAILURE, INPUT, USAGE};

/// Arguments of `lightrig flash`.
#[derive(Debug, clap::Args)]
#[command(args_conflicts_with_subcommands = true)]
pub struct Args {
    #[command(subcommand)]
    pub cmd: Option<Cmd>,
    /// The signed image to send (`lightrig flash sign` makes one).
    pub image: Option<PathBuf>,
    /// The device: `virtual`, `serial:PATH[@BAUD]`, `usb` or `usb:SERIAL`.
    #[arg(long, default_value = "virtual")]
    pub connect: Connect,
    /// Leave the new firmware unconfirmed: the bootloader swaps the old one back at the next
    /// reset, or when the device is not confirmed within 60 s.
    #[arg(long)]
    pub no_confirm: bool,
    /// Write through the board's SWD probe instead (first flash of a blank board): IMAGE is
    /// then the firmware's ELF file. Needs probe-rs; exits 3 when no probe is found.
    #[arg(long, conflicts_with = "no_confirm")]
    pub probe: bool,
    /// With --probe: the bootloader's ELF file, written before the firmware.
    #[arg(long, requires = "probe")]
    pub bootloader: Option<PathBuf>,
    /// With --probe: the board, which names the chip (`nucleo-g474re`).
    #[arg(long, requires = "probe", default_value = "nucleo-g474re")]
    pub board: String,
    /// With --probe: which probe, as probe-rs names it (VID:PID[:SERIAL]), when several are
    /// plugged in.
    #[arg(long, requires = "probe")]
    pub probe_id: Option<String>,
}

/// `lightrig flash` subcommands.
#[derive(Debug, clap::Subcommand)]
pub enum Cmd {
    /// Make a signing key pair: NAME.key (secret: keep it off shared disks) and NAME.pub (built
    /// into the firmware).
    Keygen {
        /// Path prefix of the two files.
        name: PathBuf,
    },
    /// Sign a firmware binary into an image.
    Sign {
        /// The firmware's code (a raw binary, as `cargo objcopy -- -O binary` writes it).
        code: PathBuf,
        /// The secret key (`lightrig flash keygen`'s NAME.key).
        #[arg(long, required_unless_present = "virtual_key", conflicts_with = "virtual_key")]
        key: Option<PathBuf>,
        /// Sign with the virtual board's development key (public on purpose: for the virtual
        /// rig only).
        #[arg(long)]
        virtual_key: bool,
        /// The board it was built for: `nucleo-g474re`, `qemu-mps2-an386` or `virtual`.
        #[arg(long)]
        board: String,
        /// Its firmware version, `MAJOR.MINOR.PATCH`.
        #[arg(long)]
        version: String,
        /// Its protocol schema hash (default: this host's, for firmware built from the same
        /// tree).
        #[arg(long, value_parser = parse_hex)]
        schema_hash: Option<u64>,
        /// The image file to write.
        #[arg(short, long)]
        out: PathBuf,
    },
}

fn parse_hex(s: &str) -> Result<u64, String> {
    u64::from_str_radix(s.trim_start_matches("0x"), 16).map_err(|e| format!("{s}: {e}"))
}

/// `lightrig flash …`.
pub fn run(args: &Args) -> ExitCode {
    crate::cmd::exit(match (&args.cmd, &args.image) {
        (Some(Cmd::Keygen { name }), _) => keygen(name),
        (Some(Cmd::Sign { code, key, virtual_key, board, version, schema_hash, out }), _) => {
            sign(code, key.as_deref(), *virtual_key, board, version, schema_hash.unwrap_or(SCHEMA_HASH), out)
        }
        (None, Some(elf)) if args.probe => match board_named(&args.board) {
            Some(board) => crate::cmd::flash_probe::flash(
                board,
                elf,
                args.bootloader.as_deref(),
                args.probe_id.as_deref(),
            ),
            None => Err(err(
                USAGE,
                format!("--board {}: unknown; boards: nucleo-g474re, qemu-mps2-an386, virtual", args.board),
            )),
        },
        (None, Some(image)) => send(image, &args.connect, !args.no_confirm),
        (None, None) => Err(err(
            USAGE,
            "name an image to send (`lightrig flash IMAGE --connect SPEC`), or `keygen` / `sign`",
        )),
    })
}

fn write(path: &Path, bytes: &[u8]) -> Result<(), CliError> {
    std::fs::write(path, bytes).map_err(|e| err(FAILURE, format!("{}: {e}", path.display())))
}

fn keygen(name: &Path) -> Result<(), CliError> {
    let key = flash::keygen().map_err(|e| err(FAILURE, e))?;
    let secret = name.with_extension("key");
    let public = name.with_extension("pub");
    for p in [&secret, &public] {
        if p.exists() {
            return Err(err(
                USAGE,
                format!("{}: exists; a key is never overwritten (pick another name)", p.display()),
            ));
        }
    }
    write(&secret, format!("{}\n", flash::key_hex(&key.to_bytes())).as_bytes())?;
    write(&public, format!("{}\n", flash::key_hex(&key.verifying_key().to_bytes())).as_bytes())?;
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let _ = std::fs::set_permissions(&secret, std::fs::Permissions::from_mode(0o600));
    }
    eprintln!("wrote {} (secret) and {} (public)", secret.display(), public.display());
    Ok(())
}

/// A board by its name on the command line.
pub fn board_named(name: &str) -> Option<BoardId> {
    match name {
        "nucleo-g474re" => Some(BoardId::NucleoG474re),
        "qemu-mps2-an386" => Some(BoardId::QemuMps2An386),
        "virtual" => Some(BoardId::Virtual),
        _ => None,
    }
}

fn parse_version(s: &str) -> Option<Version> {
    let mut it = s.split('.').map(|p| p.parse::<u16>().ok());
    let v = Version { major: it.next()??, minor: it.next()??, patch: it.next()?? };
    it.next().is_none().then_some(v)
}

fn version_text(v: Version) -> String {
    format!("{}.{}.{}", v.major, v.minor, v.patch)
}

fn image_text(i: &ImageInfo) -> String {
    format!("{} for {:?}", version_text(i.version), i.board)
}

fn sign(
    code: &Path,
    key: Option<&Path>,
    virtual_key: bool,
    board: &str,
    version: &str,
    schema_hash: u64,
    out: &Path,
) -> Result<(), CliError> {
    let board = board_named(board).ok_or_else(|| {
        err(USAGE, format!("--board {board}: not a board (nucleo-g474re, qemu-mps2-an386 or virtual)"))
    })?;
    let version = parse_version(version)
        .ok_or_else(|| err(USAGE, format!("--version {version}: not MAJOR.MINOR.PATCH (e.g. 1.2.0)")))?;
    let key = match key {
        Some(p) => ed25519_dalek::SigningKey::from_bytes(&flash::read_key(p).map_err(|e| err(INPUT, e))?),
        None if virtual_key && board == BoardId::Virtual => lightrig_sim::flash::virtual_key(),
        None => {
            return Err(err(USAGE, "--virtual-key signs images for the virtual board only (--board virtual)"))
        }
    };
    let bytes = std::fs::read(code).map_err(|e| err(INPUT, format!("{}: {e}", code.display())))?;
    if bytes.is_empty() {
        return Err(err(INPUT, format!("{}: empty: nothing to sign", code.display())));
    }
    let image = Image::sign(&bytes, board, version, schema_hash, &key);
    write(out, &image.to_file())?;
    eprintln!(
        "wrote {}: {} ({} bytes of code, {} signed)",
        out.display(),
        image_text(&image.info),
        bytes.len(),
        image.signed.len()
    );
    Ok(())
}

fn device_err(e: impl std::fmt::Display) -> CliError {
    err(DEVICE, e.to_string())
}

/// What to do about a refused update, in words.
fn refusal(e: &flash::FlashError) -> String {
    let flash::FlashError::Client(lightrig_host::client::ClientError::Refused { error, .. }) = e else {
        return e.to_string();
    };
    match error {
        Error::Update(UpdateError::WrongBoard { image, device }) => {
            format!("the image is for {image:?}, the device is a {device:?}: sign the firmware built for this board")
        }
        Error::Update(UpdateError::TooLarge { image, slot }) => {
            format!("the image ({image} bytes) does not fit the device's update slot ({slot} bytes)")
        }
        Error::Update(UpdateError::BadSignature) => {
            "the device refused the signature: the image was signed with another key than the one built \
             into its firmware, or was altered (nothing was swapped; the device runs what it ran)"
                .into()
        }
        Error::Update(UpdateError::Unconfirmed) => {
            "the device runs a new firmware not yet confirmed: confirm it first (`lightrig flash IMAGE` \
             confirms by itself), or reset the device to go back to the old one"
                .into()
        }
        Error::InvalidState(s) => format!("the device is busy ({s:?}): stop the acquisition, then flash"),
        other => format!("the device refused the update: {other:?}"),
    }
}

/// The device after its reset: on the same port if it stayed (a UART, a USB-serial bridge),
/// else on the port opened again as it comes back (a USB device re-enumerates): up to 30 s.
fn reconnect(transport: Box<dyn Transport>, spec: &Connect) -> Result<Client<Box<dyn Transport>>, CliError> {
    let mut last = match Client::connect_for_update(transport, fresh_nonce()) {
        Ok((c, _)) => return Ok(c),
        Err(e) => e.to_string(),
    };
    for _ in 0..30 {
        std::thread::sleep(std::time::Duration::from_secs(1));
        match lightrig_sim::transport::open(spec) {
            Ok(t) => match Client::connect_for_update(t, fresh_nonce()) {
                Ok((c, _)) => return Ok(c),
                Err(e) => last = e.to_string(),
            },
            Err(e) => last = e.to_string(),
        }
    }
    Err(err(DEVICE, format!("the device did not come back within 30 s of its reset: {last}")))
}

fn send(path: &Path, spec: &Connect, confirm: bool) -> Result<(), CliError> {
    let file = std::fs::read(path).map_err(|e| err(INPUT, format!("{}: {e}", path.display())))?;
    let image = Image::from_file(&file).map_err(|e| err(INPUT, format!("{}: {e}", path.display())))?;
    let transport = lightrig_sim::transport::open(spec).map_err(device_err)?;
    let (mut client, compatible) =
        Client::connect_for_update(transport, fresh_nonce()).map_err(device_err)?;
    let info = *client.info();
    eprintln!(
        "{}: {:?}, firmware {}{}",
        client.transport().describe(),
        info.board,
        version_text(info.firmware),
        if compatible {
            String::new()
        } else {
            format!(
                " (protocol {}, schema 0x{:016x}: another build than this host's)",
                info.protocol_version, info.schema_hash
            )
        }
    );
    if image.info.board != info.board {
        return Err(err(
            USAGE,
            format!(
                "{}: the image is for {:?}, the device is a {:?}",
                path.display(),
                image.info.board,
                info.board
            ),
        ));
    }
    let st = flash::update(&mut client, lightrig_protocol::update::UpdateCommand::Status)
        .map_err(|e| err(DEVICE, refusal(&e)))?;
    if st.slot == 0 {
        return Err(err(
            DEVICE,
            format!(
                "{:?} has no bootloader to update it over the link: flash it through its debug probe",
                info.board
            ),
        ));
    }
    eprintln!("sending {} ({} bytes)", image_text(&image.info), image.signed.len());
    let bar = indicatif::ProgressBar::new(image.signed.len() as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{bar:40} {bytes}/{total_bytes} {bytes_per_sec} eta {eta}")
            .expect("a valid template"),
    );
    let start = Instant::now();
    let st = flash::send(&mut client, &image, |sent, _| bar.set_position(u64::from(sent)))
        .map_err(|e| err(DEVICE, refusal(&e)))?;
    bar.finish_and_clear();
    let secs = start.elapsed().as_secs_f64();
    if !matches!(st.phase, UpdatePhase::Ready { .. }) {
        return Err(err(
            FAILURE,
            format!("the device did not mark the image for its bootloader ({:?})", st.phase),
        ));
    }
    eprintln!(
        "sent in {secs:.1} s ({:.1} KiB/s); the device verified the signature and resets into it",
        image.signed.len() as f64 / 1024.0 / secs.max(1e-9),
    );
    let old_boot = info.boot_id;
    let transport = flash::await_reset(client, 10_000_000).map_err(device_err)?;
    let mut client = reconnect(transport, spec)?;
    let now = *client.info();
    if now.boot_id == old_boot || now.firmware != image.info.version {
        return Err(err(
            FAILURE,
            format!(
                "after the reset the device runs firmware {}, not the image's {}: the bootloader kept the old one",
                version_text(now.firmware),
                version_text(image.info.version)
            ),
        ));
    }
    let st = if confirm {
        flash::confirm(&mut client).map_err(|e| err(DEVICE, refusal(&e)))?
    } else {
        flash::update(&mut client, lightrig_protocol::update::UpdateCommand::Status).map_err(device_err)?
    };
    let fallback = st.fallback.map_or("none".to_string(), |i| image_text(&i));
    let state = match st.phase {
        UpdatePhase::Unconfirmed => "unconfirmed: swapped back at the next reset, or in 60 s",
        _ => "confirmed",
    };
    eprintln!("running {} ({state}); fallback {fallback}", version_text(now.firmware));
    Ok(())
}
