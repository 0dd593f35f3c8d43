//! A signal (Ctrl-C's SIGINT) that cuts short the wait on a serial port is not a lost device:
//! `SerialTransport::recv` returns "nothing arrived" and the port still works.
#![cfg(target_os = "linux")]

use std::io::Write;
use std::os::unix::thread::JoinHandleExt;
use std::time::{Duration, Instant};

use lightrig_host::transport::{SerialTransport, Transport};

extern "C" fn ignore(_: libc::c_int) {}

#[test]
fn a_signal_during_a_wait_on_the_port_is_nothing_arrived_not_an_error() {
    // A handler without SA_RESTART, as a Ctrl-C handler may be: poll(2) fails with EINTR.
    unsafe {
        let mut action: libc::sigaction = std::mem::zeroed();
        action.sa_sigaction = ignore as extern "C" fn(libc::c_int) as usize;
        libc::sigemptyset(&mut action.sa_mask);
        assert_eq!(libc::sigaction(libc::SIGUSR1, &action, std::ptr::null_mut()), 0);
    }
    let (mut master, slave) = serialport::TTYPort::pair().unwrap();
    let path = serialport::SerialPort::name(&slave).unwrap();
    drop(slave);
    let mut port = SerialTransport::open(&path, 115_200).unwrap();
    let returned = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let done = returned.clone();
    let waiting = std::thread::spawn(move || {
        let mut buf = [0u8; 16];
        let deadline = port.now_us() + 20_000_000;
        let first = port.recv(&mut buf, deadline).map_err(|e| e.kind());
        let cut_short = port.now_us() < deadline;
        done.store(true, std::sync::atomic::Ordering::SeqCst);
        // The port still reads what comes after (a last signal in flight may cut one more
        // wait short).
        let mut later = None;
        for _ in 0..3 {
            match port.recv(&mut buf, port.now_us() + 20_000_000) {
                Ok(0) => continue,
                Ok(n) => later = Some(buf[..n].to_vec()),
                Err(_) => {}
            }
            break;
        }
        (first, cut_short, later)
    });
    let thread = waiting.as_pthread_t();
    // Signals until the first wait ends (cut short by one: it waits 20 s otherwise).
    let start = Instant::now();
    while !returned.load(std::sync::atomic::Ordering::SeqCst) && start.elapsed() < Duration::from_secs(5) {
        unsafe { libc::pthread_kill(thread, libc::SIGUSR1) };
        std::thread::sleep(Duration::from_millis(10));
    }
    master.write_all(b"ok").unwrap();
    let (first, cut_short, later) = waiting.join().unwrap();
    assert_eq!(first, Ok(0), "a signal is nothing arrived, not an error");
    assert!(cut_short, "the wait was cut short by a signal");
    assert_eq!(later.as_deref(), Some(&b"ok"[..]));
}
