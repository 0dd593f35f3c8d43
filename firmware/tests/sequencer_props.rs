//! Property tests: random sequences, streamed in random chunk sizes, against a model of when
//! each item is due.

mod common;

use common::*;
use lightrig_firmware::sim::Output;
use lightrig_protocol::config::Xy;
use lightrig_protocol::event::FaultCause;
use lightrig_protocol::sequence::{Action, StartAt};
use lightrig_protocol::Event;
use proptest::prelude::*;

fn action() -> impl Strategy<Value = Action> {
    prop_oneof![
        Just(Action::Trigger { camera: 0, exposure: 0 }),
        any::<u32>().prop_map(|id| Action::Marker { id }),
        (1000u16..=64000, 1000u16..=64000)
            .prop_map(|(x, y)| Action::GalvoPoint { galvo: 0, to: Xy { x, y } }),
        any::<bool>().prop_map(|on| Action::Laser { channel: 0, on }),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

    #[test]
    fn items_run_at_their_cumulative_ticks(
        items in prop::collection::vec((0u32..3_000, action()), 0..400),
        chunk_sizes in prop::collection::vec(1usize..=32, 1..40),
        start in 0u64..1_000,
    ) {
        let mut rig = rig();
        configure_all(&mut rig);
        rig.arm(0b1, 0).unwrap();
        rig.board_mut().record.clear();
        // The model: due ticks, and the first trigger that comes too soon (min interval 500).
        let mut due = Vec::new();
        let mut t = start;
        let mut last_trigger: Option<u64> = None;
        let mut fault_at = None;
        for (i, (delta, a)) in items.iter().enumerate() {
            t += u64::from(*delta);
            due.push(t);
            if let Action::Trigger { .. } = a {
                if fault_at.is_none() && last_trigger.is_some_and(|l| t - l < 500) {
                    fault_at = Some((i, t));
                }
                last_trigger = Some(t);
            }
        }
        // Stream: the host refills whenever the next chunk fits.
        let all: Vec<_> = items.iter().map(|(d, a)| item(*d, a.clone())).collect();
        let mut sent = 0usize;
        let mut chunk_no = 0u32;
        let mut sizes = chunk_sizes.iter().cycle();
        let mut events = Vec::new();
        let mut now = 0u64;
        let mut started = false;
        loop {
            while sent < all.len() || chunk_no == 0 {
                let n = (*sizes.next().unwrap()).min(all.len() - sent);
                let free = rig.buffer().map_or(256, |b| b.free as usize);
                if n > free || rig.fault().is_some() { break; }
                let last = sent + n == all.len();
                rig.load(&chunk(5, chunk_no, last, &all[sent..sent + n])).unwrap();
                sent += n;
                chunk_no += 1;
            }
            if !started {
                rig.start(5, StartAt::Tick(start), 0).unwrap();
                started = true;
            }
            now += 2_000;
            rig.run_until(now);
            events.extend(rig.drain_events());
            if rig.running().is_none() { break; }
        }
        // Triggers and markers report the item's own due tick.
        let mut ticks = Vec::new();
        for e in &events {
            match e {
                Event::Trigger(tr) => ticks.push((tr.item as usize, tr.tick)),
                Event::Marker { item, tick, .. } => ticks.push((*item as usize, *tick)),
                _ => {}
            }
        }
        for &(i, tick) in &ticks {
            prop_assert_eq!(tick, due[i]);
        }
        let reported = items.iter().enumerate().filter(|(i, (_, a))| {
            matches!(a, Action::Trigger { .. } | Action::Marker { .. }) && fault_at.is_none_or(|(f, _)| *i < f)
        }).count();
        prop_assert_eq!(ticks.len(), reported, "every trigger and marker before any fault reports");
        match fault_at {
            Some((_, t)) => {
                prop_assert_eq!(rig.fault(), Some(FaultCause::TriggerTooSoon { camera: 0 }));
                let fault = Event::Fault { cause: FaultCause::TriggerTooSoon { camera: 0 }, tick: t };
                prop_assert!(events.contains(&fault), "no fault event at {}", t);
            }
            None => {
                prop_assert_eq!(rig.fault(), None);
                // A sequence without items ends when it is started (tick 0 here), not at `start`.
                let end = due.last().copied().unwrap_or(0);
                let done = Event::SequenceDone { sequence: 5, items: items.len() as u32, tick: end };
                prop_assert!(events.contains(&done), "{:?}", events.last());
            }
        }
        // Events come in tick order; the laser never emits after the sequence.
        let mut last = 0;
        for e in &events {
            let tick = match e {
                Event::Trigger(t) => t.tick,
                Event::Marker { tick, .. } | Event::SequenceDone { tick, .. } | Event::Fault { tick, .. } => *tick,
                _ => continue,
            };
            prop_assert!(tick >= last);
            last = tick;
        }
        prop_assert_eq!(rig.lasers_on(), 0);
        let laser = rig.board().changes(|o| matches!(o, Output::Laser { channel: 0, .. }));
        if let Some(c) = laser.last() {
            prop_assert_eq!(c.output, Output::Laser { channel: 0, level: false });
        }
    }
}
