//! Semihosting (QEMU `-semihosting-config enable=on,target=native,arg=...`): the command line
//! (boot id, mode) and the exit code.

use cortex_m_semihosting::{debug, nr, syscall1};

/// What the command line asks for.
pub struct Args {
    /// `boot=N` (decimal or 0x hex): the boot id. Without it: the host's clock.
    pub boot_id: u32,
    /// `bench`: run the benchmarks instead of the controller.
    pub bench: bool,
    /// `idle=spin`: idle by spinning instead of WFI (see main.rs).
    pub spin: bool,
    /// `flash=PATH`: the flash file (`flash.rs`); none: no update slots.
    pub flash: heapless::Vec<u8, 127>,
    /// `cut=N`: cut the power at the Nth flash operation of the boot step.
    pub cut: Option<u32>,
}

/// Reads and parses the command line.
pub fn args() -> Args {
    let mut buf = [0u8; 256];
    let mut block = [buf.as_mut_ptr() as usize, buf.len() - 1];
    // SAFETY: SYS_GET_CMDLINE writes at most `block[1]` bytes into `buf` and the length back.
    let ok = unsafe { syscall1(nr::GET_CMDLINE, block.as_mut_ptr() as usize) } == 0;
    let line = if ok { buf.get(..block[1]).unwrap_or(&[]) } else { &[] };
    let mut args = Args { boot_id: 0, bench: false, spin: false, flash: heapless::Vec::new(), cut: None };
    let mut have_boot = false;
    for word in line.split(|&b| b == b' ') {
        if word == b"bench" {
            args.bench = true;
        } else if word == b"idle=spin" {
            args.spin = true;
        } else if let Some(path) = word.strip_prefix(b"flash=") {
            args.flash = heapless::Vec::from_slice(path).unwrap_or_default();
        } else if let Some(n) = word.strip_prefix(b"cut=").and_then(parse_u32) {
            args.cut = Some(n);
        } else if let Some(v) = word.strip_prefix(b"boot=").and_then(parse_u32) {
            args.boot_id = v;
            have_boot = true;
        }
    }
    if !have_boot {
        args.boot_id = fallback_boot_id();
    }
    args
}

fn parse_u32(s: &[u8]) -> Option<u32> {
    let (digits, radix) = match s.strip_prefix(b"0x") {
        Some(hex) => (hex, 16),
        None => (s, 10),
    };
    let text = core::str::from_utf8(digits).ok()?;
    u32::from_str_radix(text, radix).ok()
}

/// Without a nonce from the harness: the host's wall clock (seconds) mixed with the
/// centiseconds QEMU has run, so two starts in the same second still differ most of the time.
fn fallback_boot_id() -> u32 {
    // SAFETY: SYS_TIME and SYS_CLOCK take no argument block.
    let (secs, centis) = unsafe { (syscall1(nr::TIME, 0), syscall1(nr::CLOCK, 0)) };
    (secs as u32).wrapping_mul(0x9E37_79B9) ^ (centis as u32).rotate_left(16)
}

/// Ends the emulation with `ok` or failure.
pub fn exit(ok: bool) -> ! {
    debug::exit(if ok { debug::EXIT_SUCCESS } else { debug::EXIT_FAILURE });
    loop {
        cortex_m::asm::wfi();
    }
}
