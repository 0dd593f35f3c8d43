//! Galvo outputs: the frame formats of the converters a galvo pair can hang on, and the
//! per-pair [`GalvoOutput`] drivers a board puts behind its [`crate::hal::Galvos`]
//! implementation. Timing is the rig's job; an output only turns a position pair into bits on
//! its interface.
//!
//! Frame formats (from the converters' datasheets):
//! - **DAC8563** (TI, 16-bit dual): 24 bits, MSB first: `x x C2 C1 C0 A2 A1 A0 D15..D0`.
//!   `C = 011` writes input register n and updates DAC n; `A = 000` is DAC-A, `001` DAC-B.
//! - **AD5689** (ADI, 16-bit dual): 24 bits, MSB first: `C3..C0 A3..A0 D15..D0`.
//!   `C = 0011` writes and updates DAC channel n; `A = 0001` is DAC A, `1000` DAC B.
//! - **XY2-100**: per axis a 20-bit frame at 100 kHz, MSB first: control code `001`, the
//!   16-bit unsigned position, then an even-parity bit over the 19 bits before it.
//!
//! - **MCU DAC**: the microcontroller's two 12-bit channels, written together.
//!
//! XY2-100 over GPIO: [`xy2_100_gpio_frame`] gives a frame's pin states, [`Xy2PortPins`] turns
//! them into a port's BSRR words for a timer-paced DMA, and [`Xy2Refresh`] says which frame of
//! the DMA's two-frame ring to rewrite so that no frame mixes two positions.
//!
//! X goes to DAC channel A (channel 1), Y to channel B (channel 2).

use embedded_hal::spi::SpiDevice;
use lightrig_protocol::config::Xy;

/// One axis of a galvo pair.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Axis {
    /// X: DAC channel A.
    X,
    /// Y: DAC channel B.
    Y,
}

/// The DAC8563 frame that writes `code` to `axis` and updates that output at once.
pub const fn dac8563_frame(axis: Axis, code: u16) -> [u8; 3] {
    const WRITE_AND_UPDATE: u8 = 0b011;
    let address = match axis {
        Axis::X => 0b000,
        Axis::Y => 0b001,
    };
    [(WRITE_AND_UPDATE << 3) | address, (code >> 8) as u8, code as u8]
}

/// The AD5689 frame that writes `code` to `axis` and updates that output at once.
pub const fn ad5689_frame(axis: Axis, code: u16) -> [u8; 3] {
    const WRITE_AND_UPDATE: u8 = 0b0011;
    let address = match axis {
        Axis::X => 0b0001,
        Axis::Y => 0b1000,
    };
    [(WRITE_AND_UPDATE << 4) | address, (code >> 8) as u8, code as u8]
}

/// The XY2-100 frame for one axis: 20 bits in the low bits of the word, the first bit to send
/// at bit 19.
pub const fn xy2_100_frame(position: u16) -> u32 {
    const CONTROL: u32 = 0b001;
    let bits19 = (CONTROL << 16) | position as u32;
    let parity = bits19.count_ones() & 1; // makes the number of ones even
    (bits19 << 1) | parity
}

/// A galvo pair's output stage.
pub trait GalvoOutput {
    /// The interface's error.
    type Error;

    /// Drives both mirrors to `to` (DAC codes).
    fn set(&mut self, to: Xy) -> Result<(), Self::Error>;
}

/// Which SPI DAC frame format to speak.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SpiDacKind {
    /// TI DAC8563.
    Dac8563,
    /// ADI AD5689.
    Ad5689,
}

/// A dual 16-bit DAC on an `embedded-hal` SPI device: one 24-bit transaction per axis.
pub struct SpiDacGalvo<S> {
    spi: S,
    kind: SpiDacKind,
}

impl<S: SpiDevice> SpiDacGalvo<S> {
    /// A galvo pair on `spi` speaking `kind`'s frame format.
    pub fn new(spi: S, kind: SpiDacKind) -> Self {
        Self { spi, kind }
    }

    /// Gives the SPI device back.
    pub fn release(self) -> S {
        self.spi
    }

    fn frame(&self, axis: Axis, code: u16) -> [u8; 3] {
        match self.kind {
            SpiDacKind::Dac8563 => dac8563_frame(axis, code),
            SpiDacKind::Ad5689 => ad5689_frame(axis, code),
        }
    }
}

impl<S: SpiDevice> GalvoOutput for SpiDacGalvo<S> {
    type Error = S::Error;

    fn set(&mut self, to: Xy) -> Result<(), S::Error> {
        // Two transactions: each chip-select cycle latches one channel (write-and-update).
        self.spi.write(&self.frame(Axis::X, to.x))?;
        self.spi.write(&self.frame(Axis::Y, to.y))
    }
}

/// XY2-100 over GPIO: the pin states of one frame period, for a DMA stream into a GPIO port
/// at 4 MHz (two states per bit, 20 bits per 10 µs frame, so 100 kHz frames). Each byte is
/// one state: bit 0 `CLOCK`, bit 1 `SYNC`, bit 2 `X` (channel 1), bit 3 `Y` (channel 2).
///
/// The data lines change with the clock's rising edge and the galvo samples them on the
/// falling edge; `SYNC` is high for the first 19 bits and low for the parity bit, which marks
/// the frame's end. (Real links are differential; the line drivers take these single-ended
/// states.)
pub mod xy2_100_pins {
    /// Clock.
    pub const CLOCK: u8 = 1 << 0;
    /// Frame sync.
    pub const SYNC: u8 = 1 << 1;
    /// X data (channel 1).
    pub const X: u8 = 1 << 2;
    /// Y data (channel 2).
    pub const Y: u8 = 1 << 3;
}

/// GPIO states per XY2-100 frame.
pub const XY2_100_STATES: usize = 40;

/// The GPIO states of the XY2-100 frame that drives the mirrors to `to`.
pub const fn xy2_100_gpio_frame(to: Xy) -> [u8; XY2_100_STATES] {
    use xy2_100_pins::*;
    let (fx, fy) = (xy2_100_frame(to.x), xy2_100_frame(to.y));
    let mut out = [0u8; XY2_100_STATES];
    let mut i = 0;
    while i < 20 {
        let shift = 19 - i;
        let mut data = 0u8;
        if (fx >> shift) & 1 == 1 {
            data |= X;
        }
        if (fy >> shift) & 1 == 1 {
            data |= Y;
        }
        if i < 19 {
            data |= SYNC;
        }
        out[2 * i] = data | CLOCK;
        out[2 * i + 1] = data;
        i += 1;
    }
    out
}

/// A GPIO port fed by DMA, one state per 250 ns.
pub trait GpioStream {
    /// The stream's error.
    type Error;
    /// Queues one frame period of pin states; it repeats until the next frame is queued.
    fn queue_frame(&mut self, states: &[u8; XY2_100_STATES]) -> Result<(), Self::Error>;
}

/// The pin numbers (0-15) of the four XY2-100 lines on one GPIO port, for a DMA stream of
/// set/reset-register (BSRR) words: each word sets the lines that are high and resets the
/// others, leaving the port's other pins alone.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Xy2PortPins {
    /// Clock line.
    pub clock: u8,
    /// Frame sync line.
    pub sync: u8,
    /// X data line.
    pub x: u8,
    /// Y data line.
    pub y: u8,
}

impl Xy2PortPins {
    /// The BSRR word for one state of [`xy2_100_gpio_frame`]: bit `n` sets pin `n`, bit
    /// `16 + n` resets it. Pin numbers are taken modulo 16.
    pub const fn bsrr(self, state: u8) -> u32 {
        use xy2_100_pins::*;
        let lines = [(CLOCK, self.clock), (SYNC, self.sync), (X, self.x), (Y, self.y)];
        let mut word = 0u32;
        let mut i = 0;
        while i < lines.len() {
            let (mask, pin) = lines[i];
            let bit = 1u32 << (pin & 15);
            word |= if state & mask != 0 { bit } else { bit << 16 };
            i += 1;
        }
        word
    }

    /// The BSRR words of one frame's states.
    pub const fn bsrr_frame(self, states: &[u8; XY2_100_STATES]) -> [u32; XY2_100_STATES] {
        let mut out = [0u32; XY2_100_STATES];
        let mut i = 0;
        while i < XY2_100_STATES {
            out[i] = self.bsrr(states[i]);
            i += 1;
        }
        out
    }
}

/// Words in an XY2-100 DMA ring: two frames, played in a loop.
pub const XY2_100_RING: usize = 2 * XY2_100_STATES;

/// Which frame of a two-frame circular DMA ring to rewrite when the position changes, so the
/// link never carries a frame that mixes two positions (a torn frame can pass the parity check
/// with a position that was never asked for).
///
/// A new frame goes first into the half the DMA is not reading, if the DMA is at least
/// `margin` states from its end (the copy must finish before the DMA gets there), then, at the
/// next half boundary, into the other. Until both halves hold it, the board keeps the DMA's
/// half-transfer and transfer-complete interrupts on and calls [`Xy2Refresh::refresh`] from
/// them. Positions are given by the DMA's remaining count (NDTR: `XY2_100_RING` down to 1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Xy2Refresh {
    /// Version of the newest frame.
    latest: u32,
    /// Version each half holds.
    halves: [u32; 2],
    margin: usize,
}

impl Xy2Refresh {
    /// Both halves hold the current frame (version 0).
    pub const fn new(margin: usize) -> Self {
        Self { latest: 0, halves: [0, 0], margin }
    }

    /// The half the DMA reads next and how many states it has left in it, from the DMA's
    /// remaining count.
    pub const fn position(remaining: u16) -> (usize, usize) {
        let remaining = remaining as usize;
        let remaining = if remaining > XY2_100_RING { XY2_100_RING } else { remaining };
        let next = (XY2_100_RING - remaining) % XY2_100_RING;
        (next / XY2_100_STATES, XY2_100_STATES - next % XY2_100_STATES)
    }

    /// A new frame is the latest: both halves are stale.
    pub fn new_frame(&mut self) {
        self.latest = self.latest.wrapping_add(1);
    }

    /// The half to copy the latest frame into now, if it is stale and the DMA is far enough
    /// from it; the half is marked as holding it.
    pub fn refresh(&mut self, remaining: u16) -> Option<usize> {
        let (reading, left) = Self::position(remaining);
        let idle = 1 - reading;
        if self.halves[idle] == self.latest || left < self.margin {
            return None;
        }
        self.halves[idle] = self.latest;
        Some(idle)
    }

    /// Whether a half still holds an older frame (the board keeps calling `refresh` at the
    /// half boundaries).
    pub fn pending(&self) -> bool {
        self.halves[0] != self.latest || self.halves[1] != self.latest
    }
}

/// A galvo pair on an XY2-100 link driven from a GPIO port.
pub struct Xy2Gpio<G> {
    port: G,
}

impl<G: GpioStream> Xy2Gpio<G> {
    /// A galvo pair on `port`.
    pub fn new(port: G) -> Self {
        Self { port }
    }

    /// Gives the port back.
    pub fn release(self) -> G {
        self.port
    }
}

impl<G: GpioStream> GalvoOutput for Xy2Gpio<G> {
    type Error = G::Error;

    fn set(&mut self, to: Xy) -> Result<(), G::Error> {
        self.port.queue_frame(&xy2_100_gpio_frame(to))
    }
}

/// The microcontroller's own two 12-bit DAC channels.
pub trait DualDac12 {
    /// The converter's error.
    type Error;
    /// Writes both channels at once (`0..=4095` each; X to channel 1, Y to channel 2).
    fn write(&mut self, x: u16, y: u16) -> Result<(), Self::Error>;
}

/// A galvo pair on the MCU's DAC. Codes are already 12-bit (`DacKind::McuDac::max_code`);
/// anything above is clamped rather than wrapped, so a bad code never flips the mirror.
pub struct McuDacGalvo<D> {
    dac: D,
}

impl<D: DualDac12> McuDacGalvo<D> {
    /// A galvo pair on `dac`.
    pub fn new(dac: D) -> Self {
        Self { dac }
    }

    /// Gives the converter back.
    pub fn release(self) -> D {
        self.dac
    }
}

impl<D: DualDac12> GalvoOutput for McuDacGalvo<D> {
    type Error = D::Error;

    fn set(&mut self, to: Xy) -> Result<(), D::Error> {
        self.dac.write(to.x.min(4095), to.y.min(4095))
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use embedded_hal::spi::{ErrorType, Operation};
    use std::vec::Vec;

    #[test]
    fn dac8563_frames_exact_bits() {
        // 00 011 000 | 0x1234: write-and-update DAC-A.
        assert_eq!(dac8563_frame(Axis::X, 0x1234), [0b0001_1000, 0x12, 0x34]);
        // 00 011 001 | 0xFFFF: DAC-B.
        assert_eq!(dac8563_frame(Axis::Y, 0xFFFF), [0b0001_1001, 0xFF, 0xFF]);
    }

    #[test]
    fn ad5689_frames_exact_bits() {
        assert_eq!(ad5689_frame(Axis::X, 0x8000), [0b0011_0001, 0x80, 0x00]);
        assert_eq!(ad5689_frame(Axis::Y, 0x00FF), [0b0011_1000, 0x00, 0xFF]);
    }

    #[test]
    #[allow(clippy::unusual_byte_groupings)] // grouped by field: control | position | parity
    fn xy2_100_frames_exact_bits() {
        // 001 | 0x0000 | parity: one 1 so far, parity 1.
        assert_eq!(xy2_100_frame(0x0000), 0b001_0000_0000_0000_0000_1);
        // 001 | 0x8000: two ones, parity 0.
        assert_eq!(xy2_100_frame(0x8000), 0b001_1000_0000_0000_0000_0);
        // 001 | 0xFFFF: seventeen ones, parity 1.
        assert_eq!(xy2_100_frame(0xFFFF), 0b001_1111_1111_1111_1111_1);
        for p in [0u16, 1, 0x7fff, 0x8000, 0xA5A5, 0xffff] {
            let f = xy2_100_frame(p);
            assert_eq!(f >> 20, 0, "20 bits");
            assert_eq!(f >> 17, 0b001, "control code first");
            assert_eq!((f >> 1) as u16, p, "position MSB first");
            assert_eq!(f.count_ones() % 2, 0, "even parity over the whole frame");
        }
    }

    /// Records every SPI transaction.
    #[derive(Default)]
    struct RecordingSpi {
        transactions: Vec<Vec<u8>>,
    }

    impl ErrorType for RecordingSpi {
        type Error = core::convert::Infallible;
    }

    impl SpiDevice for RecordingSpi {
        fn transaction(&mut self, ops: &mut [Operation<'_, u8>]) -> Result<(), Self::Error> {
            let mut bytes = Vec::new();
            for op in ops {
                if let Operation::Write(w) = op {
                    bytes.extend_from_slice(w);
                }
            }
            self.transactions.push(bytes);
            Ok(())
        }
    }

    #[test]
    fn spi_dac_galvo_sends_one_frame_per_axis() {
        let mut g = SpiDacGalvo::new(RecordingSpi::default(), SpiDacKind::Ad5689);
        g.set(Xy { x: 0x1234, y: 0xBEEF }).unwrap();
        let g2 = {
            let mut g2 = SpiDacGalvo::new(RecordingSpi::default(), SpiDacKind::Dac8563);
            g2.set(Xy { x: 1, y: 2 }).unwrap();
            g2
        };
        assert_eq!(g.release().transactions, [[0x31, 0x12, 0x34], [0x38, 0xBE, 0xEF]]);
        assert_eq!(g2.release().transactions, [[0x18, 0x00, 0x01], [0x19, 0x00, 0x02]]);
    }

    #[test]
    fn xy2_100_gpio_frame_exact_states() {
        use xy2_100_pins::*;
        // X = 0x8000: frame 001 1000..0 0 (two ones, parity 0).
        // Y = 0x0001: frame 001 0000..1 0 (two ones, parity 0).
        let f = xy2_100_gpio_frame(Xy { x: 0x8000, y: 0x0001 });
        let bits =
            |mask: u8| -> u32 { (0..20).fold(0, |acc, i| (acc << 1) | u32::from(f[2 * i] & mask != 0)) };
        assert_eq!(bits(X), xy2_100_frame(0x8000));
        assert_eq!(bits(Y), xy2_100_frame(0x0001));
        assert_eq!(bits(SYNC), 0b1111_1111_1111_1111_1110, "sync low on the parity bit only");
        for i in 0..20 {
            assert_eq!(f[2 * i] & CLOCK, CLOCK, "clock high first");
            assert_eq!(f[2 * i + 1], f[2 * i] & !CLOCK, "data held across the falling edge");
        }
        // Spot check of the raw bytes: bit 2 (control `001`, third bit) carries 1 on both.
        assert_eq!(f[4], CLOCK | SYNC | X | Y);
        assert_eq!(f[6], CLOCK | SYNC | X); // X's position MSB
        assert_eq!(f[38], CLOCK); // parity 0 on both, sync low
    }

    #[test]
    fn xy2_100_bsrr_words_exact() {
        use xy2_100_pins::*;
        // CLOCK PC10, SYNC PC11, X PC12, Y PC9 (the NUCLEO-G474RE's map).
        let pins = Xy2PortPins { clock: 10, sync: 11, x: 12, y: 9 };
        // All low: the four reset bits.
        assert_eq!(pins.bsrr(0), (1 << 26) | (1 << 27) | (1 << 28) | (1 << 25));
        // All high: the four set bits.
        assert_eq!(pins.bsrr(CLOCK | SYNC | X | Y), (1 << 10) | (1 << 11) | (1 << 12) | (1 << 9));
        // Clock and X high, sync and Y low.
        assert_eq!(pins.bsrr(CLOCK | X), (1 << 10) | (1 << 12) | (1 << 27) | (1 << 25));
        assert_eq!(pins.bsrr(CLOCK | X), 0x0A00_1400);
        // Every word touches exactly the four lines, each either set or reset.
        let frame = pins.bsrr_frame(&xy2_100_gpio_frame(Xy { x: 0xA5A5, y: 0x0F0F }));
        for w in frame {
            assert_eq!((w | (w >> 16)) & 0xFFFF, 0x1E00);
            assert_eq!(w & (w >> 16), 0, "never set and reset together");
        }
        // The first state (control bit 0, clock high, sync high) is the same for every frame.
        assert_eq!(frame[0], (1 << 10) | (1 << 11) | (1 << 28) | (1 << 25));
        // Pin numbers wrap at 16 rather than overflow.
        assert_eq!(Xy2PortPins { clock: 16, sync: 17, x: 18, y: 19 }.bsrr(CLOCK), 0x000E_0001);
    }

    #[test]
    fn xy2_100_ring_position() {
        // NDTR counts down from the ring's length: 80 = word 0 next.
        assert_eq!(Xy2Refresh::position(80), (0, 40));
        assert_eq!(Xy2Refresh::position(79), (0, 39));
        assert_eq!(Xy2Refresh::position(41), (0, 1));
        assert_eq!(Xy2Refresh::position(40), (1, 40));
        assert_eq!(Xy2Refresh::position(1), (1, 1));
        // Out of range (not running): treated as the ring's start.
        assert_eq!(Xy2Refresh::position(0), (0, 40));
        assert_eq!(Xy2Refresh::position(200), (0, 40));
    }

    #[test]
    fn xy2_100_refresh_writes_the_idle_half_then_the_other() {
        let mut r = Xy2Refresh::new(8);
        assert!(!r.pending());
        assert_eq!(r.refresh(80), None, "nothing new");
        r.new_frame();
        assert!(r.pending());
        // DMA at word 10 of half 0: half 1 is idle and 30 states away.
        assert_eq!(r.refresh(70), Some(1));
        assert!(r.pending());
        assert_eq!(r.refresh(69), None, "half 0 is being read");
        // Half boundary: the DMA entered half 1, half 0 is idle.
        assert_eq!(r.refresh(40), Some(0));
        assert!(!r.pending());
        assert_eq!(r.refresh(80), None);
    }

    #[test]
    fn xy2_100_refresh_waits_when_the_dma_is_near_the_idle_half() {
        let mut r = Xy2Refresh::new(8);
        r.new_frame();
        // 7 states left in half 0: too close to start copying into half 1.
        assert_eq!(r.refresh(47), None);
        // 8 left: enough.
        let mut r2 = r;
        assert_eq!(r2.refresh(48), Some(1));
        // The boundary into half 1 (stale): half 0 is written; half 1 waits for the next one.
        assert_eq!(r.refresh(40), Some(0));
        assert!(r.pending());
        // A boundary interrupt served late, 3 states before the end of half 1: wait again.
        assert_eq!(r.refresh(3), None);
        assert_eq!(r.refresh(80), Some(1));
        assert!(!r.pending());
    }

    #[test]
    fn xy2_100_refresh_follows_the_newest_frame() {
        let mut r = Xy2Refresh::new(8);
        r.new_frame();
        assert_eq!(r.refresh(80), Some(1));
        // Another position before the first reached both halves.
        r.new_frame();
        assert_eq!(r.refresh(79), Some(1), "half 1 is stale again");
        assert_eq!(r.refresh(40), Some(0));
        assert!(!r.pending());
        // Version counters wrap without harm.
        let mut r = Xy2Refresh { latest: u32::MAX, halves: [u32::MAX; 2], margin: 8 };
        r.new_frame();
        assert_eq!(r.refresh(80), Some(1));
        assert_eq!(r.refresh(40), Some(0));
        assert!(!r.pending());
    }

    struct Port(Vec<[u8; XY2_100_STATES]>);

    impl GpioStream for Port {
        type Error = core::convert::Infallible;
        fn queue_frame(&mut self, states: &[u8; XY2_100_STATES]) -> Result<(), Self::Error> {
            self.0.push(*states);
            Ok(())
        }
    }

    struct Dac(Vec<(u16, u16)>);

    impl DualDac12 for Dac {
        type Error = core::convert::Infallible;
        fn write(&mut self, x: u16, y: u16) -> Result<(), Self::Error> {
            self.0.push((x, y));
            Ok(())
        }
    }

    #[test]
    fn xy2_and_mcu_dac_outputs() {
        let mut g = Xy2Gpio::new(Port(Vec::new()));
        g.set(Xy { x: 1, y: 2 }).unwrap();
        assert_eq!(g.release().0, [xy2_100_gpio_frame(Xy { x: 1, y: 2 })]);
        let mut d = McuDacGalvo::new(Dac(Vec::new()));
        d.set(Xy { x: 4095, y: 7 }).unwrap();
        d.set(Xy { x: 5000, y: 65535 }).unwrap();
        assert_eq!(d.release().0, [(4095, 7), (4095, 4095)]);
    }
}
