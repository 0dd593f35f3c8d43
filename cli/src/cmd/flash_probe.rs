//! `lightrig flash --probe FIRMWARE.elf [--bootloader BOOT.elf]`: the first flash of a blank
//! board through its SWD probe (the NUCLEO's on-board ST-LINK), by driving the `probe-rs`
//! tool: it knows every probe and chip, and a lab that debugs its firmware has it already.
//! The chip comes from the board's name. Without a probe (or without probe-rs, which reaches
//! it) the command says so and exits 3.

use std::path::{Path, PathBuf};
use std::process::Command;

use lightrig_protocol::session::BoardId;

use crate::error::{err, CliError, DEVICE, FAILURE, INPUT, USAGE};

/// The probe-rs binary: `LIGHTRIG_PROBE_RS` if set, else `probe-rs` on the PATH.
fn tool() -> PathBuf {
    std::env::var_os("LIGHTRIG_PROBE_RS").map_or_else(|| PathBuf::from("probe-rs"), PathBuf::from)
}

/// The probe-rs chip name of a board that is flashed through SWD.
pub fn chip_of(board: BoardId) -> Result<&'static str, CliError> {
    match board {
        BoardId::NucleoG474re => Ok("STM32G474RETx"),
        BoardId::QemuMps2An386 => Err(err(
            USAGE,
            "the QEMU board has no probe: it loads its firmware from the ELF at start \
             (boards/qemu-mps2-an386/run.sh)",
        )),
        BoardId::Virtual => Err(err(
            USAGE,
            "the virtual board has nothing to flash through a probe: update it over its link \
             (`lightrig flash IMAGE --connect virtual`)",
        )),
        BoardId::Other(n) => Err(err(USAGE, format!("board {n}: this host does not know its chip"))),
    }
}

/// The probes in `probe-rs list`'s output: its lines `[N]: DESCRIPTION`.
pub fn probes_listed(out: &str) -> Vec<String> {
    out.lines()
        .map(str::trim)
        .filter(|l| l.starts_with('[') && l.contains("]:"))
        .filter_map(|l| l.split_once("]:").map(|(_, d)| d.trim().to_string()))
        .collect()
}

/// Checks that `path` is an ELF file (probe-rs places its sections at their load addresses;
/// a raw binary would need an address the command cannot know).
fn check_elf(what: &str, path: &Path) -> Result<(), CliError> {
    let bytes = std::fs::read(path).map_err(|e| {
        err(
            INPUT,
            format!("{what} {}: {e} (build it first: see docs/flashing.md, \"First flash\")", path.display()),
        )
    })?;
    if !bytes.starts_with(b"\x7fELF") {
        return Err(err(
            INPUT,
            format!(
                "{what} {}: not an ELF file; give the linker's output \
                 (target/thumbv7em-none-eabihf/release/…), not a raw or signed image",
                path.display()
            ),
        ));
    }
    Ok(())
}

fn run_tool(args: &[&str]) -> Result<std::process::Output, CliError> {
    Command::new(tool()).args(args).output().map_err(|e| {
        if e.kind() == std::io::ErrorKind::NotFound {
            err(
                DEVICE,
                format!(
                    "no SWD probe can be reached: `{}` is not installed (install it with \
                     `cargo install probe-rs-tools --locked`, or set LIGHTRIG_PROBE_RS to its path)",
                    tool().display()
                ),
            )
        } else {
            err(FAILURE, format!("running {}: {e}", tool().display()))
        }
    })
}

/// Flashes `bootloader` (if given) and then `firmware` into `board` through its probe, each
/// verified after writing, then resets the board.
pub fn flash(
    board: BoardId,
    firmware: &Path,
    bootloader: Option<&Path>,
    probe: Option<&str>,
) -> Result<(), CliError> {
    let chip = chip_of(board)?;
    if let Some(b) = bootloader {
        check_elf("bootloader", b)?;
    }
    check_elf("firmware", firmware)?;
    let list = run_tool(&["list"])?;
    let probes = probes_listed(&String::from_utf8_lossy(&list.stdout));
    if probes.is_empty() {
        return Err(err(
            DEVICE,
            "no SWD probe found: plug the board's ST-LINK USB in (the NUCLEO's CN1, beside the \
             reset button), and on Linux install probe-rs's udev rules (https://probe.rs/docs/getting-started/probe-setup/); \
             `probe-rs list` shows what it sees",
        ));
    }
    if probes.len() > 1 && probe.is_none() {
        return Err(err(
            USAGE,
            format!(
                "{} probes found; name one with --probe-id VID:PID[:SERIAL]:\n  {}",
                probes.len(),
                probes.join("\n  ")
            ),
        ));
    }
    let mut base = vec!["--chip", chip];
    if let Some(p) = probe {
        base.extend(["--probe", p]);
    }
    let parts: Vec<(&str, &Path)> =
        bootloader.map(|b| ("bootloader", b)).into_iter().chain([("firmware", firmware)]).collect();
    for (k, (what, path)) in parts.iter().enumerate() {
        eprintln!(
            "[{}/{}] writing the {what} ({}) to the {chip} and verifying it",
            k + 1,
            parts.len(),
            path.display()
        );
        let path = path.to_string_lossy();
        let mut args = vec!["download"];
        args.extend(&base);
        args.extend(["--verify", &path]);
        step(&args, what)?;
    }
    let mut args = vec!["reset"];
    args.extend(&base);
    step(&args, "reset")?;
    eprintln!(
        "flashed through {}; the board has restarted (`lightrig info --connect usb` greets it)",
        probes[0]
    );
    Ok(())
}

fn step(args: &[&str], what: &str) -> Result<(), CliError> {
    let out = run_tool(args)?;
    if out.status.success() {
        return Ok(());
    }
    let said = String::from_utf8_lossy(&out.stderr);
    Err(err(
        DEVICE,
        format!(
            "probe-rs {} failed ({}) for the {what}: {}\na write cut half-way leaves no valid firmware; \
             the probe needs none: run the command again once the probe is reachable",
            args[0],
            out.status,
            said.trim()
        ),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn probes_are_read_from_probe_rs_list() {
        let out = "The following debug probes were found:\n[0]: STLink V3 -- 0483:374e:0025003C3532510A (ST-LINK)\n[1]: J-Link -- 1366:0101:000123 (J-Link)\n";
        assert_eq!(
            probes_listed(out),
            ["STLink V3 -- 0483:374e:0025003C3532510A (ST-LINK)", "J-Link -- 1366:0101:000123 (J-Link)"]
        );
        assert!(probes_listed("No debug probes were found.\n").is_empty());
    }

    #[test]
    fn the_chip_comes_from_the_board() {
        assert_eq!(chip_of(BoardId::NucleoG474re).unwrap(), "STM32G474RETx");
        assert_eq!(chip_of(BoardId::Virtual).unwrap_err().code, USAGE);
    }
}
