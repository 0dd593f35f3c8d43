//! Interrupt-driven CMSDK APB UART (mps2-an386: UART0 at 0x4000_4000, RX/TX interrupts 0/1;
//! UART1 at 0x4000_5000, 2/3), with software rings both ways.
//!
//! The hardware holds one byte each way. The RX interrupt moves bytes into the ring; when the
//! ring is full it leaves the byte in the UART, which stops the sender (QEMU takes no more from
//! the host), and `read` restarts it once there is room. All writes to the DATA register happen
//! in the TX interrupt, which a writer pends when the transmitter is idle, so a write never
//! waits for the wire: the run loop only queues whole frames when the ring has room for them.

use core::cell::RefCell;
use core::task::Waker;

use critical_section::Mutex;
use heapless::Deque;

use crate::irq;

const DATA: usize = 0x00;
const STATE: usize = 0x04;
const CTRL: usize = 0x08;
const INTCLEAR: usize = 0x0C;
const BAUDDIV: usize = 0x10;
const STATE_TXFULL: u32 = 1 << 0;
const STATE_RXFULL: u32 = 1 << 1;
const CTRL_TX_EN: u32 = 1 << 0;
const CTRL_RX_EN: u32 = 1 << 1;
const CTRL_TX_INTEN: u32 = 1 << 2;
const CTRL_RX_INTEN: u32 = 1 << 3;
const INT_TX: u32 = 1 << 0;
const INT_RX: u32 = 1 << 1;
/// Ring sizes: eight largest frames.
pub const RING: usize = 4096;

/// One UART and its rings.
pub struct Uart {
    base: usize,
    rx_irq: u16,
    tx_irq: u16,
    state: Mutex<RefCell<State>>,
}

struct State {
    rx: Deque<u8, RING>,
    tx: Deque<u8, RING>,
    /// The TX interrupt will come (a byte is in the transmitter).
    tx_active: bool,
    /// A byte was left in the UART for lack of room.
    rx_held: bool,
    rx_bytes: u64,
    tx_bytes: u64,
}

/// Protocol port.
pub static UART0: Uart = Uart::new(0x4000_4000, 0, 1);
/// Debug port (the recorder).
pub static UART1: Uart = Uart::new(0x4000_5000, 2, 3);

/// The run loop's waker: every UART interrupt that moves bytes wakes it.
static WAKER: Mutex<RefCell<Option<Waker>>> = Mutex::new(RefCell::new(None));

/// Registers the run loop's waker.
pub fn register(waker: &Waker) {
    critical_section::with(|cs| {
        let mut w = WAKER.borrow_ref_mut(cs);
        if !w.as_ref().is_some_and(|old| old.will_wake(waker)) {
            *w = Some(waker.clone());
        }
    });
}

fn wake(cs: critical_section::CriticalSection) {
    if let Some(w) = WAKER.borrow_ref(cs).as_ref() {
        w.wake_by_ref();
    }
}

impl Uart {
    const fn new(base: usize, rx_irq: u16, tx_irq: u16) -> Self {
        let state = State {
            rx: Deque::new(),
            tx: Deque::new(),
            tx_active: false,
            rx_held: false,
            rx_bytes: 0,
            tx_bytes: 0,
        };
        Self { base, rx_irq, tx_irq, state: Mutex::new(RefCell::new(state)) }
    }

    fn read_reg(&self, reg: usize) -> u32 {
        // SAFETY: a register of this UART instance.
        unsafe { core::ptr::read_volatile((self.base + reg) as *const u32) }
    }

    fn write_reg(&self, reg: usize, value: u32) {
        // SAFETY: a register of this UART instance.
        unsafe { core::ptr::write_volatile((self.base + reg) as *mut u32, value) }
    }

    /// 115200 baud 8N1 (QEMU does not pace the line), both directions, interrupts on.
    pub fn init(&self) {
        self.write_reg(BAUDDIV, (crate::time::CYCLES_HZ / 115_200) as u32);
        self.write_reg(INTCLEAR, INT_TX | INT_RX);
        self.write_reg(CTRL, CTRL_TX_EN | CTRL_RX_EN | CTRL_TX_INTEN | CTRL_RX_INTEN);
        irq::enable(self.rx_irq);
        irq::enable(self.tx_irq);
    }

    /// RX interrupt body.
    pub fn on_rx(&self) {
        critical_section::with(|cs| {
            let mut s = self.state.borrow_ref_mut(cs);
            // Clear first: a byte arriving while we drain raises the interrupt again.
            self.write_reg(INTCLEAR, INT_RX);
            while self.read_reg(STATE) & STATE_RXFULL != 0 {
                if s.rx.is_full() {
                    s.rx_held = true;
                    break;
                }
                let byte = self.read_reg(DATA) as u8;
                let _ = s.rx.push_back(byte);
                s.rx_bytes += 1;
            }
            wake(cs);
        });
    }

    /// TX interrupt body: fills the transmitter from the ring.
    pub fn on_tx(&self) {
        critical_section::with(|cs| {
            let mut s = self.state.borrow_ref_mut(cs);
            self.write_reg(INTCLEAR, INT_TX);
            s.tx_active = false;
            while self.read_reg(STATE) & STATE_TXFULL == 0 {
                let Some(byte) = s.tx.pop_front() else { break };
                self.write_reg(DATA, u32::from(byte));
                s.tx_bytes += 1;
                s.tx_active = true;
            }
            wake(cs);
        });
    }

    /// Takes received bytes into `buf`; returns how many.
    pub fn read(&self, buf: &mut [u8]) -> usize {
        let (n, held) = critical_section::with(|cs| {
            let mut s = self.state.borrow_ref_mut(cs);
            let mut n = 0;
            for slot in buf.iter_mut() {
                let Some(b) = s.rx.pop_front() else { break };
                *slot = b;
                n += 1;
            }
            let held = s.rx_held && n > 0;
            if held {
                s.rx_held = false;
            }
            (n, held)
        });
        if held {
            irq::pend(self.rx_irq);
        }
        n
    }

    /// Received bytes waiting.
    pub fn readable(&self) -> bool {
        critical_section::with(|cs| !self.state.borrow_ref(cs).rx.is_empty())
    }

    /// Free room in the TX ring.
    pub fn writable(&self) -> usize {
        critical_section::with(|cs| {
            let s = self.state.borrow_ref(cs);
            s.tx.capacity() - s.tx.len()
        })
    }

    /// Queues `bytes` if they all fit; `false` (nothing queued) otherwise.
    pub fn write(&self, bytes: &[u8]) -> bool {
        let start = critical_section::with(|cs| {
            let mut s = self.state.borrow_ref_mut(cs);
            if s.tx.capacity() - s.tx.len() < bytes.len() {
                return None;
            }
            for &b in bytes {
                let _ = s.tx.push_back(b);
            }
            Some(!s.tx_active)
        });
        match start {
            Some(idle) => {
                if idle {
                    irq::pend(self.tx_irq);
                }
                true
            }
            None => false,
        }
    }

    /// Bytes received and sent since start.
    pub fn counters(&self) -> (u64, u64) {
        critical_section::with(|cs| {
            let s = self.state.borrow_ref(cs);
            (s.rx_bytes, s.tx_bytes)
        })
    }

    /// Interrupt lines (RX, TX).
    pub fn irqs(&self) -> (u16, u16) {
        (self.rx_irq, self.tx_irq)
    }
}
