//! Worker threads for the host kernels (feature `std`; a firmware build has none of this).
//!
//! [`run`] splits a kernel's work into numbered tasks that write disjoint parts of its output;
//! the calling thread and the workers take task numbers from one atomic counter until none are
//! left. Which thread computes a task never changes what it computes, so results are the same
//! integers for any thread count (the engine tests compare 1 and several).
//!
//! The pool is process-wide: [`set_threads`] (called by `Engine::set_threads`) sets how many
//! threads the kernels use, the caller included, and starts the workers that are missing. A
//! worker waits for the next job by spinning briefly (kernel calls come back to back within a
//! frame) and then sleeps on a condition variable; posting a job takes no lock unless a worker
//! sleeps. One job runs at a time: a caller that finds
//! the pool busy (another thread's kernel, or a nested call) runs its tasks itself.
#![deny(clippy::indexing_slicing)]

use std::sync::atomic::{AtomicBool, AtomicPtr, AtomicU32, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Condvar, Mutex, OnceLock};

/// Most threads (caller included).
pub const MAX_THREADS: usize = 64;

/// Spins (about a microsecond each) a worker waits for the next job before it sleeps. (2000
/// measured no better on an idle machine and burns a core another process may need.)
const SPINS: usize = 200;

/// Spins of the caller's wait for a worker's last task before it yields its core ([`pause`]).
const SPINS_BEFORE_YIELD: u32 = 4096;
/// Waits (the spins, then 2048 yields: a millisecond or more) after which a worker, if it also
/// took three times as long as the caller's share of the job, counts as descheduled ([`run`]).
const STALLED: u32 = SPINS_BEFORE_YIELD + 2048;
/// Jobs that then run on the caller alone before the pool is tried again (about a quarter of a
/// 450x375 frame's). With another process busy on one of two cores, Teddy took 0.63-0.83 s on two
/// threads without this against 0.53 s on one; with it, 0.53-0.55 s.
const BACK_OFF_JOBS: u32 = 4096;
/// Jobs left to run on the caller alone (see [`STALLED`]).
static INLINE_JOBS: AtomicU32 = AtomicU32::new(0);
/// Stalled jobs (see [`STALLED`]) within [`STALL_WINDOW`] of each other that make the pool back
/// off: one alone is no sign of a busy machine. On an idle machine a worker stalls about once a
/// frame: woken from its sleep after the encoders (a futex wake-up on a VM takes hundreds of
/// microseconds) or first touching a large buffer (the OS zeroes its pages); backing off then made
/// two-thirds of a 450x375 frame's jobs run on the caller alone.
const STALLS_TO_BACK_OFF: u32 = 3;
/// See [`STALLS_TO_BACK_OFF`].
const STALL_WINDOW: std::time::Duration = std::time::Duration::from_millis(50);
/// The process's stalls (see [`StallCount`]).
static STALLS: StallCount = StallCount { n: AtomicU32::new(0), last_ns: AtomicU64::new(0) };

/// Stalls counted in the current window, and when the last one happened.
struct StallCount {
    n: AtomicU32,
    /// Nanoseconds since the pool's first use.
    last_ns: AtomicU64,
}

impl StallCount {
    /// Counts a stall at `now_ns`; `true` when it is the [`STALLS_TO_BACK_OFF`]-th, each within
    /// [`STALL_WINDOW`] of the one before (the count then starts again).
    fn stall(&self, now_ns: u64) -> bool {
        let last = self.last_ns.swap(now_ns, Ordering::Relaxed);
        let n = if now_ns.saturating_sub(last) > STALL_WINDOW.as_nanos() as u64 { 1 } else { self.n.load(Ordering::Relaxed) + 1 };
        let back_off = n >= STALLS_TO_BACK_OFF;
        self.n.store(if back_off { 0 } else { n }, Ordering::Relaxed);
        back_off
    }
}

/// Threads the kernels use, the caller included.
static THREADS: AtomicUsize = AtomicUsize::new(1);

/// A job: `tasks` calls of `f`, each number taken once.
#[repr(align(128))]
struct Job {
    /// The tasks (lifetime erased: [`run`] does not return before no worker can reach it).
    f: *const (dyn Fn(usize) + Sync),
    tasks: usize,
    next: AtomicUsize,
    done: AtomicUsize,
    /// A task panicked on a worker.
    panicked: AtomicBool,
}

/// The pool's shared state. A job is posted by storing its address in `job` and bumping
/// `epoch`; a worker announces itself in `active` before it reads `job`, so a caller that has
/// unposted its job (`job` = null) and then sees `active` at 0 knows no worker holds it (all
/// sequentially consistent: a worker that increments `active` after the caller's check reads the
/// null). Workers spin on `epoch`, then sleep on `wake`; a caller takes the lock to notify only
/// when `sleepers` says someone sleeps (the same ordering argument: the worker counts itself and
/// then rechecks `epoch` under the lock).
struct Pool {
    job: Line<AtomicPtr<Job>>,
    epoch: Line<AtomicU64>,
    active: Line<AtomicUsize>,
    sleepers: Line<AtomicUsize>,
    lock: Mutex<()>,
    wake: Condvar,
    busy: AtomicBool,
    workers: Mutex<usize>,
}

/// A value on a cache line (pair) of its own: a worker polling `epoch` must not miss on every
/// write the caller makes to the pool's other fields.
#[repr(align(128))]
struct Line<T>(T);

impl<T> core::ops::Deref for Line<T> {
    type Target = T;
    fn deref(&self) -> &T {
        &self.0
    }
}

fn pool() -> &'static Pool {
    static P: OnceLock<Pool> = OnceLock::new();
    P.get_or_init(|| Pool {
        job: Line(AtomicPtr::new(core::ptr::null_mut())),
        epoch: Line(AtomicU64::new(0)),
        active: Line(AtomicUsize::new(0)),
        sleepers: Line(AtomicUsize::new(0)),
        lock: Mutex::new(()),
        wake: Condvar::new(),
        busy: AtomicBool::new(false),
        workers: Mutex::new(0),
    })
}

/// Sets the threads the kernels use (1 to [`MAX_THREADS`], the caller included) and starts the
/// missing workers. Workers are never stopped; with fewer threads set they sleep.
pub fn set_threads(n: usize) {
    let n = n.clamp(1, MAX_THREADS);
    let p = pool();
    if let Ok(mut w) = p.workers.lock() {
        while *w + 1 < n {
            if std::thread::Builder::new().name(format!("muir-kernel-{}", *w + 1)).spawn(worker).is_err() {
                break;
            }
            *w += 1;
        }
        THREADS.store(n.min(*w + 1), Ordering::Relaxed);
    }
}

/// Whether a [`run`] now would likely go to several threads: more than one set, the pool not
/// held or busy, not backing off. (A hint for how to split work; `run` decides again.)
pub fn free() -> bool {
    threads() > 1 && !pool().busy.load(Ordering::Relaxed) && INLINE_JOBS.load(Ordering::Relaxed) == 0
}

/// Threads the kernels use, the caller included.
pub fn threads() -> usize {
    THREADS.load(Ordering::Relaxed)
}

/// Runs `f(0) .. f(tasks - 1)`, on the pool's threads when there are several and the pool is
/// free, else on the caller; returns when all have run. Each task must write only its own part
/// of the output.
pub fn run(tasks: usize, f: &(dyn Fn(usize) + Sync)) {
    let p = pool();
    let backing_off = INLINE_JOBS.load(Ordering::Relaxed) > 0;
    if backing_off {
        INLINE_JOBS.fetch_sub(1, Ordering::Relaxed);
    }
    if tasks <= 1 || threads() <= 1 || backing_off || p.busy.swap(true, Ordering::Acquire) {
        (0..tasks).for_each(f);
        return;
    }
    // SAFETY (lifetime erasure): `job` and `f` outlive every use: this function waits until all
    // tasks are done and no worker holds the job before it returns.
    let f: *const (dyn Fn(usize) + Sync) = unsafe { core::mem::transmute::<&(dyn Fn(usize) + Sync), &'static (dyn Fn(usize) + Sync)>(f) };
    let job = Job { f, tasks, next: AtomicUsize::new(0), done: AtomicUsize::new(0), panicked: AtomicBool::new(false) };
    p.job.store(&job as *const Job as *mut Job, Ordering::SeqCst);
    p.epoch.fetch_add(1, Ordering::SeqCst);
    // A sleeping worker takes a while to wake: a slow job then is no stall (see `STALLED`).
    let woke = p.sleepers.load(Ordering::SeqCst) > 0;
    if woke {
        let _g = p.lock.lock();
        p.wake.notify_all();
    }
    let start = std::time::Instant::now();
    work(&job);
    let worked = start.elapsed();
    let mut waits = 0u32;
    while job.done.load(Ordering::Acquire) < tasks {
        pause(&mut waits);
    }
    // Unpost, then wait for the workers that may still hold it (see `Pool`).
    p.job.store(core::ptr::null_mut(), Ordering::SeqCst);
    while p.active.load(Ordering::SeqCst) != 0 {
        pause(&mut waits);
    }
    p.busy.store(false, Ordering::Release);
    if !woke && waits >= STALLED && start.elapsed() > 3 * worked && repeated_stall() {
        // A worker held its task far longer than the caller's own share took (and over a
        // millisecond), several times within a short while: the OS deschedules it (the cores
        // are busy with other processes). Waiting on it again would make the frame slower than
        // one thread, so the next jobs run on the caller alone. (Coarse jobs, e.g. the float
        // engine's halves of a product, wait long but not for longer than they worked.)
        INLINE_JOBS.store(BACK_OFF_JOBS, Ordering::Relaxed);
    }
    if job.panicked.load(Ordering::Relaxed) {
        #[allow(clippy::panic)] // a bug in a task, not a consequence of input: report it where it ran
        {
            panic!("a kernel task panicked on a worker thread");
        }
    }
}

/// Counts a stalled job now ([`StallCount::stall`]).
fn repeated_stall() -> bool {
    static EPOCH: OnceLock<std::time::Instant> = OnceLock::new();
    STALLS.stall(EPOCH.get_or_init(std::time::Instant::now).elapsed().as_nanos() as u64)
}

/// One step of the caller's wait for a worker's last task: a spin, and after a while a yield of
/// the core, so that a worker the OS has descheduled mid-task (a machine busy with other
/// processes) gets it back instead of waiting behind a spinning caller.
#[inline]
fn pause(waits: &mut u32) {
    *waits += 1;
    if *waits < SPINS_BEFORE_YIELD {
        std::hint::spin_loop();
    } else {
        std::thread::yield_now();
    }
}

/// Holds the pool until the returned guard is dropped, on any thread: meanwhile every [`run`]
/// runs its tasks on its caller. For work that is split coarsely already (the two image encoders
/// on two threads), whose threads the pool's workers would only compete with for the cores. The
/// encoders' pair hands the guard to the shorter of its two threads, so that the longer one's
/// kernels get the pool's workers back as soon as the other is done.
pub fn hold() -> Hold {
    Hold(!pool().busy.swap(true, Ordering::Acquire))
}

/// See [`hold`] (`true`: this guard set the pool busy and clears it when dropped).
pub struct Hold(bool);

impl Drop for Hold {
    fn drop(&mut self) {
        if self.0 {
            pool().busy.store(false, Ordering::Release);
        }
    }
}

/// Takes and runs task numbers until none are left.
fn work(job: &Job) {
    loop {
        let i = job.next.fetch_add(1, Ordering::Relaxed);
        if i >= job.tasks {
            return;
        }
        // SAFETY: `run` keeps `f` alive until every task is done.
        let f = unsafe { &*job.f };
        if std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| f(i))).is_err() {
            job.panicked.store(true, Ordering::Relaxed);
        }
        job.done.fetch_add(1, Ordering::Release);
    }
}

fn worker() {
    let p = pool();
    let mut seen = p.epoch.load(Ordering::SeqCst);
    loop {
        let mut spins = 0;
        while p.epoch.load(Ordering::SeqCst) == seen {
            if spins < SPINS {
                for _ in 0..64 {
                    std::hint::spin_loop();
                }
                spins += 1;
                continue;
            }
            // Sleep until the next job (counted first, then the epoch rechecked under the lock).
            let Ok(mut g) = p.lock.lock() else {
                return;
            };
            p.sleepers.fetch_add(1, Ordering::SeqCst);
            while p.epoch.load(Ordering::SeqCst) == seen {
                g = match p.wake.wait(g) {
                    Ok(g) => g,
                    Err(_) => return,
                };
            }
            p.sleepers.fetch_sub(1, Ordering::SeqCst);
        }
        seen = p.epoch.load(Ordering::SeqCst);
        p.active.fetch_add(1, Ordering::SeqCst);
        let job = p.job.load(Ordering::SeqCst);
        if !job.is_null() {
            // SAFETY: a posted job is alive until `run` unposts it and then sees `active` at 0;
            // this worker counted itself in `active` before reading the pointer.
            work(unsafe { &*job });
        }
        p.active.fetch_sub(1, Ordering::SeqCst);
    }
}

/// `v` grown to at least `n` elements (never shrunk), its first `n` as a slice (contents
/// unspecified): the host kernels' per-thread scratch.
pub fn scratch<T: Copy + Default>(v: &mut Vec<T>, n: usize) -> &mut [T] {
    if v.len() < n {
        v.resize(n, T::default());
    }
    v.get_mut(..n).unwrap_or_default()
}

/// Maps every page of a fresh, untouched allocation `v` (a large `vec![0; n]`: pages the OS
/// maps and zeroes on first touch) in one system call (Linux 5.14+ `MADV_POPULATE_WRITE`)
/// rather than one page fault per 4 KB as the first writes reach them: the attention's kept
/// softmax weights, 112 MB at 1242 x 375, took 28 000 faults. Only advice: where the call is
/// not available (an older kernel, another OS) nothing changes.
pub fn populate<T>(v: &mut [T]) {
    #[cfg(target_os = "linux")]
    {
        unsafe extern "C" {
            fn madvise(addr: *mut core::ffi::c_void, len: usize, advice: i32) -> i32;
        }
        const MADV_POPULATE_WRITE: i32 = 23;
        const PAGE: usize = 4096;
        let start = v.as_mut_ptr() as usize;
        let end = start.saturating_add(core::mem::size_of_val(v));
        let (a, b) = (start.next_multiple_of(PAGE), end / PAGE * PAGE);
        if b > a {
            // SAFETY: `a .. b` lies inside `v`'s allocation, page-aligned; populating writable
            // pages maps them (zeroed, as they read already) and changes no value.
            unsafe { madvise(a as *mut core::ffi::c_void, b - a, MADV_POPULATE_WRITE) };
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = v;
}

/// A raw pointer that tasks on several threads may hold; each task touches only its own
/// elements (the caller's guarantee).
#[derive(Clone, Copy)]
pub struct Shared<T>(pub *mut T);
// SAFETY: see the type's doc: tasks write disjoint elements.
unsafe impl<T> Sync for Shared<T> {}
// SAFETY: as above.
unsafe impl<T> Send for Shared<T> {}

impl<T> Shared<T> {
    /// Elements `at .. at + len`.
    ///
    /// # Safety
    /// They lie in the buffer, and no other task touches them while the slice lives.
    #[allow(clippy::mut_from_ref)]
    pub unsafe fn slice(&self, at: usize, len: usize) -> &mut [T] {
        // SAFETY: the caller's guarantee.
        unsafe { core::slice::from_raw_parts_mut(self.0.add(at), len) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_task_runs_once_for_any_thread_count() {
        for n in [1, 2, 3] {
            set_threads(n);
            for tasks in [0, 1, 2, 7, 100] {
                let hits: Vec<AtomicUsize> = (0..tasks).map(|_| AtomicUsize::new(0)).collect();
                run(tasks, &|i| {
                    if let Some(h) = hits.get(i) {
                        h.fetch_add(1, Ordering::Relaxed);
                    }
                });
                assert!(hits.iter().all(|h| h.load(Ordering::Relaxed) == 1), "{n} threads, {tasks} tasks");
            }
        }
        set_threads(1);
    }

    #[test]
    fn one_stall_is_no_back_off_but_repeated_ones_are() {
        let c = StallCount { n: AtomicU32::new(0), last_ns: AtomicU64::new(0) };
        let (ms, win) = (1_000_000u64, STALL_WINDOW.as_nanos() as u64);
        let t0 = 10 * win;
        // Within one window of each other: the third stall backs off and the count starts again.
        let within: Vec<bool> = (0..4).map(|i| c.stall(t0 + i * ms)).collect();
        assert_eq!(within, [false, false, true, false]);
        // A stall after a quiet window starts a new count: spread-out stalls never back off.
        let spread: Vec<bool> = (1..=5).map(|i| c.stall(t0 + i * (win + ms))).collect();
        assert_eq!(spread, [false; 5]);
        // Two close ones after a gap are two, not three.
        let t1 = t0 + 10 * win;
        assert_eq!([c.stall(t1), c.stall(t1 + ms), c.stall(t1 + 2 * ms)], [false, false, true]);
    }
}
