//! A global allocator that counts live heap bytes and their peak, for tests that bound memory.
//! A test binary that includes this (`#[path = "support/counting_alloc.rs"] mod counting_alloc;`)
//! counts every allocation it makes, so such a binary holds one test.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

/// The system allocator, counting.
pub struct Counting;

/// Live bytes.
pub static LIVE: AtomicUsize = AtomicUsize::new(0);
/// The most live bytes since the last [`measured`] began.
pub static PEAK: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            let now = LIVE.fetch_add(layout.size(), Ordering::SeqCst) + layout.size();
            PEAK.fetch_max(now, Ordering::SeqCst);
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) };
        LIVE.fetch_sub(layout.size(), Ordering::SeqCst);
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// Runs `f` and returns its result with the heap's peak above the level before it (bytes),
/// and what it left allocated.
#[allow(dead_code)] // not every binary that counts uses it
pub fn measured<R>(f: impl FnOnce() -> R) -> (R, usize, usize) {
    let base = LIVE.load(Ordering::SeqCst);
    PEAK.store(base, Ordering::SeqCst);
    let r = f();
    let peak = PEAK.load(Ordering::SeqCst) - base;
    let kept = LIVE.load(Ordering::SeqCst).saturating_sub(base);
    (r, peak, kept)
}
