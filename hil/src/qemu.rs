//! The emulated board: builds its firmware, starts QEMU headless with both UARTs on ptys, and
//! kills QEMU on every way out (drop, panic, and — through `PR_SET_PDEATHSIG` — the harness
//! itself being killed).

use std::io::{BufRead, BufReader, Read};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

/// The board workspace, relative to the repository root.
pub const BOARD_DIR: &str = "boards/qemu-mps2-an386";
/// The firmware ELF inside it, once built.
pub const ELF: &str = "target/thumbv7em-none-eabihf/release/lightrig-qemu";

/// The repository root (this crate lives in `hil/`).
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().map(Path::to_path_buf).unwrap_or_default()
}

/// Builds the emulated board's firmware (its own workspace and target directory) and returns
/// the ELF's path.
pub fn build_firmware() -> Result<PathBuf, String> {
    let dir = repo_root().join(BOARD_DIR);
    let status = Command::new(std::env::var("CARGO").unwrap_or_else(|_| "cargo".into()))
        .args(["build", "--release", "--locked"])
        .current_dir(&dir)
        // The board workspace has its own target directory and flags.
        .env_remove("CARGO_TARGET_DIR")
        .env_remove("RUSTFLAGS")
        .env_remove("CARGO_BUILD_TARGET")
        .status()
        .map_err(|e| format!("cargo build in {}: {e}", dir.display()))?;
    if !status.success() {
        return Err(format!("building the firmware in {} failed ({status})", dir.display()));
    }
    Ok(dir.join(ELF))
}

/// How to start QEMU.
#[derive(Debug, Clone)]
pub struct Options {
    /// Firmware ELF.
    pub elf: PathBuf,
    /// `-icount shift=N`: each instruction advances virtual time 2^N ns.
    pub shift: u8,
    /// Words for the firmware's semihosting command line (`boot=N`, `bench`).
    pub args: Vec<String>,
    /// Where QEMU's defmt stream (semihosting) and stderr go.
    pub log_dir: PathBuf,
}

/// A running QEMU; killed when dropped.
pub struct Qemu {
    child: Child,
    /// The protocol UART (UART0).
    pub uart0: String,
    /// The debug UART (UART1, the recorder).
    pub uart1: String,
    stdout: Option<std::thread::JoinHandle<()>>,
}

/// The pty path in a line QEMU prints for `-serial pty`.
pub fn pty_of(line: &str) -> Option<&str> {
    let rest = line.strip_prefix("char device redirected to ")?;
    let path = rest.split_whitespace().next()?;
    path.starts_with("/dev/").then_some(path)
}

impl Qemu {
    /// Starts QEMU and waits (bounded) until it says where both UARTs are.
    pub fn start(opts: &Options) -> Result<Self, String> {
        std::fs::create_dir_all(&opts.log_dir).map_err(|e| format!("{}: {e}", opts.log_dir.display()))?;
        let stderr =
            std::fs::File::create(opts.log_dir.join("qemu-stderr.txt")).map_err(|e| e.to_string())?;
        let mut semi = String::from("enable=on,target=native,arg=lightrig");
        for a in &opts.args {
            semi.push_str(",arg=");
            semi.push_str(a);
        }
        let mut cmd = Command::new("qemu-system-arm");
        cmd.args(["-M", "mps2-an386", "-display", "none", "-monitor", "none", "-nodefaults"])
            .args(["-icount", &format!("shift={},sleep=on", opts.shift)])
            .args(["-serial", "pty", "-serial", "pty"])
            .args(["-semihosting-config", &semi])
            .arg("-kernel")
            .arg(&opts.elf)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(stderr);
        // SAFETY: prctl is async-signal-safe; it asks the kernel to kill QEMU when we die.
        unsafe {
            cmd.pre_exec(|| {
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let mut child = cmd.spawn().map_err(|e| {
            format!("qemu-system-arm: {e}; install it with `bash hil/install-tools.sh` (Debian bookworm-backports)")
        })?;
        let Some(out) = child.stdout.take() else {
            let _ = child.kill();
            return Err("no stdout from QEMU".into());
        };
        // QEMU prints the ptys on stdout, then the firmware's defmt stream (semihosting) follows.
        let (tx, rx) = mpsc::channel();
        let defmt_path = opts.log_dir.join("defmt.bin");
        let reader = std::thread::spawn(move || {
            let mut out = BufReader::new(out);
            let mut ptys = Vec::new();
            let mut line = Vec::new();
            while ptys.len() < 2 {
                line.clear();
                match out.read_until(b'\n', &mut line) {
                    Ok(0) | Err(_) => break,
                    Ok(_) => {
                        if let Some(p) = pty_of(String::from_utf8_lossy(&line).trim_end()) {
                            ptys.push(p.to_string());
                        }
                    }
                }
            }
            let _ = tx.send(ptys);
            let mut rest = Vec::new();
            let _ = out.read_to_end(&mut rest);
            let _ = std::fs::write(defmt_path, rest);
        });
        let mut qemu = Qemu { child, uart0: String::new(), uart1: String::new(), stdout: Some(reader) };
        // The only wait on the external process: QEMU opens its ptys within seconds.
        match rx.recv_timeout(Duration::from_secs(20)) {
            Ok(p) if p.len() == 2 => {
                qemu.uart0 = p[0].clone();
                qemu.uart1 = p[1].clone();
                Ok(qemu)
            }
            _ => Err(format!(
                "QEMU did not report its serial ptys (see {})",
                opts.log_dir.join("qemu-stderr.txt").display()
            )),
        }
    }

    /// Whether QEMU is still running (it exits if the firmware panics or faults).
    pub fn running(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    /// Waits (bounded) for QEMU to end by itself, e.g. after the firmware's semihosting exit;
    /// its exit status, or `None` if it is still running at the deadline.
    pub fn wait_exit(&mut self, within: Duration) -> Option<std::process::ExitStatus> {
        let deadline = std::time::Instant::now() + within;
        loop {
            if let Ok(Some(s)) = self.child.try_wait() {
                return Some(s);
            }
            if std::time::Instant::now() >= deadline {
                return None;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Qemu {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        if let Some(t) = self.stdout.take() {
            let _ = t.join();
        }
    }
}

/// Reads a line-oriented text stream from a pty (the benchmark output), up to `deadline`.
pub fn read_lines(
    port: &mut dyn serialport::SerialPort,
    until: &str,
    within: Duration,
) -> Result<Vec<String>, String> {
    let deadline = std::time::Instant::now() + within;
    let mut text = Vec::new();
    let mut buf = [0u8; 512];
    loop {
        let lines: Vec<String> = String::from_utf8_lossy(&text).lines().map(str::to_string).collect();
        if lines.iter().any(|l| l.trim() == until) {
            return Ok(lines);
        }
        if std::time::Instant::now() >= deadline {
            return Err(format!("no `{until}` within {} s; got {lines:?}", within.as_secs()));
        }
        match port.read(&mut buf) {
            Ok(n) => text.extend_from_slice(&buf[..n]),
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
            Err(e) => return Err(e.to_string()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::pty_of;

    #[test]
    fn finds_the_pty_in_qemus_line() {
        assert_eq!(pty_of("char device redirected to /dev/pts/7 (label serial0)"), Some("/dev/pts/7"));
        assert_eq!(pty_of("char device redirected to /dev/pts/12"), Some("/dev/pts/12"));
        assert_eq!(pty_of("qemu-system-arm: warning: something"), None);
        assert_eq!(pty_of("char device redirected to nowhere"), None);
    }
}
