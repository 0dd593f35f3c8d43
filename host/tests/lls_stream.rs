//! The streamed LLS stack's memory: with a fixed block budget the heap's peak while a pass is
//! written and read back block by block does not grow with the number of frames (a counting
//! allocator; this binary holds this one test so that nothing else allocates meanwhile).

use lightrig_host::fit::lls::stack::{block_pixels, Block, TraceStack};

#[path = "support/counting_alloc.rs"]
mod counting_alloc;
use counting_alloc::{LIVE as NOW, PEAK};
use std::sync::atomic::Ordering;

/// Streams `frames` frames of `w × h` through a stack with block budget `budget`, reads every
/// block back and checks the values; returns the heap's peak above its level before.
fn peak_streaming(frames: usize, w: usize, h: usize, budget: usize, dir: &std::path::Path) -> usize {
    let base = NOW.load(Ordering::SeqCst);
    PEAK.store(base, Ordering::SeqCst);
    let pixels = w * h;
    let value = |i: usize, k: usize, c: usize| ((i * 7 + k * 13 + c) % 1000) as f32 / 1000.0;
    {
        let path = dir.join(format!("stack-{frames}"));
        let mut stack = TraceStack::create(&path, pixels, frames, block_pixels(budget, frames)).unwrap();
        let mut bytes = Vec::new();
        // One frame at a time, as a decoder delivers them.
        let mut frame = vec![0f32; pixels * 3];
        for k in 0..frames {
            for (j, v) in frame.iter_mut().enumerate() {
                *v = value(j / 3, k, j % 3);
            }
            stack.write_position(k, &frame, &mut bytes).unwrap();
        }
        drop(frame);
        let mut block = Block::default();
        let mut checked = 0;
        for b in 0..stack.blocks() {
            stack.read_block(b, &mut block).unwrap();
            assert!(block.resident_bytes() <= budget);
            for i in block.pixels.clone() {
                for k in [0, frames / 2, frames - 1] {
                    assert_eq!(block.rate(i, k, 1), value(i, k, 1));
                }
                checked += 1;
            }
        }
        assert_eq!(checked, pixels);
    }
    PEAK.load(Ordering::SeqCst) - base
}

#[test]
fn the_streamed_stack_s_peak_memory_does_not_grow_with_the_frames() {
    let dir = std::env::temp_dir().join(format!("lightrig-stream-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (w, h, budget) = (64, 48, 256 << 10);
    let frame_bytes = w * h * 3 * 4;
    let peaks: Vec<(usize, usize)> =
        [50, 400, 1600].iter().map(|&n| (n, peak_streaming(n, w, h, budget, &dir))).collect();
    // In memory the stack would take frames × frame_bytes (2.4, 19.7, 79 MB); streamed, one
    // frame, one block (≤ budget), the write buffer (one block's row) and the read buffer.
    let bound = budget + 2 * frame_bytes + (64 << 10);
    for &(n, peak) in &peaks {
        assert!(peak <= bound, "{n} frames: peak {peak} bytes > {bound}");
    }
    let (least, most) = peaks.iter().fold((usize::MAX, 0), |a, p| (a.0.min(p.1), a.1.max(p.1)));
    assert!(most - least <= budget / 4, "peaks {peaks:?}");
    std::fs::remove_dir_all(&dir).ok();
}
