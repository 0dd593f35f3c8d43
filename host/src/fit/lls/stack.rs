//! A pass's frames streamed to a scratch file in trace blocks, for `lightrig fit lls`.
//!
//! The fit needs each pixel's trace through a whole pass (every frame's value at that pixel),
//! while frames arrive one image at a time. Holding the pass in memory costs
//! `frames × pixels × 3` values; here each merged position is written once into a scratch
//! file laid out block-major (the pixels, row-major, cut into blocks of `block_pixels`; a
//! block holds every position's values of its pixels, position after position), and the fit
//! reads one block at a time. What is resident is one frame while streaming and one block
//! (`block_pixels × positions × 3` values) while fitting: choose `block_pixels` from a byte
//! budget ([`block_pixels`]) and the peak does not grow with the number of frames.

use std::fs::File;
use std::io::{Seek, SeekFrom, Write};
use std::ops::Range;
use std::path::{Path, PathBuf};

use rayon::prelude::*;

/// Bytes of one value (`f32`).
const VALUE: usize = 4;

/// Pixels per block such that a block of `positions` positions (RGB `f32`) takes at most
/// `budget` bytes (at least one pixel).
pub fn block_pixels(budget: usize, positions: usize) -> usize {
    (budget / (positions.max(1) * 3 * VALUE)).max(1)
}

/// One pass on disk, block-major; the file is removed when the stack is dropped.
#[derive(Debug)]
pub struct TraceStack {
    file: File,
    path: PathBuf,
    pixels: usize,
    positions: usize,
    block_pixels: usize,
    /// The largest value per channel over every position (NaN left out).
    pub peak: [f32; 3],
}

/// One block read back: its pixels' values at every position.
#[derive(Debug, Default)]
pub struct Block {
    /// The pixels (row-major indices).
    pub pixels: Range<usize>,
    positions: usize,
    data: Vec<f32>,
}

impl Block {
    /// Channel `c` of pixel `i` (inside [`Block::pixels`]) at position `k`.
    pub fn rate(&self, i: usize, k: usize, c: usize) -> f32 {
        self.data[(k * self.pixels.len() + (i - self.pixels.start)) * 3 + c]
    }

    /// Positions.
    pub fn positions(&self) -> usize {
        self.positions
    }

    /// Bytes of values held.
    pub fn resident_bytes(&self) -> usize {
        self.data.capacity() * VALUE
    }

    /// The traces of the consecutive pixels `px` (inside [`Block::pixels`]) copied out
    /// pixel-major: in the block a pixel's trace takes a cache line a position, and the fit
    /// of one pixel evicts what its neighbours would have shared; a few pixels (a cache line's
    /// worth, or more) copied at once read each line once.
    pub fn gather(&self, px: Range<usize>) -> Gathered {
        let (n, positions) = (self.pixels.len(), self.positions);
        let off = px.start - self.pixels.start;
        let mut data = vec![0.0; px.len() * positions * 3];
        for k in 0..positions {
            let at = (k * n + off) * 3;
            for (j, rgb) in self.data[at..at + px.len() * 3].chunks_exact(3).enumerate() {
                let to = (j * positions + k) * 3;
                data[to..to + 3].copy_from_slice(rgb);
            }
        }
        Gathered { pixels: px, positions, data }
    }
}

/// Some consecutive pixels' traces out of a [`Block`] ([`Block::gather`]).
#[derive(Debug)]
pub struct Gathered {
    pixels: Range<usize>,
    positions: usize,
    data: Vec<f32>,
}

impl Gathered {
    /// Whether pixel `i` is one of the gathered.
    pub fn holds(&self, i: usize) -> bool {
        self.pixels.contains(&i)
    }

    /// Pixel `i`'s trace (one of the gathered pixels): RGB at every position, position after
    /// position.
    pub fn trace(&self, i: usize) -> &[f32] {
        let n = self.positions * 3;
        let at = (i - self.pixels.start) * n;
        &self.data[at..at + n]
    }
}

impl TraceStack {
    /// A stack at `path` for `positions` images of `pixels` RGB pixels.
    pub fn create(
        path: &Path,
        pixels: usize,
        positions: usize,
        block_pixels: usize,
    ) -> std::io::Result<Self> {
        let file =
            std::fs::OpenOptions::new().read(true).write(true).create(true).truncate(true).open(path)?;
        file.set_len((pixels * positions * 3 * VALUE) as u64)?;
        Ok(TraceStack {
            file,
            path: path.to_path_buf(),
            pixels,
            positions,
            block_pixels: block_pixels.max(1),
            peak: [f32::MIN; 3],
        })
    }

    /// Positions.
    pub fn positions(&self) -> usize {
        self.positions
    }

    /// Blocks.
    pub fn blocks(&self) -> usize {
        self.pixels.div_ceil(self.block_pixels)
    }

    /// The pixels of block `b`.
    pub fn block_range(&self, b: usize) -> Range<usize> {
        let start = b * self.block_pixels;
        start..(start + self.block_pixels).min(self.pixels)
    }

    /// Where block `b` starts in the file.
    fn block_offset(&self, b: usize) -> u64 {
        (b * self.block_pixels * self.positions * 3 * VALUE) as u64
    }

    /// Writes position `k`: `rate`, interleaved RGB of every pixel, row-major. `bytes` is a
    /// buffer the caller keeps between calls (one block's row of bytes at most).
    pub fn write_position(&mut self, k: usize, rate: &[f32], bytes: &mut Vec<u8>) -> std::io::Result<()> {
        for (c, peak) in self.peak.iter_mut().enumerate() {
            *peak = rate.iter().skip(c).step_by(3).filter(|v| !v.is_nan()).fold(*peak, |a, &v| a.max(v));
        }
        for b in 0..self.blocks() {
            let px = self.block_range(b);
            bytes.clear();
            bytes.extend(rate[px.start * 3..px.end * 3].iter().flat_map(|v| v.to_le_bytes()));
            let at = self.block_offset(b) + (k * px.len() * 3 * VALUE) as u64;
            self.file.seek(SeekFrom::Start(at))?;
            self.file.write_all(bytes)?;
        }
        Ok(())
    }

    /// Reads block `b` into `out` (its buffer reused), in 64 KiB pieces on the thread pool:
    /// the fit waits for the block, and one thread copying it out of the page cache had left
    /// the other cores idle for about a twentieth of the fit.
    pub fn read_block(&mut self, b: usize, out: &mut Block) -> std::io::Result<()> {
        let px = self.block_range(b);
        let n = px.len() * self.positions * 3;
        if out.data.len() != n {
            out.data.clear();
            out.data.reserve_exact(n);
            out.data.resize(n, 0.0);
        }
        const PIECE: usize = (1 << 16) / VALUE;
        let (file, start) = (&self.file, self.block_offset(b));
        out.data.par_chunks_mut(PIECE).enumerate().try_for_each(|(j, values)| {
            // Into the values' own bytes (a copy and a pass through a buffer fewer: a fiftieth
            // of the fit), then from little-endian where the machine is not.
            read_at(file, bytemuck::cast_slice_mut(values), start + (j * PIECE * VALUE) as u64)?;
            if cfg!(target_endian = "big") {
                for v in values.iter_mut() {
                    *v = f32::from_bits(u32::from_le(v.to_bits()));
                }
            }
            Ok::<(), std::io::Error>(())
        })?;
        out.pixels = px;
        out.positions = self.positions;
        Ok(())
    }

    /// The scratch file.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// Fills `buf` from `file` at `offset`, without its cursor (so that threads can read one file
/// at once).
fn read_at(file: &File, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
    #[cfg(unix)]
    {
        std::os::unix::fs::FileExt::read_exact_at(file, buf, offset)
    }
    #[cfg(windows)]
    {
        let (mut buf, mut offset) = (buf, offset);
        while !buf.is_empty() {
            match std::os::windows::fs::FileExt::seek_read(file, buf, offset) {
                Ok(0) => return Err(std::io::ErrorKind::UnexpectedEof.into()),
                Ok(n) => {
                    buf = &mut buf[n..];
                    offset += n as u64;
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }
    #[cfg(not(any(unix, windows)))]
    {
        let _ = (file, buf, offset);
        Err(std::io::Error::new(std::io::ErrorKind::Unsupported, "positioned reads on this platform"))
    }
}

impl Drop for TraceStack {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blocks_give_back_every_pixel_at_every_position() {
        let dir = std::env::temp_dir().join(format!("lightrig-stack-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (pixels, positions) = (23, 7);
        let value = |i: usize, k: usize, c: usize| (i * 100 + k * 3 + c) as f32;
        for bp in [1, 4, 23, 100] {
            let path = dir.join(format!("s{bp}"));
            let mut s = TraceStack::create(&path, pixels, positions, bp).unwrap();
            let mut bytes = Vec::new();
            for k in 0..positions {
                let rate: Vec<f32> = (0..pixels * 3).map(|j| value(j / 3, k, j % 3)).collect();
                s.write_position(k, &rate, &mut bytes).unwrap();
            }
            assert_eq!(s.blocks(), pixels.div_ceil(bp.min(pixels).max(1)).max(1));
            let mut seen = 0;
            let mut block = Block::default();
            for b in 0..s.blocks() {
                s.read_block(b, &mut block).unwrap();
                for i in block.pixels.clone() {
                    for k in 0..positions {
                        for c in 0..3 {
                            assert_eq!(block.rate(i, k, c), value(i, k, c));
                        }
                    }
                    seen += 1;
                }
                // Gathered a few at a time, from any pixel of the block: the same traces.
                let px = block.pixels.clone();
                for start in px.clone() {
                    let run = start..(start + 3).min(px.end);
                    let g = block.gather(run.clone());
                    assert!(!g.holds(run.end) && (start == 0 || !g.holds(start - 1)));
                    for i in run {
                        assert!(g.holds(i));
                        let want: Vec<f32> = (0..positions * 3).map(|j| value(i, j / 3, j % 3)).collect();
                        assert_eq!(g.trace(i), &want[..]);
                    }
                }
            }
            assert_eq!(seen, pixels);
            assert_eq!(s.peak, [value(22, 6, 0), value(22, 6, 1), value(22, 6, 2)]);
            drop(s);
            assert!(!path.exists(), "the scratch file is removed");
        }
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn the_block_budget_does_not_depend_on_the_frames() {
        let budget = 1 << 20;
        for positions in [10, 400, 4000, 40000] {
            let bp = block_pixels(budget, positions);
            assert!(bp * positions * 3 * VALUE <= budget);
            assert!((bp + 1) * positions * 3 * VALUE > budget);
        }
        // More frames than the budget holds for one pixel: one pixel a block.
        assert_eq!(block_pixels(1000, 1000), 1);
    }
}
