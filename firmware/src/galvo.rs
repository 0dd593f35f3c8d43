//! Galvo outputs: the frame formats of the converters a galvo pair can hang on, and the
//! [`GalvoOutput`] trait the sequencer drives. Timing is the scheduler's job; an output only
//! turns a 16-bit position pair into bits on its interface.
//!
//! Frame formats (from the converters' datasheets):
//! - **DAC8563** (TI, 16-bit dual): 24 bits, MSB first: `x x C2 C1 C0 A2 A1 A0 D15..D0`.
//!   `C = 011` writes input register n and updates DAC n; `A = 000` is DAC-A, `001` DAC-B.
//! - **AD5689** (ADI, 16-bit dual): 24 bits, MSB first: `C3..C0 A3..A0 D15..D0`.
//!   `C = 0011` writes and updates DAC channel n; `A = 0001` is DAC A, `1000` DAC B.
//! - **XY2-100**: per axis a 20-bit frame at 100 kHz, MSB first: control code `001`, the
//!   16-bit unsigned position, then an even-parity bit over the 19 bits before it.
//!
//! X goes to DAC channel A, Y to channel B.

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
}
