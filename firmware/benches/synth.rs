//! Voice-coil synthesis cost per output sample.
//!
//!     cargo bench -p lightrig-firmware --bench synth
//!
//! Two channels at 48 kHz, each filling a 256-sample buffer per iteration; one element is one
//! sample of both channels, so time per element is the cost of a two-channel output sample.
//! - `steady_2x8`: 8 partials per channel, not ramping (the usual state).
//! - `crossfade_2x16`: 16 voices per channel, all ramping (8 fading out, 8 fading in): the
//!   worst case.
//!
//! These are host figures; the Cortex-M4's cost has to be measured on the board.

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use lightrig_firmware::synth::Synth;
use lightrig_protocol::sequence::Partial;

const RATE: u32 = 48_000;
const BUFFER: usize = 256;

/// Eight partials from `base_mhz` up, summing to just under full scale.
fn partials(base_mhz: u32) -> [Partial; 8] {
    core::array::from_fn(|i| Partial {
        freq_mhz: base_mhz + 13_579 * i as u32 * (i as u32 + 1),
        amplitude: 8_000 - 300 * i as u16,
        phase: 7_919 * i as u16,
    })
}

fn channels(crossfade: bool) -> [Synth; 2] {
    [20_000, 31_000].map(|base| {
        let mut s = Synth::new(RATE);
        s.set(&partials(base), 0).unwrap();
        if crossfade {
            // A ramp of u32::MAX samples (a day) keeps all 16 voices ramping throughout.
            s.set(&partials(base + 500_000), u32::MAX).unwrap();
        }
        s
    })
}

fn synth(c: &mut Criterion) {
    let mut group = c.benchmark_group("synth");
    group.throughput(Throughput::Elements(BUFFER as u64));
    for (name, crossfade, voices) in [("steady_2x8", false, 8), ("crossfade_2x16", true, 16)] {
        let mut chans = channels(crossfade);
        assert!(chans.iter().all(|s| s.active_voices() == voices));
        let mut out = [[0i16; BUFFER]; 2];
        group.bench_function(name, |b| {
            b.iter(|| {
                for (s, o) in chans.iter_mut().zip(out.iter_mut()) {
                    s.fill(black_box(o));
                }
                black_box(&out);
            })
        });
        assert!(chans.iter().all(|s| s.active_voices() == voices));
    }
    group.finish();
}

criterion_group!(benches, synth);
criterion_main!(benches);
