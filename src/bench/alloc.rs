//! A counting global allocator for the peak-memory column of `tapestry bench`.
//!
//! The `tapestry` binary installs [`CountingAlloc`] as its `#[global_allocator]`; it forwards
//! to the system allocator and keeps the bytes currently allocated and their high-water mark
//! in two atomics. [`measure_peak`] resets the mark, runs a closure and returns the peak
//! allocated above the level at the start (bytes held by every thread, the rayon workers
//! included). In a program that does not install the allocator (the test binaries) nothing is
//! counted and [`installed`] is false: the bench then reports `peak_bytes` as null.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

static CURRENT: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);
static INSTALLED: AtomicBool = AtomicBool::new(false);

/// The system allocator with byte counting (see the module docs).
pub struct CountingAlloc;

impl CountingAlloc {
    fn add(n: usize) {
        let now = CURRENT.fetch_add(n, Ordering::Relaxed) + n;
        PEAK.fetch_max(now, Ordering::Relaxed);
    }
    fn sub(n: usize) {
        CURRENT.fetch_sub(n, Ordering::Relaxed);
    }
    /// Counts a fresh block `p` of `size` bytes (none when null) and marks the allocator as
    /// installed.
    fn counted(p: *mut u8, size: usize) -> *mut u8 {
        if !p.is_null() {
            Self::add(size);
            if !INSTALLED.load(Ordering::Relaxed) {
                INSTALLED.store(true, Ordering::Relaxed);
            }
        }
        p
    }
}

// SAFETY: every call forwards to `System` with the same layout; the counters have no effect on
// the memory handed out.
unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        Self::counted(System.alloc(layout), layout.size())
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        Self::counted(System.alloc_zeroed(layout), layout.size())
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout);
        Self::sub(layout.size());
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = System.realloc(ptr, layout, new_size);
        if !p.is_null() {
            Self::sub(layout.size());
            Self::add(new_size);
        }
        p
    }
}

/// Whether [`CountingAlloc`] is this program's global allocator (it has counted something).
pub fn installed() -> bool {
    INSTALLED.load(Ordering::Relaxed)
}

/// Runs `f` and returns its result with the peak bytes allocated above the level at the start
/// while it ran (`None` when the counting allocator is not installed).
pub fn measure_peak<R>(f: impl FnOnce() -> R) -> (R, Option<u64>) {
    let base = CURRENT.load(Ordering::Relaxed);
    PEAK.store(base, Ordering::Relaxed);
    let r = f();
    let peak = PEAK.load(Ordering::Relaxed).saturating_sub(base);
    (r, installed().then_some(peak as u64))
}
