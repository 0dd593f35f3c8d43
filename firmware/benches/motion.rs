//! Step-time generation: how fast `StepTimes` yields step ticks, and what one closed-form
//! `Trapezoid::step_tick` costs, on the host's CPU (the firmware's Cortex-M4 is far slower;
//! these figures compare methods, they are not the MCU's).
//!
//!     cargo bench -p lightrig-firmware --bench motion
//!
//! Moves of 1 000 000 steps:
//! - `trapezoid`: 100 000 steps/s reached at 20 000 steps/s²: 250 000 steps of ramp at either
//!   end, 500 000 of cruise.
//! - `triangle`: 20 000 steps/s², never reaching the speed limit: every step is a ramp step
//!   (the square-root path).
//!
//! each at 1 MHz and at 170 MHz ticks. One iteration generates the whole move; throughput is
//! in steps, so elements/s is steps/s. `step_tick` evaluates the closed form at 1 000 steps
//! spread over the trapezoid (all three phases); there an element is one call.

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use lightrig_firmware::motion::Trapezoid;

const STEPS: u32 = 1_000_000;
const RATES: [(u32, &str); 2] = [(1_000_000, "1MHz"), (170_000_000, "170MHz")];

fn plans(tick_hz: u32) -> [(&'static str, Trapezoid); 2] {
    [
        ("trapezoid", Trapezoid::new(STEPS, 100_000, 20_000, tick_hz).unwrap()),
        ("triangle", Trapezoid::new(STEPS, tick_hz / 2, 20_000, tick_hz).unwrap()),
    ]
}

/// Runs the whole move, folding the ticks so none is optimised away.
fn run(plan: &Trapezoid) -> u64 {
    plan.stepper().fold(0u64, |acc, t| acc ^ t)
}

fn stepper(c: &mut Criterion) {
    let mut group = c.benchmark_group("stepper");
    group.throughput(Throughput::Elements(u64::from(STEPS)));
    group.sample_size(20);
    for (tick_hz, rate) in RATES {
        for (shape, plan) in plans(tick_hz) {
            // What is measured must be right: the generator ends on the closed form's end.
            assert_eq!(plan.stepper().last(), Some(plan.duration()));
            group.bench_with_input(BenchmarkId::new(shape, rate), &plan, |b, plan| {
                b.iter(|| run(black_box(plan)))
            });
        }
    }
    group.finish();
}

fn closed_form(c: &mut Criterion) {
    const CALLS: u32 = 1_000;
    let mut group = c.benchmark_group("step_tick");
    group.throughput(Throughput::Elements(u64::from(CALLS)));
    for (tick_hz, rate) in RATES {
        let (_, plan) = plans(tick_hz)[0];
        let ks: Vec<u32> = (1..=CALLS).map(|i| i * (STEPS / CALLS) - 7).collect();
        group.bench_with_input(BenchmarkId::new("trapezoid", rate), &ks, |b, ks| {
            b.iter(|| ks.iter().fold(0u64, |acc, &k| acc ^ black_box(&plan).step_tick(k)))
        });
    }
    group.finish();
}

criterion_group!(benches, stepper, closed_form);
criterion_main!(benches);
