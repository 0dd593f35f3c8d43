//! Writes `memory.x` (from `memory.in.x`) where cortex-m-rt's `link.x` finds it, and the firmware's version.
//!
//! Feature `slot`: the firmware is linked at `APP_BASE` (the code the bootloader copies out of
//! the active slot of the flash file) instead of at 0, where QEMU loads an ELF by itself.
//! `LIGHTRIG_FIRMWARE_VERSION` (`MAJOR.MINOR.PATCH`, default the crate's) is the version the
//! firmware reports: the update tests build two that differ only in it.
use std::{env, fs, path::PathBuf};

/// Keep in step with `lightrig_firmware::boards::qemu_flash::{APP_BASE, ACTIVE}`.
const APP_BASE: u32 = 0x0010_0000;
const ACTIVE_LEN: u32 = 80 * 4096;

fn main() {
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    let memory = fs::read_to_string("memory.in.x").expect("read memory.in.x");
    let memory = if env::var_os("CARGO_FEATURE_SLOT").is_some() {
        memory.replace(
            "FLASH : ORIGIN = 0x00000000, LENGTH = 4M",
            &format!("FLASH : ORIGIN = {APP_BASE:#010x}, LENGTH = {ACTIVE_LEN}"),
        )
    } else {
        memory
    };
    assert!(memory.contains("FLASH"), "memory.x has a FLASH region");
    fs::write(out.join("memory.x"), memory).expect("write memory.x");
    let version =
        env::var("LIGHTRIG_FIRMWARE_VERSION").unwrap_or_else(|_| env::var("CARGO_PKG_VERSION").unwrap());
    let parts: Vec<u16> = version
        .split('.')
        .map(|p| p.parse().expect("LIGHTRIG_FIRMWARE_VERSION: MAJOR.MINOR.PATCH"))
        .collect();
    assert_eq!(parts.len(), 3, "LIGHTRIG_FIRMWARE_VERSION: MAJOR.MINOR.PATCH");
    fs::write(
        out.join("version.rs"),
        format!(
            "/// The version this build reports.\npub const FIRMWARE: lightrig_protocol::session::Version = \
             lightrig_protocol::session::Version {{ major: {}, minor: {}, patch: {} }};\n",
            parts[0], parts[1], parts[2]
        ),
    )
    .expect("write version.rs");
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed=memory.in.x");
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-env-changed=LIGHTRIG_FIRMWARE_VERSION");
}
