//! Writes memory.x from the flash layout (layout.rs: the firmware lives in the active
//! partition, after the bootloader) and the update key from `LIGHTRIG_UPDATE_KEY`.
//!
//! `LIGHTRIG_UPDATE_KEY` is the ed25519 public key images must be signed with: the 64 hex
//! digits of `lightrig flash keygen`'s NAME.pub, or the path of that file. Without it the
//! firmware has no key and refuses updates over the link (it still runs, and the probe still
//! flashes it).

use std::fmt::Write as _;
use std::path::PathBuf;

include!("layout.rs");

fn parse_hex(s: &str) -> Option<[u8; 32]> {
    let s = s.trim();
    if s.len() != 64 {
        return None;
    }
    let mut key = [0u8; 32];
    for (i, k) in key.iter_mut().enumerate() {
        *k = u8::from_str_radix(s.get(2 * i..2 * i + 2)?, 16).ok()?;
    }
    Some(key)
}

fn update_key() -> Option<[u8; 32]> {
    let v = std::env::var("LIGHTRIG_UPDATE_KEY").ok().filter(|v| !v.trim().is_empty())?;
    if let Some(k) = parse_hex(&v) {
        return Some(k);
    }
    println!("cargo:rerun-if-changed={v}");
    let text = std::fs::read_to_string(&v).unwrap_or_else(|e| {
        panic!("LIGHTRIG_UPDATE_KEY: {v}: {e} (give NAME.pub from `lightrig flash keygen`, or its 64 hex digits)")
    });
    Some(
        parse_hex(&text)
            .unwrap_or_else(|| panic!("LIGHTRIG_UPDATE_KEY: {v}: not 64 hex digits (a NAME.pub file)")),
    )
}

fn main() {
    let out = PathBuf::from(std::env::var_os("OUT_DIR").unwrap());
    let mut x = String::new();
    writeln!(x, "MEMORY\n{{").unwrap();
    writeln!(x, "  FLASH : ORIGIN = {:#010x}, LENGTH = {}", FLASH_BASE + ACTIVE.0, ACTIVE.1).unwrap();
    writeln!(x, "  RAM   : ORIGIN = {:#010x}, LENGTH = {}", RAM.0, RAM.1).unwrap();
    writeln!(x, "}}").unwrap();
    std::fs::write(out.join("memory.x"), x).unwrap();
    let key = match update_key() {
        Some(k) => format!("Some({k:?})"),
        None => {
            println!(
                "cargo:warning=LIGHTRIG_UPDATE_KEY not set: this firmware refuses updates over the link"
            );
            "None".into()
        }
    };
    std::fs::write(
        out.join("update_key.rs"),
        format!("/// The public key update images must be signed with.\npub const UPDATE_KEY: Option<[u8; 32]> = {key};\n"),
    )
    .unwrap();
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed=layout.rs");
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-env-changed=LIGHTRIG_UPDATE_KEY");
}
