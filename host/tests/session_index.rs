//! Reading a session for processing holds memory that grows with its steps, not its frames: the
//! index keeps each attempt's place in the journal, a step's records are read back on demand.
//!
//! The whole test binary counts its heap with a global allocator, so this file holds one test.

use std::path::{Path, PathBuf};

use lightrig_host::session::{pair, Arrival, Session, SessionIndex};

#[path = "support/counting_alloc.rs"]
mod counting_alloc;
use counting_alloc::measured;

#[path = "support/sessions.rs"]
mod sessions;
use sessions::{event_record, manifest, plan, trigger_event, triggers_of};

const FRAMES_PER_STEP: u32 = 300;

/// A complete session of `steps` steps of `FRAMES_PER_STEP` frames from one camera.
fn session(dir: &Path, steps: u32) {
    let _ = std::fs::remove_dir_all(dir);
    let mut s = Session::create(dir, manifest(plan(steps, 1, FRAMES_PER_STEP))).unwrap();
    s.device_connected(&lightrig_firmware::sim::virtual_device_info()).unwrap();
    let mut index = 0;
    for id in s.pending_steps() {
        let step = s.manifest().step(id).unwrap().clone();
        s.start_step(id, id).unwrap();
        let triggers = triggers_of(&step, id);
        for t in &triggers {
            s.record_event(&event_record(1, index, trigger_event(t))).unwrap();
            index += 1;
        }
        let arrivals: Vec<Arrival> = triggers
            .iter()
            .map(|t| Arrival { camera: t.camera, frame: Some(t.frame), host_us: t.tick as f64 + 500.0 })
            .collect();
        for p in &pair(&triggers, &arrivals, 5_000.0).pairs {
            s.store_frame(p, "raw", &[7; 8]).unwrap();
        }
        s.finish_step().unwrap();
    }
    s.finish().unwrap();
}

fn scratch(name: &str) -> PathBuf {
    let shm = Path::new("/dev/shm");
    let base = if shm.is_dir() { shm.to_path_buf() } else { std::env::temp_dir() };
    base.join(format!("lightrig-index-{name}-{}", std::process::id()))
}

#[test]
fn the_index_and_a_steps_records_do_not_grow_with_the_sessions_frames() {
    let (small, large) = (scratch("small"), scratch("large"));
    let (few, many) = (4u32, 16u32);
    session(&small, few);
    session(&large, many);
    let more_steps = (many - few) as usize;
    let more_frames = more_steps * FRAMES_PER_STEP as usize;

    let (a, a_peak, a_kept) = measured(|| SessionIndex::read(&small).unwrap());
    let (b, b_peak, b_kept) = measured(|| SessionIndex::read(&large).unwrap());
    let (_, _, read_a) = measured(|| Session::read(&small).unwrap());
    let (_, _, read_b) = measured(|| Session::read(&large).unwrap());
    let per_frame_read = (read_b - read_a) as f64 / more_frames as f64;
    let per_step_index = b_kept.saturating_sub(a_kept) as f64 / more_steps as f64;
    eprintln!(
        "index: kept {a_kept} → {b_kept} B ({per_step_index:.0} B a step), peak {a_peak} → {b_peak} B; \
         Session::read keeps {per_frame_read:.0} B a frame"
    );
    // The full reader keeps every frame record; the index about 1 kB a step (its attempt in
    // the state's maps and its place in the journal), whatever the step's frames.
    assert!(per_frame_read > 200.0, "{per_frame_read}");
    assert!(per_step_index < 2048.0, "{per_step_index}");
    // While reading, the open attempt's records only: a session four times as long peaks
    // within its steps' entries of the short one (a step's records are ~100 kB here).
    assert!(b_peak < a_peak + 16 * 1024 + more_steps * 2048, "{a_peak} → {b_peak}");

    // A step's records: the same bytes whichever session they are read from.
    let (ra, step_a, _) = measured(|| a.step(12).unwrap());
    let (rb, step_b, _) = measured(|| b.step(12).unwrap());
    assert_eq!((ra.frames.len(), rb.frames.len(), rb.triggers.len()), (300, 300, 300));
    assert!(step_b <= step_a + 1024, "{step_a} → {step_b}");
    std::fs::remove_dir_all(&small).unwrap();
    std::fs::remove_dir_all(&large).unwrap();
}
