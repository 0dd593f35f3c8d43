//! `lightrig-hil`: the conformance suite against the emulated board (QEMU) or a real board,
//! and the emulated board's figures. See `hil/README.md`.
//!
//! ```text
//! lightrig-hil [suite] [--elf ELF] [--shift N] [--only NAME]...   QEMU mps2-an386 (built unless --elf)
//! lightrig-hil suite --port /dev/ttyACM0 [--baud B]               a real board, serial
//! lightrig-hil suite --usb 1209:4c52[:SERIAL]                     a real board, USB
//! lightrig-hil figures [--elf ELF] [--shift N]                    instruction counts and UART throughput
//! lightrig-hil update [--shift N]                               firmware updates, resets and power cuts (QEMU)
//! lightrig-hil pins --port /dev/pts/N                             the emulated board's recorded outputs
//! ```

mod debug;
mod figures;
mod qemu;
mod suite;
mod update;

use std::path::PathBuf;
use std::process::ExitCode;

use lightrig_host::transport::{SerialTransport, Transport, UsbTransport};

struct Args {
    command: String,
    elf: Option<PathBuf>,
    shift: u8,
    port: Option<String>,
    baud: u32,
    usb: Option<String>,
    only: Vec<String>,
    logs: PathBuf,
}

const USAGE: &str =
    "usage: lightrig-hil [suite|figures|pins|update] [--elf ELF] [--shift N] [--port PATH [--baud B]] \
                     [--usb VID:PID[:SERIAL]] [--only NAME]... [--logs DIR]";

fn parse() -> Result<Args, String> {
    let mut a = Args {
        command: "suite".into(),
        elf: None,
        shift: 0,
        port: None,
        baud: 115_200,
        usb: None,
        only: Vec::new(),
        logs: qemu::repo_root().join("target/hil"),
    };
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        let mut value = |name: &str| it.next().ok_or(format!("{name} needs a value\n{USAGE}"));
        match arg.as_str() {
            "suite" | "figures" | "pins" | "update" => a.command = arg,
            "--elf" => a.elf = Some(value("--elf")?.into()),
            "--shift" => a.shift = value("--shift")?.parse().map_err(|e| format!("--shift: {e}"))?,
            "--port" => a.port = Some(value("--port")?),
            "--baud" => a.baud = value("--baud")?.parse().map_err(|e| format!("--baud: {e}"))?,
            "--usb" => a.usb = Some(value("--usb")?),
            "--only" => a.only.push(value("--only")?),
            "--logs" => a.logs = value("--logs")?.into(),
            "-h" | "--help" => return Err(USAGE.into()),
            other => return Err(format!("unknown argument `{other}`\n{USAGE}")),
        }
    }
    if a.shift > 10 {
        return Err("--shift: 0..=10 (2^N ns per instruction)".into());
    }
    // Refused here, not by each check when it opens the board.
    if let Some(spec) = &a.usb {
        usb_ids(spec)?;
    }
    Ok(a)
}

/// `VID:PID[:SERIAL]` → the ids and the serial, if given.
fn usb_ids(spec: &str) -> Result<(u16, u16, Option<&str>), String> {
    let mut parts = spec.split(':');
    let hex = |s: Option<&str>| -> Result<u16, String> {
        u16::from_str_radix(s.unwrap_or(""), 16).map_err(|_| format!("--usb {spec}: expected VID:PID in hex"))
    };
    let (vid, pid) = (hex(parts.next())?, hex(parts.next())?);
    Ok((vid, pid, parts.next()))
}

/// `VID:PID[:SERIAL]` → a transport: the lightrig vendor interface when the ids are
/// lightrig's, else the CDC-ACM serial port the system lists with those ids.
fn open_usb(spec: &str, baud: u32) -> Result<Box<dyn Transport>, String> {
    let (vid, pid, serial) = usb_ids(spec)?;
    use lightrig_host::transport::{USB_PID, USB_VID};
    if (vid, pid) == (USB_VID, USB_PID) {
        return Ok(Box::new(UsbTransport::open(serial).map_err(|e| e.to_string())?));
    }
    let ports = serialport::available_ports().map_err(|e| e.to_string())?;
    let port = ports
        .into_iter()
        .find(|p| match &p.port_type {
            serialport::SerialPortType::UsbPort(u) => {
                u.vid == vid && u.pid == pid && serial.is_none_or(|s| u.serial_number.as_deref() == Some(s))
            }
            _ => false,
        })
        .ok_or(format!("no USB device {vid:04x}:{pid:04x} with a serial interface"))?;
    Ok(Box::new(SerialTransport::open(&port.port_name, baud).map_err(|e| e.to_string())?))
}

fn boot_nonce() -> u32 {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u32(std::process::id());
    (h.finish() as u32) | 1
}

fn run(a: Args) -> Result<bool, String> {
    if a.command == "pins" {
        // The recorder of a running emulated board: every change it still holds.
        let path = a.port.ok_or("pins needs --port, the debug UART's pty")?;
        let mut d = debug::DebugPort::open(&path)?;
        d.rewind()?;
        let records = d.read_new()?;
        let info = d.info()?;
        for r in records {
            println!("{:>12} {:?}", r.tick, r.output);
        }
        println!("({} changes recorded since start; board tick {})", info.written, info.now);
        return Ok(true);
    }
    if a.command == "figures" {
        let elf = match a.elf {
            Some(e) => e,
            None => qemu::build_firmware()?,
        };
        figures::run(&elf, a.shift, &a.logs)?;
        return Ok(true);
    }
    if a.command == "update" {
        println!("lightrig-hil: firmware updates of the emulated board (QEMU mps2-an386)");
        return Ok(update::run(a.shift, &a.logs.join("update"))? == 0);
    }
    if let Some(path) = a.port.clone() {
        println!("lightrig-hil: suite against serial {path}");
        let baud = a.baud;
        let target = suite::Target {
            open: Box::new(move || {
                SerialTransport::open(&path, baud)
                    .map(|t| Box::new(t) as Box<dyn Transport>)
                    .map_err(|e| e.to_string())
            }),
            debug: None,
            boot_id: None,
            alive: Box::new(|| true),
        };
        return Ok(suite::Suite::new(target).run(&a.only) == 0);
    }
    if let Some(spec) = a.usb.clone() {
        println!("lightrig-hil: suite against USB {spec}");
        let baud = a.baud;
        let target = suite::Target {
            open: Box::new(move || open_usb(&spec, baud)),
            debug: None,
            boot_id: None,
            alive: Box::new(|| true),
        };
        return Ok(suite::Suite::new(target).run(&a.only) == 0);
    }
    let elf = match a.elf {
        Some(e) => e,
        None => qemu::build_firmware()?,
    };
    let boot = boot_nonce();
    let opts = qemu::Options {
        elf,
        shift: a.shift,
        args: vec![format!("boot={boot:#x}"), "idle=spin".into()],
        log_dir: a.logs.clone(),
    };
    let qemu = std::rc::Rc::new(std::cell::RefCell::new(qemu::Qemu::start(&opts)?));
    let (uart0, uart1) = (qemu.borrow().uart0.clone(), qemu.borrow().uart1.clone());
    println!("lightrig-hil: QEMU mps2-an386, -icount shift={}, protocol {uart0}, debug {uart1}", a.shift);
    let alive = qemu.clone();
    let target = suite::Target {
        open: Box::new(move || {
            SerialTransport::open(&uart0, 115_200)
                .map(|t| Box::new(t) as Box<dyn Transport>)
                .map_err(|e| e.to_string())
        }),
        debug: Some(debug::DebugPort::open(&uart1)?),
        boot_id: Some(boot),
        alive: Box::new(move || alive.borrow_mut().running()),
    };
    let failed = suite::Suite::new(target).run(&a.only);
    println!(
        "lightrig-hil: {} (defmt log: {}, decode with `defmt-print -e ELF`)",
        if failed == 0 { "all passed".to_string() } else { format!("{failed} failed") },
        a.logs.join("defmt.bin").display()
    );
    drop(qemu);
    Ok(failed == 0)
}

fn main() -> ExitCode {
    match parse().and_then(run) {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::FAILURE,
        Err(e) => {
            eprintln!("lightrig-hil: {e}");
            ExitCode::from(2)
        }
    }
}
