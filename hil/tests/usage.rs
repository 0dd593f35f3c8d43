//! The command line refuses what it cannot run before it builds or starts anything, with exit
//! status 2 and what to type instead. (This test also makes the workspace's test build link the
//! `lightrig-hil` binary itself, which CI's hil stage then runs without a build of its own.)

use std::process::{Command, Output};

fn hil(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_lightrig-hil")).args(args).output().expect("lightrig-hil runs")
}

fn refused(args: &[&str]) -> String {
    let out = hil(args);
    assert_eq!(out.status.code(), Some(2), "{args:?}: {out:?}");
    assert!(out.stdout.is_empty(), "{args:?}: nothing on stdout: {out:?}");
    String::from_utf8(out.stderr).unwrap()
}

#[test]
fn an_unknown_argument_is_named_with_the_usage() {
    let e = refused(&["suite", "--frobnicate"]);
    assert!(
        e.starts_with("lightrig-hil: unknown argument `--frobnicate`\nusage: lightrig-hil [suite|"),
        "{e}"
    );
}

#[test]
fn a_missing_value_is_named() {
    let e = refused(&["--only"]);
    assert!(e.starts_with("lightrig-hil: --only needs a value\nusage:"), "{e}");
}

#[test]
fn a_shift_beyond_ten_is_refused() {
    assert_eq!(refused(&["--shift", "11"]), "lightrig-hil: --shift: 0..=10 (2^N ns per instruction)\n");
    let e = refused(&["--shift", "x"]);
    assert!(e.starts_with("lightrig-hil: --shift: invalid digit"), "{e}");
}

#[test]
fn usb_ids_must_be_hex_and_pins_needs_its_port() {
    assert_eq!(refused(&["--usb", "zz:1"]), "lightrig-hil: --usb zz:1: expected VID:PID in hex\n");
    assert_eq!(refused(&["pins"]), "lightrig-hil: pins needs --port, the debug UART's pty\n");
}
