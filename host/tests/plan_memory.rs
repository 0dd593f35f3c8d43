//! A plan holds step heads, not step sequences: planning the DISCO example at full size (72 views
//! × 64² spots × 3 lasers, 885 k triggers) must not allocate its items and labels up front.
//!
//! The whole test binary counts its heap with a global allocator, so this file holds one test
//! (no other test's allocations run alongside).

use std::path::PathBuf;

use lightrig_firmware::sim::virtual_device_info;
use lightrig_host::plan::from_rig;
use lightrig_host::rigfile::RigFile;
use lightrig_protocol::sequence::{Action, Item};

#[path = "support/counting_alloc.rs"]
mod counting_alloc;
use counting_alloc::measured;

#[test]
fn the_full_disco_plan_holds_heads_and_builds_one_step_at_a_time() {
    let path = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/rigs/disco.toml"));
    let rig = RigFile::load(&path).unwrap();
    let info = virtual_device_info();

    let (plan, peak, kept) = measured(|| from_rig::plan(&rig, &info).unwrap());
    let s = plan.summary();
    // The white balance (a frame per laser), then 72 views at each of the two camera positions:
    // the registration frame and 3 × 64² spots.
    assert_eq!((s.steps, s.triggers), (1 + 2 * 72, 3 + 2 * 72 * (1 + 3 * 64 * 64)));
    // One view's sequence: a move, and per laser on/ready/off around
    // 4096 × (jump, trigger); ≈ 50 k items.
    let items_per_view = plan.steps[1].items().len();
    assert!(items_per_view > 3 * 64 * 64 * 2, "{items_per_view}");
    let all_items = 2 * 72 * items_per_view * std::mem::size_of::<Item>();
    eprintln!(
        "plan: peak {:.1} MB, kept {:.1} MB; all items would be {:.1} MB (+ labels)",
        peak as f64 / 1e6,
        kept as f64 / 1e6,
        all_items as f64 / 1e6
    );
    // Planning builds one view at a time (to count it) and keeps heads only: far below the
    // items of the whole plan, and not growing with the number of views.
    assert!(kept < all_items / 50, "the plan keeps {kept} B; all its items are {all_items} B");
    assert!(peak < all_items / 16, "planning peaked at {peak} B; all its items are {all_items} B");

    // Running the steps one after another: the peak is one step's body, whatever the count.
    let (lasers, peak, _) = measured(|| {
        let mut on = 0usize;
        for step in &plan.steps {
            on += step.items().iter().filter(|i| matches!(i.action, Action::Laser { on: true, .. })).count();
        }
        on
    });
    assert_eq!(
        lasers,
        3 + 2 * 72 * 4,
        "the spotlights and three lasers per view, three for the white balance"
    );
    let one_body = {
        let b = plan.steps[1].body();
        b.items.capacity() * std::mem::size_of::<Item>()
            + b.shots.iter().map(|s| std::mem::size_of_val(s) + s.label.capacity()).sum::<usize>()
    };
    assert!(peak < 3 * one_body, "building every step in turn peaked at {peak} B; one step is {one_body} B");
}
