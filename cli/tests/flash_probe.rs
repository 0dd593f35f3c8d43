//! `lightrig flash --probe`: the first flash through an SWD probe, driving probe-rs. No probe
//! is plugged in here, so a stand-in `probe-rs` (a script that logs its arguments and answers
//! `list` as told) takes its place; without any probe-rs, or with no probe listed, the
//! command says so and exits 3.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

mod common;
use common::Scratch;

fn scratch(name: &str) -> Scratch {
    Scratch::new("flash-probe", name)
}

/// A stand-in probe-rs: `list` prints `listing`; every call appends its arguments to
/// `calls.log`; `download` of a file named `bad.elf` fails as a lost probe would.
fn fake_probe_rs(dir: &Path, listing: &str) -> PathBuf {
    let path = dir.join("probe-rs");
    let script = format!(
        "#!/bin/sh\necho \"$*\" >> '{log}'\nif [ \"$1\" = list ]; then printf '%s' '{listing}'; fi\n\
         case \"$*\" in *bad.elf*) echo 'Error: probe was disconnected' >&2; exit 1;; esac\nexit 0\n",
        log = dir.join("calls.log").display()
    );
    std::fs::write(&path, script).unwrap();
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755)).unwrap();
    }
    path
}

fn elf(dir: &Path, name: &str) {
    let mut bytes = b"\x7fELF\x01\x01\x01".to_vec();
    bytes.resize(64, 0);
    std::fs::write(dir.join(name), bytes).unwrap();
}

fn lightrig(dir: &Path, probe_rs: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_lightrig"))
        .current_dir(dir)
        .env("LIGHTRIG_PROBE_RS", probe_rs)
        .args(args)
        .output()
        .unwrap()
}

fn said(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn calls(dir: &Path) -> Vec<String> {
    std::fs::read_to_string(dir.join("calls.log")).unwrap_or_default().lines().map(String::from).collect()
}

const ONE_PROBE: &str =
    "The following debug probes were found:\n[0]: STLink V3 -- 0483:374e:0025003C3532510A (ST-LINK)\n";

#[test]
fn bootloader_then_firmware_are_written_verified_and_the_board_reset() {
    let dir = scratch("ok");
    let tool = fake_probe_rs(&dir, ONE_PROBE);
    elf(&dir, "boot.elf");
    elf(&dir, "fw.elf");
    let o = lightrig(&dir, &tool, &["flash", "--probe", "fw.elf", "--bootloader", "boot.elf"]);
    assert!(o.status.success(), "{}", said(&o));
    assert_eq!(
        calls(&dir),
        [
            "list",
            "download --chip STM32G474RETx --verify boot.elf",
            "download --chip STM32G474RETx --verify fw.elf",
            "reset --chip STM32G474RETx",
        ]
    );
    let s = said(&o);
    assert!(
        s.contains("[1/2] writing the bootloader (boot.elf)") && s.contains("[2/2] writing the firmware"),
        "{s}"
    );
}

#[test]
fn without_a_probe_or_without_probe_rs_it_says_so_and_exits_3() {
    let dir = scratch("none");
    let tool = fake_probe_rs(&dir, "No debug probes were found.\n");
    elf(&dir, "fw.elf");
    let o = lightrig(&dir, &tool, &["flash", "--probe", "fw.elf"]);
    assert_eq!(o.status.code(), Some(3), "{}", said(&o));
    assert!(said(&o).contains("no SWD probe found: plug the board's ST-LINK USB in"), "{}", said(&o));
    assert_eq!(calls(&dir), ["list"], "nothing written");

    let o = lightrig(&dir, &dir.join("not-installed/probe-rs"), &["flash", "--probe", "fw.elf"]);
    assert_eq!(o.status.code(), Some(3), "{}", said(&o));
    assert!(
        said(&o).contains("is not installed (install it with `cargo install probe-rs-tools --locked`"),
        "{}",
        said(&o)
    );
}

#[test]
fn wrong_files_several_probes_and_a_failed_write_are_each_reported() {
    let dir = scratch("bad");
    let two = format!("{ONE_PROBE}[1]: J-Link -- 1366:0101:000123 (J-Link)\n");
    let tool = fake_probe_rs(&dir, &two);
    elf(&dir, "fw.elf");
    elf(&dir, "bad.elf");
    std::fs::write(dir.join("fw.lrfw"), b"LRIG....").unwrap();
    // A signed image is not an ELF file: refused before the probe is asked.
    let o = lightrig(&dir, &tool, &["flash", "--probe", "fw.lrfw"]);
    assert_eq!(o.status.code(), Some(4), "{}", said(&o));
    assert!(said(&o).contains("fw.lrfw: not an ELF file"), "{}", said(&o));
    let o = lightrig(&dir, &tool, &["flash", "--probe", "missing.elf"]);
    assert_eq!(o.status.code(), Some(4), "{}", said(&o));
    assert!(said(&o).contains("firmware missing.elf: No such file"), "{}", said(&o));
    assert!(calls(&dir).is_empty());
    // Two probes: which one must be said.
    let o = lightrig(&dir, &tool, &["flash", "--probe", "fw.elf"]);
    assert_eq!(o.status.code(), Some(2), "{}", said(&o));
    assert!(
        said(&o).contains("2 probes found; name one with --probe-id") && said(&o).contains("J-Link"),
        "{}",
        said(&o)
    );
    let o = lightrig(&dir, &tool, &["flash", "--probe", "fw.elf", "--probe-id", "0483:374e"]);
    assert!(o.status.success(), "{}", said(&o));
    assert!(
        calls(&dir).contains(&"download --chip STM32G474RETx --probe 0483:374e --verify fw.elf".to_string())
    );
    // A write that fails: exit 3 with probe-rs's own words, and no reset.
    let before = calls(&dir).len();
    let o = lightrig(&dir, &tool, &["flash", "--probe", "bad.elf", "--probe-id", "0483:374e"]);
    assert_eq!(o.status.code(), Some(3), "{}", said(&o));
    assert!(
        said(&o).contains("probe-rs download failed") && said(&o).contains("probe was disconnected"),
        "{}",
        said(&o)
    );
    assert!(!calls(&dir)[before..].iter().any(|c| c.starts_with("reset")));
    // A board without a probe.
    let o = lightrig(&dir, &tool, &["flash", "--probe", "fw.elf", "--board", "virtual"]);
    assert_eq!(o.status.code(), Some(2), "{}", said(&o));
    assert!(said(&o).contains("update it over its link"), "{}", said(&o));
}
