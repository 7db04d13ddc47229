//! A `static` that the firmware's `main` borrows mutably, once: the engine arena, the frames and
//! the output maps of every board's `src/bin/stereo.rs` (included there with `#[path]`). Zero-
//! initialised ones land in `.bss` (or the NOLOAD section a board places them in): no flash.

use core::cell::UnsafeCell;

pub struct Static<T>(UnsafeCell<T>);

// SAFETY: single core, no interrupt handler touches these; `take` hands out one borrow.
unsafe impl<T> Sync for Static<T> {}

impl<T> Static<T> {
    pub const fn new(value: T) -> Self {
        Self(UnsafeCell::new(value))
    }
    /// The cell's address, for volatile accesses that never form a reference (e.g. a marker
    /// a debugger or emulator plugin watches).
    #[allow(dead_code)] // the QEMU boards use it; the real boards do not
    pub const fn as_ptr(&self) -> *mut T {
        self.0.get()
    }
    /// # Safety
    /// At most once per static, and nothing else may access it afterwards.
    #[allow(clippy::mut_from_ref)]
    pub unsafe fn take(&'static self) -> &'static mut T {
        unsafe { &mut *self.0.get() }
    }
}
