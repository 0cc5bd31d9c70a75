//! Active waiting for a rayon pool's idle workers, the counterpart of OpenMP's
//! `OMP_WAIT_POLICY=active` / `KMP_BLOCKTIME`.
//!
//! A differentiable frame is a chain of short parallel regions (binning, the tile pass,
//! assembly, the loss, each backward) separated by short serial stretches (tape bookkeeping,
//! set-up, frees). rayon parks a worker that has found no work for a few dozen rounds (some
//! 20-40 us), and waking it again costs the kernel's and, on a VM, the hypervisor's wake-up
//! latency: measured on the 2-core development VM, a `join` of two 100 us halves after a serial
//! stretch of 40 us or more took 160-190 us instead of 100 us, the second half starting about
//! 30 us late and the joining thread waking about 30 us late in turn. With millisecond frames
//! and a dozen regions each, that is a tenth or more of the frame.
//!
//! [`ActiveWait`] keeps the other workers of the current pool busy-polling for work
//! ([`rayon::yield_now`]) while it lives, so that they steal a new region's jobs within a
//! microsecond. Each poller gives up after `max_idle` without work (then rayon's own parking
//! takes over again), and all of them stop when the guard is dropped. It changes only which
//! thread runs a job, when: results are the same bits as without it (the library's parallel
//! reductions do not depend on the thread that runs a task). The price is one core spinning
//! per idle worker during serial stretches, so use it around the work of a frame or a fitting
//! loop, not around a whole program that waits on I/O.
//!
//! ```
//! let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
//! let sum: u64 = pool.install(|| {
//!     let _hot = autodiff::ActiveWait::new();
//!     use rayon::prelude::*;
//!     (0..1000u64).into_par_iter().sum()
//! });
//! assert_eq!(sum, 499_500);
//! ```
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// While alive, the other workers of the current rayon pool poll for work instead of
/// parking (see the [module docs](self)). Create it inside the pool the work runs in
/// (`pool.install(|| { let _hot = ActiveWait::new(); ... })`); outside any pool it serves
/// rayon's global pool.
#[must_use = "the workers stop polling when the guard is dropped"]
pub struct ActiveWait {
    shared: Arc<Shared>,
}

struct Shared {
    stop: AtomicBool,
    polling: AtomicUsize,
}

impl ActiveWait {
    /// Idle time after which a polling worker gives up and lets rayon park it: longer than
    /// the serial stretches between a frame's parallel regions, short enough not to hold a
    /// core for long after the work has ended.
    pub const DEFAULT_MAX_IDLE: Duration = Duration::from_millis(2);

    /// Guard with [`Self::DEFAULT_MAX_IDLE`].
    pub fn new() -> Self {
        Self::with_max_idle(Self::DEFAULT_MAX_IDLE)
    }

    /// Guard whose pollers give up after `max_idle` without finding work.
    pub fn with_max_idle(max_idle: Duration) -> Self {
        let creator = rayon::current_thread_index();
        let n = rayon::current_num_threads();
        let shared = Arc::new(Shared {
            stop: AtomicBool::new(false),
            polling: AtomicUsize::new(n - usize::from(creator.is_some())),
        });
        // One job per worker, bound to that worker (a spawned job could be popped by the
        // creator itself while it idles, and the other workers would never see it).
        if shared.polling.load(Ordering::Relaxed) > 0 {
            let s = shared.clone();
            rayon::spawn_broadcast(move |ctx| {
                if Some(ctx.index()) != creator {
                    poll_until_idle(&s, max_idle);
                    s.polling.fetch_sub(1, Ordering::AcqRel);
                }
            });
        }
        ActiveWait { shared }
    }

    /// How many of this guard's pollers have not ended yet (queued or polling: one per
    /// worker other than the creating one; a poller ends when the guard is dropped or after
    /// `max_idle` without work).
    pub fn polling(&self) -> usize {
        self.shared.polling.load(Ordering::Acquire)
    }
}

impl Default for ActiveWait {
    fn default() -> Self {
        Self::new()
    }
}

impl Drop for ActiveWait {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::Release);
    }
}

/// One worker's polling loop: [`rayon::yield_now`] runs any job this worker finds (its own,
/// stolen or injected) until the guard is dropped or nothing turned up for `max_idle`.
fn poll_until_idle(shared: &Shared, max_idle: Duration) {
    let mut idle_since = Instant::now();
    while !shared.stop.load(Ordering::Acquire) {
        match rayon::yield_now() {
            Some(rayon::Yield::Executed) => idle_since = Instant::now(),
            // Let other runnable threads have the core (a no-op on an idle machine).
            Some(rayon::Yield::Idle) if idle_since.elapsed() < max_idle => std::thread::yield_now(),
            _ => break,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

    fn pool(n: usize) -> rayon::ThreadPool {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .unwrap()
    }

    /// Nested joins and parallel iterators inside the guard complete (no poller deadlocks the
    /// worker that created it) and give the same result as without it, for 1 to 4 threads.
    #[test]
    fn work_under_the_guard_completes_with_the_same_result() {
        let work = || -> f64 {
            (0..20_000u32)
                .into_par_iter()
                .with_min_len(64)
                .map(|i| {
                    let (a, b) = rayon::join(|| (i as f64).sqrt(), || (i as f64).ln_1p());
                    a * b
                })
                .sum::<f64>()
        };
        let plain = pool(1).install(work);
        for n in 1..=4 {
            let p = pool(n);
            for _ in 0..20 {
                let hot = p.install(|| {
                    let _hot = ActiveWait::new();
                    work()
                });
                // `sum` of f64 over a parallel iterator is reassociated by rayon's splits, so
                // compare with a tolerance here; the library's own reductions are fixed-order.
                assert!((hot - plain).abs() <= 1e-9 * plain.abs(), "{n} threads");
            }
        }
    }

    /// Wait up to 10 s for `cond`.
    fn eventually(cond: impl Fn() -> bool) -> bool {
        let t = Instant::now();
        while !cond() {
            if t.elapsed() > Duration::from_secs(10) {
                return false;
            }
            std::thread::sleep(Duration::from_micros(100));
        }
        true
    }

    /// The other worker polls while the guard lives and stops when it is dropped.
    #[test]
    fn pollers_stop_on_drop() {
        let p = pool(2);
        let hot = p.install(|| ActiveWait::with_max_idle(Duration::from_secs(60)));
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(hot.polling(), 1, "the other worker polls");
        let shared = hot.shared.clone();
        drop(hot);
        assert!(eventually(|| shared.polling.load(Ordering::Acquire) == 0));
    }

    /// Pollers give up after `max_idle` without work even while the guard lives.
    #[test]
    fn pollers_give_up_when_idle() {
        let p = pool(3);
        let hot = p.install(|| ActiveWait::with_max_idle(Duration::from_millis(1)));
        assert!(eventually(|| hot.polling() == 0));
        // and the pool still works
        assert_eq!(p.install(|| (0..100u64).into_par_iter().sum::<u64>()), 4950);
    }

    /// Outside any pool the guard serves the global pool and drops cleanly.
    #[test]
    fn outside_a_pool() {
        let _hot = ActiveWait::new();
        let s: u64 = (0..100u64).into_par_iter().sum();
        assert_eq!(s, 4950);
    }
}
