//! Writes `memory.x`: the bootloader at 0 (QEMU loads it and starts there), its RAM in the top
//! quarter of SSRAM2/3, clear of what the firmware keeps across a reset.
use std::{env, fs, path::PathBuf};

fn main() {
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    let memory = "MEMORY\n{\n  FLASH : ORIGIN = 0x00000000, LENGTH = 1M\n  RAM   : ORIGIN = 0x20300000, LENGTH = 1M\n}\n";
    fs::write(out.join("memory.x"), memory).expect("write memory.x");
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed=build.rs");
}
