//! Writes memory.x from the shared flash layout (../nucleo-g474re/layout.rs): the bootloader's own region.

use std::fmt::Write as _;

include!("../nucleo-g474re/layout.rs");

fn main() {
    let out = std::path::PathBuf::from(std::env::var_os("OUT_DIR").unwrap());
    let mut x = String::new();
    writeln!(x, "MEMORY\n{{").unwrap();
    writeln!(x, "  FLASH : ORIGIN = {:#010x}, LENGTH = {}", FLASH_BASE + BOOTLOADER.0, BOOTLOADER.1).unwrap();
    writeln!(x, "  RAM   : ORIGIN = {:#010x}, LENGTH = {}", RAM.0, RAM.1).unwrap();
    writeln!(x, "}}").unwrap();
    std::fs::write(out.join("memory.x"), x).unwrap();
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed=../nucleo-g474re/layout.rs");
    println!("cargo:rerun-if-changed=build.rs");
}
