//! Data-parallel loops of the float engine on the kernel pool (`muir::kernels::pool`, the threads
//! of [`super::set_threads`]). Every element is computed by one task, with the same operations
//! whichever thread runs it, so the results are the same bits for any thread count.

use muir::kernels::pool;

/// Elements below which a loop stays on the caller (a pool job costs microseconds).
const SMALL: usize = 1 << 13;

/// `f(start, chunk)` over consecutive chunks of `out` (`start`: the chunk's first index), each
/// a multiple of `grain` elements long but the last; split over the pool's threads when `out` is
/// long enough.
pub fn chunks(out: &mut [f32], grain: usize, f: &(dyn Fn(usize, &mut [f32]) + Sync)) {
    let threads = pool::threads();
    let grain = grain.max(1);
    let units = out.len().div_ceil(grain);
    if threads <= 1 || out.len() < SMALL || units < 2 {
        f(0, out);
        return;
    }
    let tasks = units.min(4 * threads);
    let per = units.div_ceil(tasks) * grain;
    let len = out.len();
    let p = pool::Shared(out.as_mut_ptr());
    pool::run(len.div_ceil(per), &|t| {
        let p = &p;
        let start = t * per;
        let n = per.min(len - start);
        // SAFETY: task t owns out[start .. start + n]; the tasks' ranges do not overlap and lie in
        // `out`, which outlives `run`.
        f(start, unsafe { p.slice(start, n) });
    });
}

/// `f(i)` for `i < n`, split over the pool's threads when `work` (a measure of the total, in
/// elements) is large enough. Each call must write only its own part of any output.
pub fn each(n: usize, work: usize, f: &(dyn Fn(usize) + Sync)) {
    if pool::threads() <= 1 || work < SMALL {
        (0..n).for_each(f);
    } else {
        pool::run(n, f);
    }
}
