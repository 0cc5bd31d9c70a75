//! glibc `malloc` tuning for define-by-run tapes.
//!
//! A tape keeps every activation until it is dropped, then frees them all at once; the next
//! step allocates them again. With glibc's defaults, blocks above the (dynamic) mmap threshold
//! are fresh `mmap`s and a large free at the top of the heap is trimmed back to the kernel, so
//! each step page-faults and zeroes its whole working set again: on a 50-op chain over 1e6 f32
//! that was 60% of the time in the kernel and 5x a plain copy of the same bytes. On the first
//! [`crate::Tape`] this module fixes the mmap threshold at glibc's maximum (32 MiB, so smaller
//! blocks come from the heap and are reused) and the trim threshold at 1 GiB (freed memory up
//! to that much stays mapped for the next step), as `mallopt(3)` allows.
//!
//! Nothing is changed when the process already chose (`MALLOC_MMAP_THRESHOLD_`,
//! `MALLOC_TRIM_THRESHOLD_` or `GLIBC_TUNABLES` in the environment) or opts out with
//! `TAPESTRY_MALLOC_TUNING=0`; on other C libraries and platforms this is a no-op.

use std::sync::Once;

/// mmap threshold: glibc's largest allowed value on 64-bit targets.
const MMAP_THRESHOLD: i32 = 32 << 20;
/// Trim threshold: free memory kept mapped at the top of a heap.
const TRIM_THRESHOLD: i32 = 1 << 30;

static TUNE: Once = Once::new();

/// Applies the tuning once per process (see the module documentation). [`crate::Tape::new`]
/// calls it; entry points that allocate large buffers outside a tape (the rasterizer) do too.
pub fn tune() {
    TUNE.call_once(|| {
        let chosen = |k: &str| std::env::var_os(k).is_some();
        if chosen("MALLOC_MMAP_THRESHOLD_")
            || chosen("MALLOC_TRIM_THRESHOLD_")
            || chosen("GLIBC_TUNABLES")
            || std::env::var("TAPESTRY_MALLOC_TUNING").is_ok_and(|v| v == "0")
        {
            return;
        }
        apply();
    });
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn apply() {
    // SAFETY: mallopt only sets allocator parameters; it is thread-safe and takes no pointers.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD);
        libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn apply() {
    let _ = (MMAP_THRESHOLD, TRIM_THRESHOLD);
}
