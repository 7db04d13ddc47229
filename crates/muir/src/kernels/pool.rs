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
//!
//! [`beside`] runs two coarse streams of work side by side, one on the caller and one on a
//! worker (the engine's two encoders, and its refinement passes that run beside each other).
//! The worker's stream is posted in a slot of its own, which a worker takes or the caller takes
//! back, so that neither stream ever waits on one that no thread runs.
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
    /// [`beside`]'s other stream, posted for a worker to take (null: none). A slot of its own,
    /// not `job`: a worker takes it by swapping in null, its poster takes it back by swapping
    /// out its own address, and exactly one of them wins, whatever else is posted meanwhile.
    side: Line<AtomicPtr<Side>>,
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
        side: Line(AtomicPtr::new(core::ptr::null_mut())),
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

/// [`beside`]'s other stream as the pool's side slot holds it.
struct Side {
    /// Runs the stream (once: only the thread that takes it out of the slot calls this), catches
    /// its panic, releases the pool and sets `done` (lifetime erased: [`beside`] does not return
    /// before the stream is done or taken back).
    f: *const (dyn Fn() + Sync),
    /// The stream has returned or unwound: the last thing the thread that ran it does with this.
    done: AtomicBool,
    /// Run (or being run) by the caller, where it was never posted (see `Beside::take_back`).
    claimed: AtomicBool,
}

impl Side {
    fn run(&self) {
        // SAFETY: see `f`.
        let f = unsafe { &*self.f };
        f();
        self.done.store(true, Ordering::Release);
    }
}

/// What [`beside`]'s `mine` may ask about `other`.
pub struct Beside<'a> {
    side: &'a Side,
    /// Its address as posted in the pool's side slot; null where it was not posted (the pool
    /// not free: the caller runs it).
    posted: *mut Side,
    /// Releases the pool (once; see [`beside`]).
    release: &'a (dyn Fn() + Sync),
}

impl Beside<'_> {
    /// `other` has returned (or unwound).
    pub fn other_done(&self) -> bool {
        self.side.done.load(Ordering::Acquire)
    }

    /// Runs `other` on this thread, now, if no worker has taken it yet (the pool released first,
    /// so that its kernels have the workers); `false` if a worker has it.
    fn take_back(&self) -> bool {
        if self.posted.is_null() {
            if self.side.claimed.swap(true, Ordering::Relaxed) {
                return false;
            }
            self.side.run();
            return true;
        }
        if pool().side.compare_exchange(self.posted, core::ptr::null_mut(), Ordering::SeqCst, Ordering::SeqCst).is_err() {
            return false;
        }
        (self.release)();
        self.side.run();
        true
    }

    /// Waits until `ready()` or until `other` is done, whichever comes first: for `mine` to wait
    /// on something `other` does. Where no worker has taken `other` yet (the pool's workers busy
    /// with another caller's stream, or descheduled) it runs here, so the wait cannot hang.
    pub fn wait(&self, mut ready: impl FnMut() -> bool) {
        let mut waits = 0u32;
        while !ready() && !self.other_done() {
            if !self.take_back() {
                pause(&mut waits);
            }
        }
    }
}

/// Runs `other` on one of the pool's workers and `mine` on the caller, side by side, and returns
/// both results (`mine`'s first): for two streams of work that are split coarsely already (the
/// two image encoders, the refinement's passes beside each other, `engine::side`). While both
/// run, the pool is held: each one's kernels run on its own thread. When `other` is done first,
/// the pool is released and the caller's kernels get the worker back; when `mine` is, the caller
/// runs `other` itself if no worker has taken it yet (the pool released), else waits for it.
/// Where `mine` waits on `other`, it waits with [`Beside::wait`].
///
/// Why a worker rather than a new thread: a thread started for each pass waited 0.1-0.3 ms for
/// a core (the pool's worker spins on it for a while after its last job), started with cold
/// scratch, and left the worker asleep, to be woken when the caller's kernels needed it again.
///
/// `other` is posted in a slot of its own (the pool's `side`), which a worker takes or the caller
/// takes back, never both: `mine` never waits on a stream no thread runs. Where the pool is not
/// free (one thread, another caller's kernels or streams, backing off) both run here, `other`
/// after `mine`. A panic in either is resumed here once both are done (`other`'s as a new panic
/// where it ran on a worker).
pub fn beside<A: Send, B>(other: impl FnOnce() -> A + Send, mine: impl FnOnce(&Beside<'_>) -> B) -> (B, A) {
    let p = pool();
    let held = threads() >= 2 && INLINE_JOBS.load(Ordering::Relaxed) == 0 && !p.busy.swap(true, Ordering::Acquire);
    let released = AtomicBool::new(!held);
    let release = || {
        if !released.swap(true, Ordering::AcqRel) {
            p.busy.store(false, Ordering::Release);
        }
    };
    let slot = std::sync::Mutex::new(Some(other));
    let out = std::sync::Mutex::new(None);
    let panicked = AtomicBool::new(false);
    let task = || {
        let f = slot.lock().ok().and_then(|mut s| s.take());
        if let Some(f) = f {
            match std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)) {
                Ok(a) => {
                    if let Ok(mut o) = out.lock() {
                        *o = Some(a);
                    }
                }
                Err(_) => panicked.store(true, Ordering::Relaxed),
            }
        }
        release();
    };
    let task: &(dyn Fn() + Sync) = &task;
    // SAFETY (lifetime erasure): `side` and `task` outlive every use: this function returns only
    // once the stream is done, whichever thread ran it, also when `mine` panics.
    let f: *const (dyn Fn() + Sync) = unsafe { core::mem::transmute::<&(dyn Fn() + Sync), &'static (dyn Fn() + Sync)>(task) };
    let side = Side { f, done: AtomicBool::new(false), claimed: AtomicBool::new(false) };
    let posted = &side as *const Side as *mut Side;
    if held {
        // The slot is empty: only the pool's holder posts, and takes its stream back (or sees it
        // taken) before it releases the pool.
        p.side.store(posted, Ordering::SeqCst);
        if p.sleepers.load(Ordering::SeqCst) > 0 {
            let _g = p.lock.lock();
            p.wake.notify_all();
        }
    }
    let handle = Beside { side: &side, posted: if held { posted } else { core::ptr::null_mut() }, release: &release };
    let mine = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| mine(&handle)));
    if !handle.take_back() {
        // A worker has it (or this thread ran it already, in `Beside::wait`): wait until it is
        // done, the pool still held, so that its kernels run on its thread alone. (Split over
        // the pool, the encoders' short head rows ran slower on two threads than on one.)
        let mut waits = 0u32;
        while !side.done.load(Ordering::Acquire) {
            pause(&mut waits);
        }
    }
    let other = out.into_inner().ok().flatten();
    match (mine, other) {
        (Err(panic), _) => std::panic::resume_unwind(panic),
        (Ok(b), Some(a)) if !panicked.load(Ordering::Relaxed) => (b, a),
        _ => {
            #[allow(clippy::panic)] // a bug in `other`, not a consequence of input: report it here
            {
                panic!("a stream beside the caller panicked");
            }
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
    // Nothing new: no job posted since `seen`, no side stream posted.
    let idle = |seen: u64| p.epoch.load(Ordering::SeqCst) == seen && p.side.load(Ordering::SeqCst).is_null();
    loop {
        let mut spins = 0;
        while idle(seen) {
            if spins < SPINS {
                for _ in 0..64 {
                    std::hint::spin_loop();
                }
                spins += 1;
                continue;
            }
            // Sleep until the next job or side stream (counted first, then both rechecked under
            // the lock).
            let Ok(mut g) = p.lock.lock() else {
                return;
            };
            p.sleepers.fetch_add(1, Ordering::SeqCst);
            while idle(seen) {
                g = match p.wake.wait(g) {
                    Ok(g) => g,
                    Err(_) => return,
                };
            }
            p.sleepers.fetch_sub(1, Ordering::SeqCst);
        }
        let side = p.side.swap(core::ptr::null_mut(), Ordering::SeqCst);
        if !side.is_null() {
            // SAFETY: a posted side stream lives until its poster has taken it back or seen it
            // done; this worker took it out of the slot, so its poster waits for `done`.
            unsafe { &*side }.run();
            continue;
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

    /// Counts every task of a job of `n` tasks on the pool; `true` when each ran once.
    fn all_tasks_once(n: usize) -> bool {
        let hits: Vec<AtomicUsize> = (0..n).map(|_| AtomicUsize::new(0)).collect();
        run(n, &|i| {
            if let Some(h) = hits.get(i) {
                h.fetch_add(1, Ordering::Relaxed);
            }
        });
        hits.iter().all(|h| h.load(Ordering::Relaxed) == 1)
    }

    /// Busy work of about `us` microseconds.
    fn busy(us: u64) {
        let t = std::time::Instant::now();
        while t.elapsed() < std::time::Duration::from_micros(us) {
            std::hint::spin_loop();
        }
    }

    /// One round of every case of [`beside`]: either stream finishing first (the other's jobs
    /// then run with the finished one's help), `mine` waiting on `other` ([`Beside::wait`]), and
    /// `mine` ending before a worker could take `other`. `true` when both results came back and
    /// every job's tasks each ran once.
    fn beside_round(round: u64) -> bool {
        let (long, short) = (300 + 20 * (round % 5), 10);
        let (b, a) = beside(
            || {
                busy(long);
                (0..3).all(|_| all_tasks_once(33))
            },
            |_| (0..3).all(|_| all_tasks_once(17)),
        );
        let (d, c) = beside(
            || {
                busy(short);
                (0..3).all(|_| all_tasks_once(33))
            },
            |_| {
                busy(long);
                (0..3).all(|_| all_tasks_once(17))
            },
        );
        let (tx, rx) = std::sync::mpsc::channel();
        let (got, sent) = beside(
            move || {
                let _ = tx.send(round);
                busy(short);
                all_tasks_once(5)
            },
            |other| {
                let mut v = None;
                other.wait(|| {
                    v = rx.try_recv().ok();
                    v.is_some()
                });
                let ok = all_tasks_once(7);
                while !other.other_done() {
                    std::hint::spin_loop();
                }
                (v.or_else(|| rx.try_recv().ok()), ok)
            },
        );
        let (f, e) = beside(|| all_tasks_once(9), |_| 7);
        a && b && c && d && sent && got == (Some(round), true) && (f, e) == (7, true)
    }

    /// Every case of `beside` returns both results and runs every job once, a panic in either
    /// stream reaches the caller once both are done, and the pool works afterwards.
    #[test]
    fn beside_runs_both_streams_and_their_jobs() {
        set_threads(2);
        for round in 0..40 {
            assert!(beside_round(round), "round {round}");
        }
        let hook = std::panic::take_hook();
        std::panic::set_hook(Box::new(|_| {}));
        let other = std::panic::catch_unwind(|| beside(|| panic!("other"), |_| all_tasks_once(40)));
        let mine = std::panic::catch_unwind(|| beside(|| all_tasks_once(40), |_| -> bool { panic!("mine") }));
        std::panic::set_hook(hook);
        assert!(other.is_err() && mine.is_err());
        assert!(all_tasks_once(50));
        assert!(beside(|| all_tasks_once(10), |_| all_tasks_once(10)) == (true, true));
        set_threads(1);
    }

    /// Several callers at once, each with its pairs of streams and kernel jobs, while the thread
    /// count changes under them (as other tests of this process do): every round completes (no
    /// stream waits for a worker that never takes it) with every job run once. A hang fails the
    /// test after a minute rather than stopping the run.
    #[test]
    fn beside_from_several_callers_never_hangs() {
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            set_threads(3);
            let ok = std::thread::scope(|s| {
                let callers: Vec<_> = (0..3u64).map(|c| s.spawn(move || (0..60).all(|r| beside_round(c * 100 + r) && all_tasks_once(21)))).collect();
                let toggler = s.spawn(|| {
                    for i in 0..200 {
                        set_threads([3, 2, 1][i % 3]);
                        busy(200);
                    }
                    set_threads(2);
                });
                let ok = callers.into_iter().all(|h| h.join().unwrap_or(false));
                ok && toggler.join().is_ok()
            });
            set_threads(1);
            let _ = tx.send(ok);
        });
        assert_eq!(rx.recv_timeout(std::time::Duration::from_secs(60)), Ok(true));
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
