//! lightrig firmware for the emulated board: QEMU `mps2-an386` (Cortex-M4F).
//!
//! The same controller as every board (`lightrig_firmware::Controller` over `Rig`), on
//! - embassy-executor (a thread-mode executor that sleeps with WFI: QEMU does not halt on
//!   WFE, so the stock one would spin) and embassy-time (`time.rs`: SysTick clock, 1 µs ticks);
//! - the protocol on UART0 and the recorder's debug port on UART1 (`uart.rs`, interrupt
//!   driven);
//! - simulated peripherals that record what the pins would do (`board.rs`);
//! - defmt over semihosting, the boot id from the semihosting command line (`semi.rs`).
//!
//! With `bench` on the command line it runs the benchmarks (`bench.rs`) and exits.
#![no_std]
#![no_main]

mod bench;
mod board;
mod flash;
mod irq;
mod semi;
mod time;
mod uart;

use core::future::poll_fn;
use core::mem::MaybeUninit;
use core::sync::atomic::{AtomicBool, Ordering};
use core::task::Poll;

use cortex_m_rt::{entry, exception};
use defmt_semihosting as _;
use embassy_executor::raw::Executor;
use embassy_futures::select::select;
use embassy_time::{Instant, Timer};
use lightrig_firmware::controller::EmbassyClock;
use lightrig_firmware::Controller;
use lightrig_protocol::frame::FrameDecoder;
use lightrig_protocol::session::{BoardId, Capabilities, DeviceInfo, ResetCause, Version};
use lightrig_protocol::MAX_FRAME;

use crate::board::{with_pins, QemuBoard};
use crate::uart::{UART0, UART1};

/// The controller's retransmission timeout: 50 ms in ticks.
const RTO_TICKS: u64 = 50_000;

fn device_info(boot_id: u32, firmware: Version, reset_cause: ResetCause) -> DeviceInfo {
    DeviceInfo {
        // The controller fills in the protocol version, schema hash and its own capacities.
        protocol_version: 0,
        schema_hash: 0,
        firmware,
        board: BoardId::QemuMps2An386,
        serial: 0x4C52_514D_5532_3836, // "LRQMU286": one emulated board
        tick_hz: embassy_time::TICK_HZ as u32,
        reset_cause,
        boot_id,
        capabilities: Capabilities {
            galvos: 2,
            lasers: 4,
            steppers: 2,
            filter_wheels: 1,
            voice_coils: 2,
            partials_per_coil: 8,
            cameras: 2,
            sequence_buffer: 0,
            event_queue: 0,
            link_window: 0,
            max_packet: lightrig_protocol::MAX_PACKET as u16,
        },
    }
}

/// Starts since QEMU powered the board on: RAM outside the ELF survives a reset.
fn starts_since_power_on() -> u32 {
    const MAGIC: u32 = 0x4C52_5354; // "LRST"
    #[link_section = ".uninit.lightrig_starts"]
    static mut STARTS: MaybeUninit<[u32; 2]> = MaybeUninit::uninit();
    // SAFETY: runs once, before anything else uses the memory; any bit pattern is a valid
    // [u32; 2] (QEMU powers RAM on as zeros).
    unsafe {
        let p = core::ptr::addr_of_mut!(STARTS).cast::<[u32; 2]>();
        let [magic, n] = p.read_volatile();
        let n = if magic == MAGIC { n.wrapping_add(1) } else { 0 };
        p.write_volatile([MAGIC, n]);
        n
    }
}

include!(concat!(env!("OUT_DIR"), "/version.rs"));

/// The update slots in the flash file the command line names (`flash.rs`), if any. The swap
/// itself is the bootloader's (boards/qemu-mps2-an386-bootloader), before this firmware starts.
fn open_slots(args: &semi::Args) -> Option<flash::Slots> {
    if args.flash.is_empty() {
        return None;
    }
    let Some(file) = flash::FileFlash::open(&args.flash) else {
        defmt::error!("flash file: cannot open it (or too short); no update slots");
        return None;
    };
    static FLASH: static_cell::StaticCell<
        embassy_sync::blocking_mutex::Mutex<
            embassy_sync::blocking_mutex::raw::NoopRawMutex,
            core::cell::RefCell<flash::FileFlash>,
        >,
    > = static_cell::StaticCell::new();
    let shared = FLASH.init(embassy_sync::blocking_mutex::Mutex::new(core::cell::RefCell::new(file)));
    Some(flash::slots(shared))
}

/// Set by the executor's pender (a task was woken); the idle loop sleeps only while it is clear.
static WOKEN: AtomicBool = AtomicBool::new(true);

#[unsafe(export_name = "__pender")]
fn pender(_context: *mut ()) {
    WOKEN.store(true, Ordering::SeqCst);
}

#[entry]
fn main() -> ! {
    let Some(mut core) = cortex_m::Peripherals::take() else { semi::exit(false) };
    time::init(&mut core.SYST);
    UART0.init();
    UART1.init();
    let args = semi::args();
    if args.bench {
        bench::run();
        // Let the last line leave the UART.
        while UART0.writable() < uart::RING {}
        semi::exit(true);
    }
    // A reset keeps RAM (the command line, and so its boot id, stays): count the starts so each
    // has its own boot id, and a software reset says so.
    let starts = starts_since_power_on();
    let boot_id = args.boot_id ^ starts.wrapping_mul(0x9E37_79B9);
    let reset_cause = if starts == 0 { ResetCause::PowerOn } else { ResetCause::Software };
    defmt::info!("lightrig-qemu: boot id {=u32:#010x}, start {=u32} since power-on", boot_id, starts);
    let board = QemuBoard { slots: open_slots(&args) };

    static mut EXECUTOR: MaybeUninit<Executor> = MaybeUninit::uninit();
    // SAFETY: `main` runs once and never returns, so this is the only reference ever made.
    let executor: &'static Executor =
        unsafe { (*core::ptr::addr_of_mut!(EXECUTOR)).write(Executor::new(core::ptr::null_mut())) };
    match run(device_info(boot_id, FIRMWARE, reset_cause), board) {
        Ok(task) => executor.spawner().spawn(task),
        Err(_) => semi::exit(false),
    }
    loop {
        // SAFETY: polled only from this thread-mode loop.
        unsafe { executor.poll() };
        if args.spin {
            // Idle by executing: under -icount, virtual time then only advances with
            // instructions, never by QEMU's real-time warp over a halted CPU (which overshoots
            // by however long the host was busy, and makes the rig late).
            while !WOKEN.swap(false, Ordering::SeqCst) {
                cortex_m::asm::nop();
            }
            continue;
        }
        // Sleep unless a wake-up came since the poll; WFI returns on a pending interrupt even
        // with interrupts masked, so none is missed between the check and the sleep.
        cortex_m::interrupt::free(|_| {
            if !WOKEN.swap(false, Ordering::SeqCst) {
                cortex_m::asm::wfi();
            }
        });
    }
}

/// One frame waiting for room in a UART's ring.
struct Pending {
    frame: [u8; MAX_FRAME],
    len: usize,
}

impl Pending {
    const fn new() -> Self {
        Self { frame: [0; MAX_FRAME], len: 0 }
    }

    /// Writes the held frame if the ring has room; `true` once nothing is held.
    fn flush(&mut self, uart: &uart::Uart) -> bool {
        if self.len > 0 && uart.write(&self.frame[..self.len]) {
            self.len = 0;
        }
        self.len == 0
    }
}

/// The run loop: one task owns the controller.
#[embassy_executor::task]
async fn run(info: DeviceInfo, board: QemuBoard) -> ! {
    let mut ctl = Controller::new(EmbassyClock, board, info, RTO_TICKS);
    let mut rx = [0u8; 256];
    let mut out0 = Pending::new();
    let mut out1 = Pending::new();
    let mut debug_rx = FrameDecoder::new();
    let mut packet = [0u8; lightrig_protocol::MAX_PACKET];
    let mut rejected = 0u32;
    let mut busy = 0u64;
    let mut wakeups = 0u64;
    let mut deadline: Option<u64> = None;
    loop {
        let t0 = time::cycles();
        wakeups += 1;
        let now = t0 / time::CYCLES_PER_TICK;
        if let Some(d) = deadline.filter(|&d| now > d + 200) {
            defmt::warn!("woke {=u64} ticks after the deadline {=u64}", now - d, d);
        }
        // Host bytes: each complete request is handled at once.
        let n = UART0.read(&mut rx);
        if n > 0 {
            ctl.receive(&rx[..n]);
            let now_rejected = ctl.link().stats().rejected();
            if now_rejected != rejected {
                let s = ctl.link().stats();
                defmt::warn!(
                    "rejected {=u32} frame(s): cobs {=u32} crc {=u32} long {=u32} short {=u32} type {=u32} payload {=u32}",
                    now_rejected.wrapping_sub(rejected),
                    s.bad_cobs,
                    s.bad_crc,
                    s.too_long,
                    s.too_short,
                    s.unknown_type,
                    s.bad_payload
                );
                rejected = now_rejected;
            }
        }
        ctl.poll();
        // Frames for the host, as long as the ring takes whole frames: a host that stops
        // reading must not stop the rig (its safety timers run in `poll`).
        while out0.flush(&UART0) {
            match ctl.poll_transmit(&mut out0.frame) {
                Some(len) => out0.len = len,
                None => break,
            }
        }
        // The debug port: requests to the recorder.
        if out1.flush(&UART1) {
            let n = UART1.read(&mut rx);
            for &byte in &rx[..n] {
                let Some(Ok(len)) = debug_rx.push(byte) else { continue };
                let len = len.min(packet.len());
                packet[..len].copy_from_slice(debug_rx.packet(len));
                let (rx0, tx0) = UART0.counters();
                let counters = [rx0, tx0, busy, wakeups];
                let now = Instant::now().as_ticks();
                if let Some(n) = with_pins(|p| p.answer(&packet[..len], now, counters, &mut out1.frame)) {
                    out1.len = n;
                }
                if !out1.flush(&UART1) {
                    // The rest waits in the decoder's input (the ring) until the answer is out.
                    break;
                }
            }
        }
        if ctl.wants_reset() && out0.len == 0 {
            // An update is marked (the host has the answer), or a swapped-in firmware was not
            // confirmed in time: reset into the bootloader's swap.
            defmt::info!("resetting for the bootloader");
            while UART0.writable() < uart::RING {}
            cortex_m::peripheral::SCB::sys_reset();
        }
        let spent = time::cycles() - t0;
        busy += spent;
        if spent > 200 * time::CYCLES_PER_TICK {
            defmt::warn!("one turn of the run loop took {=u64} ticks", spent / time::CYCLES_PER_TICK);
        }

        // Sleep until bytes arrive, a held frame fits, or the controller's next deadline.
        let ready = poll_fn(|cx| {
            uart::register(cx.waker());
            let ready = UART0.readable()
                || (out0.len > 0 && UART0.writable() >= out0.len)
                || (out0.len == 0 && UART1.readable())
                || (out1.len > 0 && UART1.writable() >= out1.len);
            if ready {
                Poll::Ready(())
            } else {
                Poll::Pending
            }
        });
        deadline = ctl.next_deadline();
        match deadline {
            Some(at) => {
                select(ready, Timer::at(Instant::from_ticks(at))).await;
            }
            None => ready.await,
        }
    }
}

#[exception]
fn SysTick() {
    time::on_systick();
}

// The board's interrupt lines, by number (no PAC: cortex-m-rt routes them all here).
#[exception]
unsafe fn DefaultHandler(irqn: i16) {
    let (u0rx, u0tx) = UART0.irqs();
    let (u1rx, u1tx) = UART1.irqs();
    match irqn as u16 {
        n if n == u0rx => UART0.on_rx(),
        n if n == u0tx => UART0.on_tx(),
        n if n == u1rx => UART1.on_rx(),
        n if n == u1tx => UART1.on_tx(),
        time::TIMER0_IRQ => time::on_timer0(),
        _ => {}
    }
}

#[exception]
unsafe fn HardFault(_frame: &cortex_m_rt::ExceptionFrame) -> ! {
    lasers_off_and_exit()
}

#[panic_handler]
fn panic(_info: &core::panic::PanicInfo) -> ! {
    defmt::error!("panic");
    lasers_off_and_exit()
}

/// The board's duty before a reset: every laser enable inactive (recorded, so the harness sees
/// it), then end the emulation with a failure so the harness sees the crash.
fn lasers_off_and_exit() -> ! {
    let now = time::cycles() / time::CYCLES_PER_TICK;
    with_pins(|p| p.lasers_off(now));
    semi::exit(false)
}
