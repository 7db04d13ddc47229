//! Dot products with int8 weights on Helium, the M-profile Vector Extension of Armv8.1-M
//! (Cortex-M55/M85), feature `mve` (build with `-C target-cpu=cortex-m55`).
//!
//! A Q register holds eight 16-bit lanes. `VLDRB.S16` loads eight int8 weights and widens them
//! to 16 bits, `VLDRB.U16` / `VLDRB.S16` eight u8 / i8 activations; `VMLADAVA.S16` (written
//! `vmlava.s16`) multiplies the eight lane pairs and adds all eight products to a 32-bit general
//! register: eight MACs per instruction. Loops are low-overhead tail-predicated loops
//! (`DLSTP`/`LETP`): the last iteration runs with only the remaining lanes enabled (disabled lanes
//! are neither loaded nor added), so no scalar tail is needed for whole groups, and `LETP` resets
//! `FPSCR.LTPSIZE` to 4 on exit (no predication leaks into compiler-generated vector code).
//!
//! [`dot2x2_split`] (u8) and [`dot2x2_split_i16`] read the two patches of the split pair layout
//! (`Elem::SPLIT_PAIRS`: patch `a`'s values, then patch `b`'s) with contiguous write-back loads,
//! the tail included by predication: u8 activations sixteen to a vector as `x - 128` in i8 (13
//! instructions per 64 MACs; the `dsp` loop needs 40 per 32), i16 ones eight to a vector with
//! widening weight loads (9 instructions per 32 MACs). [`aggregate`] and [`dot_i16_i64`] are the
//! MGA attention's sums, [`copy`] the gather's row copies, [`requant4`] the convolution epilogue
//! on four output channels.
//!
//! The results are the same integers as the portable loops in `kernels`: every product is exact
//! in 32 bits and the accumulators are 32-bit, with the same bounds as there and in `dsp` (u8 and
//! i8 activations: `|w x| < 2^15`, fewer than 2^16 terms; i16 activations: chunks of at most
//! `kernels::I16_CHUNK` terms, `|w x| <= 2^22`, which the caller in `kernels` makes; the i16
//! pair loop [`dot2x2_split_i16`] accumulates in 64 bits instead), so no partial sum overflows
//! and the summation order does not matter. The QEMU firmware
//! `boards/qemu-mps3-m55` checks the whole frame against the host engine, and these functions
//! against the portable ones on the target
//! (`boards/qemu-mps3-m55/src/bin/kernels.rs`): the host cannot run them.
//!
//! Register constraints of the encodings: the widening loads take a low base register (r0-r7),
//! `VMLADAVA` an even destination register, hence the fixed registers below.

use core::arch::asm;

use crate::model::graph::MAX_PARTS;

/// An activation type with a Helium kernel.
pub trait Lanes: Copy + Into<i32> {
    /// `sum w[i] * x[i]` over `i < n`, `n >= 1`, `n <= w.len()`, `n <= x.len()`.
    ///
    /// # Safety
    /// The bounds above.
    unsafe fn dot_n(w: &[i8], x: &[Self], n: usize) -> i32;
}

impl Lanes for u8 {
    #[inline(always)]
    unsafe fn dot_n(w: &[i8], x: &[u8], n: usize) -> i32 {
        let mut acc = 0i32;
        // SAFETY: the loop reads `n` bytes of each slice (tail-predicated); registers as listed.
        unsafe {
            asm!(
                "dlstp.16 lr, {n}",
                "2:",
                "vldrb.u16 q0, [r1], #8",
                "vldrb.s16 q1, [r3], #8",
                "vmlava.s16 r0, q0, q1",
                "letp lr, 2b",
                n = in(reg) n,
                inout("r0") acc,
                inout("r1") x.as_ptr() => _,
                inout("r3") w.as_ptr() => _,
                out("lr") _,
                out("d0") _, out("d1") _, out("d2") _, out("d3") _,
                options(nostack, readonly),
            );
        }
        acc
    }
}

impl Lanes for i8 {
    #[inline(always)]
    unsafe fn dot_n(w: &[i8], x: &[i8], n: usize) -> i32 {
        let mut acc = 0i32;
        // SAFETY: as for u8; sixteen i8 x i8 products per `VMLADAVA.S8`.
        unsafe {
            asm!(
                "dlstp.8 lr, {n}",
                "2:",
                "vldrb.u8 q0, [{x}], #16",
                "vldrb.u8 q1, [{w}], #16",
                "vmlava.s8 r0, q0, q1",
                "letp lr, 2b",
                n = in(reg) n,
                inout("r0") acc,
                x = inout(reg) x.as_ptr() => _,
                w = inout(reg) w.as_ptr() => _,
                out("lr") _,
                out("d0") _, out("d1") _, out("d2") _, out("d3") _,
                options(nostack, readonly),
            );
        }
        acc
    }
}

impl Lanes for i16 {
    #[inline(always)]
    unsafe fn dot_n(w: &[i8], x: &[i16], n: usize) -> i32 {
        let mut acc = 0i32;
        // SAFETY: as for u8.
        unsafe {
            asm!(
                "dlstp.16 lr, {n}",
                "2:",
                "vldrh.u16 q0, [{x}], #16",
                "vldrb.s16 q1, [r3], #8",
                "vmlava.s16 r0, q0, q1",
                "letp lr, 2b",
                n = in(reg) n,
                inout("r0") acc,
                x = inout(reg) x.as_ptr() => _,
                inout("r3") w.as_ptr() => _,
                out("lr") _,
                out("d0") _, out("d1") _, out("d2") _, out("d3") _,
                options(nostack, readonly),
            );
        }
        acc
    }
}

/// `sum w[i] * x[i]` (int8 weights; u8, i8 or i16 activations). For i16 activations at most
/// `kernels::I16_CHUNK` terms (the caller chunks, see the module doc).
#[inline]
pub fn dot<T: Lanes>(w: &[i8], x: &[T]) -> i32 {
    let n = w.len().min(x.len());
    if n == 0 {
        return 0;
    }
    // SAFETY: 1 <= n <= both lengths.
    unsafe { T::dot_n(w, x, n) }
}

/// `sum q[i] * k[i]` over `min(q.len(), k.len())` i16 values, exact in 64 bits (the MGA logits):
/// `VMLALDAVA.S16` (written `vmlalva.s16`) adds eight products to a 64-bit pair of general
/// registers, so two loads and one instruction make eight MACs (tail-predicated loop).
#[inline]
pub fn dot_i16_i64(q: &[i16], k: &[i16]) -> i64 {
    let n = q.len().min(k.len());
    if n == 0 {
        return 0;
    }
    let (mut lo, mut hi) = (0u32, 0u32);
    // SAFETY: the loop reads `n` values of each slice (tail-predicated: disabled lanes are not
    // loaded); RdaLo/RdaHi must be an even/odd register pair, hence r0/r1.
    unsafe {
        asm!(
            "dlstp.16 lr, {n}",
            "2:",
            "vldrh.u16 q0, [{q}], #16",
            "vldrh.u16 q1, [{k}], #16",
            "vmlalva.s16 r0, r1, q0, q1",
            "letp lr, 2b",
            n = in(reg) n,
            q = inout(reg) q.as_ptr() => _,
            k = inout(reg) k.as_ptr() => _,
            inout("r0") lo,
            inout("r1") hi,
            out("lr") _,
            out("d0") _, out("d1") _, out("d2") _, out("d3") _,
            options(nostack, readonly),
        );
    }
    ((hi as u64) << 32 | lo as u64) as i64
}

/// The MGA logits of one query of 32 values against a block of keys, less the query's maximum:
/// `e[j] = q . k_j - max` for the `nb = min(kb.len() / 32, e.len())` keys `k_j = kb[32 j ..]`, each
/// exact in 64 bits (`VMLALDAVA.S16`) and checked to fit in i32. The query stays in four vector
/// registers for the whole block: per key four loads, four `VMLALDAVA`, the 64-bit subtraction,
/// the i32 test and the store (14 instructions; `dot_i16_i64` per key took about 26 with its
/// call). Returns `Some(nb)`, or `None` (with `e` partly written) when `q` is not 32 values long,
/// there is no key, or some difference does not fit in i32.
#[inline]
pub fn logits32(q: &[i16], kb: &[i16], max: i64, e: &mut [i32]) -> Option<usize> {
    let nb = (kb.len() / 32).min(e.len());
    if q.len() != 32 || nb == 0 {
        return None;
    }
    let bad: u32;
    // SAFETY: reads the 32 values of `q` and `32 nb <= kb.len()` values of `kb`, writes `nb <=
    // e.len()` values of `e`; the sums in the even/odd pair r0/r1 (`VMLALDAVA`).
    unsafe {
        asm!(
            "vldrw.u32 q4, [{q}]",
            "vldrw.u32 q5, [{q}, #16]",
            "vldrw.u32 q6, [{q}, #32]",
            "vldrw.u32 q7, [{q}, #48]",
            "mov.w {bad}, #0",
            "dls lr, {n}",
            "2:",
            "vldrh.u16 q0, [{k}], #16",
            "vldrh.u16 q1, [{k}], #16",
            "vldrh.u16 q2, [{k}], #16",
            "vldrh.u16 q3, [{k}], #16",
            "vmlaldav.s16 r0, r1, q0, q4",
            "vmlaldava.s16 r0, r1, q1, q5",
            "vmlaldava.s16 r0, r1, q2, q6",
            "vmlaldava.s16 r0, r1, q3, q7",
            "subs.w r0, r0, {mlo}",
            "sbc.w r1, r1, {mhi}",
            "eor.w r1, r1, r0, asr #31",
            "orr.w {bad}, {bad}, r1",
            "str r0, [{e}], #4",
            "le lr, 2b",
            q = in(reg) q.as_ptr(),
            k = inout(reg) kb.as_ptr() => _,
            e = inout(reg) e.as_mut_ptr() => _,
            n = in(reg) nb,
            mlo = in(reg) max as u32,
            mhi = in(reg) (max >> 32) as u32,
            bad = out(reg) bad,
            out("r0") _,
            out("r1") _,
            out("lr") _,
            out("d0") _, out("d1") _, out("d2") _, out("d3") _, out("d4") _, out("d5") _, out("d6") _, out("d7") _,
            out("d8") _, out("d9") _, out("d10") _, out("d11") _, out("d12") _, out("d13") _, out("d14") _, out("d15") _,
            options(nostack),
        );
    }
    (bad == 0).then_some(nb)
}

/// The MGA value sums of one block of keys: `acc[ch] += sum_j e[j] * v[j * cv + ch]` for every
/// `ch < acc.len()` and key `j < e.len()` (`v` key-major, `cv` values per key; the softmax
/// weights `e` are `0..=32768`). Lanes run over four keys: a gather load (`VLDRH.S32` with the
/// offsets `j cv`) picks one channel of four keys, `VMLALDAVA.S32` adds the four products
/// `e_j v_j` to that channel's 64-bit sum in two general registers; four channels per pass
/// (`muir_mve_aggregate4`, 11 instructions per 16 MACs), then two (inline, 7 per 8) share the
/// weights' load and the offsets' step. Exact, so the same integers as the portable loop.
/// Channels the slices do not cover are left as they are (the engine's always are).
pub fn aggregate(e: &[i32], v: &[i16], cv: usize, acc: &mut [i64]) {
    let nb = e.len();
    let chans = acc.len().min(cv);
    // Every read below is `v[j cv + ch]` for `j < nb`, `ch < chans`.
    if nb == 0 || chans == 0 || v.len() < (nb - 1) * cv + chans || cv > (u32::MAX / 8) as usize {
        return;
    }
    let offs: [u32; 4] = [0, cv as u32, 2 * cv as u32, 3 * cv as u32];
    let step = 4 * cv as u32;
    let mut ch = 0;
    // Four channels per pass (`muir_mve_aggregate4`: one weight load for four gathers).
    while ch + 4 <= chans {
        if let Some(a) = acc.get_mut(ch..ch + 4) {
            let args = Agg4Args { e: e.as_ptr(), base: v.as_ptr().wrapping_add(ch), nb, offs: offs.as_ptr(), step, acc: a.as_mut_ptr() };
            // SAFETY: `nb` lanes (tail-predicated) of `e`, gathers of `v[j cv + ch + i]` for
            // `j < nb`, `i < 4` only, inside `v` by the check above since `ch + 3 < chans`; it
            // adds to the four sums at `a`.
            unsafe { muir_mve_aggregate4(&args) };
        }
        ch += 4;
    }
    while ch + 2 <= chans {
        let (mut l0, mut h0, mut l1, mut h1) = (0u32, 0u32, 0u32, 0u32);
        // SAFETY: `nb` lanes (tail-predicated) of `e`, and gathers of `v[j cv + ch]` and
        // `v[j cv + ch + 1]` for `j < nb` only (disabled lanes are not loaded), inside `v` by the
        // check above since `ch + 1 < chans`. RdaLo/RdaHi pairs: even/odd registers.
        unsafe {
            let b0 = v.as_ptr().add(ch);
            asm!(
                "vldrw.u32 q3, [{offs}]",
                "dlstp.32 lr, {nb}",
                "2:",
                "vldrw.u32 q0, [{e}], #16",
                "vldrh.s32 q1, [{b0}, q3, uxtw #1]",
                "vldrh.s32 q2, [{b1}, q3, uxtw #1]",
                "vmlalva.s32 r0, r1, q0, q1",
                "vmlalva.s32 r2, r3, q0, q2",
                "vadd.i32 q3, q3, {step}",
                "letp lr, 2b",
                offs = in(reg) offs.as_ptr(),
                nb = in(reg) nb,
                e = inout(reg) e.as_ptr() => _,
                b0 = in(reg) b0,
                b1 = in(reg) b0.add(1),
                step = in(reg) step,
                inout("r0") l0,
                inout("r1") h0,
                inout("r2") l1,
                inout("r3") h1,
                out("lr") _,
                out("d0") _, out("d1") _, out("d2") _, out("d3") _, out("d4") _, out("d5") _,
                out("d6") _, out("d7") _,
                options(nostack, readonly),
            );
        }
        if let Some([a0, a1]) = acc.get_mut(ch..ch + 2).and_then(|a| <&mut [i64; 2]>::try_from(a).ok()) {
            *a0 += ((h0 as u64) << 32 | l0 as u64) as i64;
            *a1 += ((h1 as u64) << 32 | l1 as u64) as i64;
        }
        ch += 2;
    }
    if ch < chans {
        // An odd last channel: the portable sum.
        let s: i64 = e.iter().zip(v.iter().skip(ch).step_by(cv)).map(|(w, x)| *w as i64 * *x as i64).sum();
        if let Some(a) = acc.get_mut(ch) {
            *a += s;
        }
    }
}

/// u8 activations sixteen at a time: each flipped to `x - 128` in i8 (`VEOR` with 0x80) so that
/// `VMLADAVA.S8` multiplies sixteen signed byte pairs per instruction, and
/// `w . x = w . (x - 128) + 128 sum(w)` with `VADDVA.S8` summing the weights in the same pass.
/// Per 64 MACs two activation loads, two flips, two weight loads, two weight sums, four
/// `VMLADAVA` and `LETP` (13 instructions; eight activations per vector took 18). Exact: `|w (x - 128)| <= 2^14`,
/// `|sum(w)| <= 2^7 n` and the result `|w . x| < 2^15 n` stay in i32 for `n < 2^16` (the u8
/// bound of the module doc).
///
/// # Safety
/// `n >= 1`, `n <= w0.len()`, `n <= w1.len()`, `n <= a.len()`, `n <= b.len()`.
#[inline(always)]
unsafe fn dot2x2_u8_n(w0: &[i8], w1: &[i8], a: &[u8], b: &[u8], n: usize) -> [i32; 4] {
    let [mut s0, mut s1, mut s2, mut s3] = [0i32; 4];
    let (mut sw0, mut sw1) = (0i32, 0i32);
    // SAFETY: `n` lanes (tail-predicated: disabled lanes are not loaded, flipped lanes of
    // them are not added) of each slice, inside them by the caller's bounds; the sums in even
    // registers (`VMLADAVA`, `VADDVA`), q3 the flip mask, set before the loop.
    unsafe {
        asm!(
            "vmov.i8 q3, #0x80",
            "dlstp.8 lr, {n}",
            "2:",
            "vldrb.u8 q0, [{a}], #16",
            "vldrb.u8 q1, [{b}], #16",
            "veor q0, q0, q3",
            "veor q1, q1, q3",
            "vldrb.u8 q2, [{w0}], #16",
            "vaddva.s8 r0, q2",
            "vmlava.s8 r4, q0, q2",
            "vmlava.s8 r8, q1, q2",
            "vldrb.u8 q2, [{w1}], #16",
            "vaddva.s8 r2, q2",
            "vmlava.s8 r10, q0, q2",
            "vmlava.s8 r12, q1, q2",
            "letp lr, 2b",
            n = in(reg) n,
            a = inout(reg) a.as_ptr() => _,
            b = inout(reg) b.as_ptr() => _,
            w0 = inout(reg) w0.as_ptr() => _,
            w1 = inout(reg) w1.as_ptr() => _,
            inout("r0") sw0,
            inout("r2") sw1,
            inout("r4") s0,
            inout("r10") s1,
            inout("r8") s2,
            inout("r12") s3,
            out("lr") _,
            out("d0") _, out("d1") _, out("d2") _, out("d3") _, out("d4") _, out("d5") _, out("d6") _, out("d7") _,
            options(nostack, readonly),
        );
    }
    let (c0, c1) = (sw0.wrapping_mul(128), sw1.wrapping_mul(128));
    [s0.wrapping_add(c0), s1.wrapping_add(c1), s2.wrapping_add(c0), s3.wrapping_add(c1)]
}

/// Four dot products, two output channels at two output pixels, with the two u8 patches side by
/// side (the Helium pair layout, `kernels::pair_index`: patch `a` then patch `b`):
/// `[w0 . a, w1 . a, w0 . b, w1 . b]` over `n = min` of the lengths, by the loop above:
/// contiguous loads with write-back, tail-predicated, no scalar tail. (i16 patches:
/// [`dot2x2_split_i16`].)
#[inline]
pub fn dot2x2_split(w0: &[i8], w1: &[i8], a: &[u8], b: &[u8]) -> [i32; 4] {
    let n = w0.len().min(w1.len()).min(a.len()).min(b.len());
    if n == 0 {
        return [0; 4];
    }
    // SAFETY: 1 <= n <= every length.
    unsafe { dot2x2_u8_n(w0, w1, a, b, n) }
}

/// The arguments of `muir_mve_aggregate4`.
#[repr(C)]
struct Agg4Args {
    e: *const i32,
    base: *const i16,
    nb: usize,
    offs: *const u32,
    step: u32,
    acc: *mut i64,
}

core::arch::global_asm!(
    ".syntax unified",
    ".thumb",
    ".cpu cortex-m55",
    ".section .text.muir_mve_aggregate4,\"ax\",%progbits",
    ".global muir_mve_aggregate4",
    ".type muir_mve_aggregate4,%function",
    ".p2align 2",
    ".thumb_func",
    // r0 = &Agg4Args. [`aggregate`]'s loop for four channels: the weights of four keys (r10),
    // gathers of one channel of the four keys from bases r6, r7, r11, r12 (channels ch .. ch + 3)
    // at the offsets q3 (stepped by q4), 64-bit sums r0:r1, r2:r3, r4:r5, r8:r9 added to acc.
    "muir_mve_aggregate4:",
    "    push {{r4-r11, lr}}",
    "    vpush {{d8-d9}}",
    "    ldr.w r10, [r0]",
    "    ldr r6, [r0, #4]",
    "    ldr.w lr, [r0, #8]",
    "    ldr r1, [r0, #12]",
    "    vldrw.u32 q3, [r1]",
    "    ldr r1, [r0, #16]",
    "    vdup.32 q4, r1",
    "    str r0, [sp, #-8]!",
    "    adds r7, r6, #2",
    "    add.w r11, r6, #4",
    "    add.w r12, r6, #6",
    "    movs r0, #0",
    "    movs r1, #0",
    "    movs r2, #0",
    "    movs r3, #0",
    "    movs r4, #0",
    "    movs r5, #0",
    "    mov.w r8, #0",
    "    mov.w r9, #0",
    "    dlstp.32 lr, lr",
    "2:",
    "    vldrw.u32 q0, [r10], #16",
    "    vldrh.s32 q1, [r6, q3, uxtw #1]",
    "    vldrh.s32 q2, [r7, q3, uxtw #1]",
    "    vmlalva.s32 r0, r1, q0, q1",
    "    vmlalva.s32 r2, r3, q0, q2",
    "    vldrh.s32 q1, [r11, q3, uxtw #1]",
    "    vldrh.s32 q2, [r12, q3, uxtw #1]",
    "    vmlalva.s32 r4, r5, q0, q1",
    "    vmlalva.s32 r8, r9, q0, q2",
    "    vadd.i32 q3, q3, q4",
    "    letp lr, 2b",
    "    ldr r12, [sp], #8",
    "    ldr.w r12, [r12, #20]",
    "    ldrd r6, r7, [r12]",
    "    adds r6, r6, r0",
    "    adcs r7, r1",
    "    strd r6, r7, [r12]",
    "    ldrd r6, r7, [r12, #8]",
    "    adds r6, r6, r2",
    "    adcs r7, r3",
    "    strd r6, r7, [r12, #8]",
    "    ldrd r6, r7, [r12, #16]",
    "    adds r6, r6, r4",
    "    adcs r7, r5",
    "    strd r6, r7, [r12, #16]",
    "    ldrd r6, r7, [r12, #24]",
    "    adds.w r6, r6, r8",
    "    adc.w r7, r7, r9",
    "    strd r6, r7, [r12, #24]",
    "    vpop {{d8-d9}}",
    "    pop {{r4-r11, pc}}",
    ".size muir_mve_aggregate4, . - muir_mve_aggregate4",
);

unsafe extern "C" {
    fn muir_mve_aggregate4(args: *const Agg4Args);
}

/// `dst[..n] = src[..n]` for `n = min` of the lengths, sixteen bytes per load/store pair in a
/// tail-predicated loop (3 instructions per 16 bytes; the library `memcpy` the compiler calls
/// for `copy_from_slice` needs about 17 per 8 on these short runs). For plain-data `T` only
/// (the activation types: every byte pattern valid, no padding).
#[inline]
pub fn copy<T: Copy>(dst: &mut [T], src: &[T]) {
    let bytes = dst.len().min(src.len()) * core::mem::size_of::<T>();
    if bytes == 0 {
        return;
    }
    // SAFETY: `bytes` bytes of each slice (tail-predicated: disabled lanes are neither loaded nor
    // stored); the slices cannot overlap (one is borrowed mutably).
    unsafe {
        asm!(
            "dlstp.8 lr, {n}",
            "2:",
            "vldrb.u8 q0, [{s}], #16",
            "vstrb.8 q0, [{d}], #16",
            "letp lr, 2b",
            n = in(reg) bytes,
            s = inout(reg) src.as_ptr() => _,
            d = inout(reg) dst.as_mut_ptr() => _,
            out("lr") _,
            out("d0") _, out("d1") _,
            options(nostack),
        );
    }
}

/// `dst` set to all-one bits (`u16::MAX`; every value initialised), sixteen bytes a store,
/// tail-predicated (the path steps' windows, `fullres::path_step`: `[u16::MAX; N]` became a
/// `memset` call of about 40 instructions).
#[inline]
pub fn fill_ones(dst: &mut [core::mem::MaybeUninit<u16>]) {
    // SAFETY: every bit pattern is an initialised `u16`.
    unsafe { fill_bytes::<0xff, _>(dst) }
}

/// `dst` set to all-zero bytes (the value 0 of the kernels' element types), sixteen bytes a
/// store, tail-predicated: `fill(0)` of a few dozen bytes became a byte-wise `__aeabi_memclr` call
/// of about 170 instructions (the patches' padding columns, `conv::gather_part`).
#[inline]
pub fn zero<T: crate::kernels::Elem>(dst: &mut [T]) {
    // SAFETY: every `Elem` (u8, i8, i16) is 0 when all its bytes are.
    unsafe { fill_bytes::<0, _>(dst) }
}

/// Every byte of `dst` set to `B`, sixteen bytes a store, tail-predicated ([`fill_ones`],
/// [`zero`]).
///
/// # Safety
/// Bytes `B` must make a valid `T`.
#[inline(always)]
unsafe fn fill_bytes<const B: u8, T>(dst: &mut [T]) {
    let bytes = core::mem::size_of_val(dst);
    if bytes == 0 {
        return;
    }
    // SAFETY: `bytes` bytes of `dst` (tail-predicated: disabled lanes are not stored).
    unsafe {
        asm!(
            "vmov.i8 q0, #{b}",
            "dlstp.8 lr, {n}",
            "2:",
            "vstrb.8 q0, [{d}], #16",
            "letp lr, 2b",
            b = const B,
            n = in(reg) bytes,
            d = inout(reg) dst.as_mut_ptr() => _,
            out("lr") _,
            out("d0") _, out("d1") _,
            options(nostack),
        );
    }
}

/// The four products of the split pair layout for i16 activations over a whole part of any
/// length, in one call and without chunks: `VMLALDAVA.S16` adds each vector's eight products into
/// a 64-bit register pair, so the sums are exact for any `n` (below `2^41` terms). A standalone
/// function (`muir_mve_dot2x2_i16`): four 64-bit sums, four pointers and the loop counter need
/// r0-r12 and lr, two more registers than inline assembly may take (r6, r7). Per 32 MACs two
/// activation loads, two widening weight loads, four `VMLALDAVA` and `LETP` (9 instructions);
/// the 508-term chunks it needed before (each with its call and four 64-bit adds) were 5 % of the
/// Cortex-M55 frame.
#[inline]
pub fn dot2x2_split_i16(w0: &[i8], w1: &[i8], a: &[i16], b: &[i16]) -> [i64; 4] {
    let n = w0.len().min(w1.len()).min(a.len()).min(b.len());
    let mut acc = [0i64; 4];
    if n > 0 {
        // SAFETY: the loop reads `n` values of each slice (tail-predicated), `n <=` every length;
        // it writes the four sums to `acc`.
        unsafe { muir_mve_dot2x2_i16(a.as_ptr(), b.as_ptr(), w0.as_ptr(), w1.as_ptr(), n, &mut acc) };
    }
    acc
}

/// One vector step of the i16 two-by-two products (`muir_mve_dot2x2_i16`, `muir_mve_dots_i16`):
/// eight activations of each pixel (r6, r7), eight widened weights of each channel (r4, r5) into
/// the four 64-bit sums r0:r1, r2:r3, r8:r9, r10:r11. Shared text for `global_asm!` (a Rust macro,
/// not an assembler `.macro`: blocks may be assembled in different codegen units).
macro_rules! dot2x2_i16_vec {
    () => {
        concat!(
            "    vldrh.u16 q0, [r6], #16\n",
            "    vldrh.u16 q1, [r7], #16\n",
            "    vldrb.s16 q2, [r4], #8\n",
            "    vmlaldava.s16 r0, r1, q0, q2\n",
            "    vmlaldava.s16 r2, r3, q1, q2\n",
            "    vldrb.s16 q2, [r5], #8\n",
            "    vmlaldava.s16 r8, r9, q0, q2\n",
            "    vmlaldava.s16 r10, r11, q1, q2\n",
        )
    };
}

/// One vector step of `muir_mve_dots_s8_1`: sixteen bytes of each pixel (r7, r9), each
/// channel's weights (r1, r3, r5) into its two sums (the unrolled and the tail-predicated loops).
macro_rules! dots_s8_1_vec {
    () => {
        concat!(
            "    vldrb.u8 q0, [r7], #16\n",
            "    vldrb.u8 q1, [r9], #16\n",
            "    vldrb.u8 q2, [r1], #16\n",
            "    vmladava.s8 r0, q0, q2\n",
            "    vmladava.s8 r6, q1, q2\n",
            "    vldrb.u8 q2, [r3], #16\n",
            "    vmladava.s8 r2, q0, q2\n",
            "    vmladava.s8 r8, q1, q2\n",
            "    vldrb.u8 q2, [r5], #16\n",
            "    vmladava.s8 r4, q0, q2\n",
            "    vmladava.s8 r10, q1, q2\n",
        )
    };
}

core::arch::global_asm!(
    ".syntax unified",
    ".thumb",
    // Module-level assembly does not see `-C target-cpu`: enable Helium's integer instructions.
    ".cpu cortex-m55",
    ".section .text.muir_mve_dot2x2_i16,\"ax\",%progbits",
    ".global muir_mve_dot2x2_i16",
    ".type muir_mve_dot2x2_i16,%function",
    ".p2align 2",
    ".thumb_func",
    // r0 = a, r1 = b, r2 = w0, r3 = w1, [sp] = n, [sp + 4] = out. Sums: w0.a in r0:r1, w0.b in
    // r2:r3, w1.a in r8:r9, w1.b in r10:r11 (even/odd pairs, as VMLALDAVA takes them); the
    // widening weight loads need low base registers (r4, r5), the activations run in r6, r7.
    "muir_mve_dot2x2_i16:",
    "    push {{r4-r11, lr}}",
    "    ldr r12, [sp, #36]",
    "    mov r6, r0",
    "    mov r7, r1",
    "    mov r4, r2",
    "    mov r5, r3",
    "    movs r0, #0",
    "    movs r1, #0",
    "    movs r2, #0",
    "    movs r3, #0",
    "    mov.w r8, #0",
    "    mov.w r9, #0",
    "    mov.w r10, #0",
    "    mov.w r11, #0",
    "    dlstp.16 lr, r12",
    "1:",
    dot2x2_i16_vec!(),
    "    letp lr, 1b",
    "    ldr r12, [sp, #40]",
    "    strd r0, r1, [r12]",
    "    strd r8, r9, [r12, #8]",
    "    strd r2, r3, [r12, #16]",
    "    strd r10, r11, [r12, #24]",
    "    pop {{r4-r11, pc}}",
    ".size muir_mve_dot2x2_i16, . - muir_mve_dot2x2_i16",
);

unsafe extern "C" {
    fn muir_mve_dot2x2_i16(a: *const i16, b: *const i16, w0: *const i8, w1: *const i8, n: usize, out: *mut [i64; 4]);
}

/// The part lengths of an i16 layer for [`PartLens::dots4`] (each `ch k k`, at least 1), checked
/// once per layer: at most `MAX_PARTS` parts summing to the patch length `kl`.
#[derive(Clone, Copy, Debug)]
pub struct PartLens {
    lens: [u32; MAX_PARTS],
    np: usize,
    kl: usize,
}

/// The arguments of `muir_mve_dots_i16`, which advances `a`, `w0`, `lens` and `out` part by part
/// (`zero`: eight zero words, loaded into the sums by one `LDM` per part).
#[repr(C)]
struct DotsArgs {
    zero: [u32; 8],
    a: *const i16,
    w0: *const i8,
    kl: usize,
    lens: *const u32,
    np: usize,
    out: *mut i32,
}

impl PartLens {
    /// The lengths `lens` (one per part) of a patch of `kl` values, or `None` where a length is
    /// 0, there are no or more than `MAX_PARTS` parts, they do not sum to `kl`, or `kl` reaches
    /// `2^26` (far beyond any layer; the byte offsets stay in `u32`).
    pub fn new(lens: impl Iterator<Item = usize>, kl: usize) -> Option<PartLens> {
        let mut l = PartLens { lens: [0; MAX_PARTS], np: 0, kl };
        let mut sum = 0usize;
        for n in lens {
            if n == 0 || kl >= 1 << 26 {
                return None;
            }
            *l.lens.get_mut(l.np)? = n as u32;
            l.np += 1;
            sum += n;
        }
        (l.np > 0 && sum == kl).then_some(l)
    }

    /// The i32 dot products of a block of four output channels at two pixels, part by part:
    /// `d[8 p + c] = w_c . a_p` and `d[8 p + 4 + c] = w_c . b_p` for channel `c < 4` (weight row
    /// `c` of `w`, `kl` values each, part `p` at offset `o_p`, the sum of the lengths before
    /// it) and part `p`'s pair block at `2 o_p` of `pair` (patch `a_p`, then `b_p`, the split
    /// pair layout). One call per channel pair for all parts (`muir_mve_dots_i16`: the
    /// [`dot2x2_split_i16`] loop, 64-bit sums, each checked to fit in i32 and stored as i32).
    /// Returns false, with `d` partly written, when a sum does not fit in i32 or `w` or `pair`
    /// is shorter than `4 kl` and `2 kl`.
    #[inline]
    pub fn dots4(&self, w: &[i8], pair: &[i16], d: &mut [i32; 8 * MAX_PARTS]) -> bool {
        let kl = self.kl;
        if w.len() < 4 * kl || pair.len() < 2 * kl {
            return false;
        }
        let mut bad = 0;
        for j in 0..2 {
            let mut args = DotsArgs {
                zero: [0; 8],
                a: pair.as_ptr(),
                w0: w.as_ptr().wrapping_add(2 * j * kl),
                kl,
                lens: self.lens.as_ptr(),
                np: self.np,
                out: d.as_mut_ptr().wrapping_add(2 * j),
            };
            // SAFETY: part `p` reads `lens[p] >= 1` values at `2 o_p` and `2 o_p + lens[p]` of
            // `pair` and at `o_p` of weight rows `2j` and `2j + 1` (`2 j kl + o_p`, `+ kl`), all
            // inside the slices since the lengths sum to `kl` (`PartLens::new`) and the lengths
            // were checked above; it writes `d[8 p + 2 j + {0, 1, 4, 5}]`, inside `d` for
            // `p < np <= MAX_PARTS`, `j < 2`.
            bad |= unsafe { muir_mve_dots_i16(&mut args) };
        }
        bad == 0
    }
}

core::arch::global_asm!(
    ".syntax unified",
    ".thumb",
    ".cpu cortex-m55",
    ".section .text.muir_mve_dots_i16,\"ax\",%progbits",
    ".global muir_mve_dots_i16",
    ".type muir_mve_dots_i16,%function",
    ".p2align 2",
    ".thumb_func",
    // r0 = &mut DotsArgs (kept in r12). Per part: the sums cleared by one LDM of `zero`, the loop
    // of `muir_mve_dot2x2_i16` (sums w0.a r0:r1, w0.b r2:r3, w1.a r8:r9, w1.b r10:r11; weights r4,
    // r5; activations r6, r7; LR the part's length, then the loop count), then the four low words
    // stored, and each high word XOR the low word's sign (zero when the sum fits in i32) ORed into
    // [sp]; returns that OR.
    "muir_mve_dots_i16:",
    "    push {{r4-r11, lr}}",
    "    sub sp, #8",
    "    mov r12, r0",
    "    movs r0, #0",
    "    str r0, [sp]",
    "1:",
    "    ldr.w r1, [r12, #44]",
    "    ldr lr, [r1], #4",
    "    str.w r1, [r12, #44]",
    "    ldr.w r6, [r12, #32]",
    "    add.w r7, r6, lr, lsl #1",
    "    add.w r1, r7, lr, lsl #1",
    "    str.w r1, [r12, #32]",
    "    ldrd r4, r5, [r12, #36]",
    "    add r5, r4",
    "    add.w r1, r4, lr",
    "    str.w r1, [r12, #36]",
    // Whole groups of 32 terms unpredicated, four vectors an iteration (`LE`), then the last
    // `n % 32` (kept at [sp, #4]) by the tail-predicated loop (skipped by `WLSTP` when 0).
    "    and r0, lr, #31",
    "    str r0, [sp, #4]",
    "    ldm.w r12, {{r0-r3, r8-r11}}",
    "    lsrs.w lr, lr, #5",
    "    beq 5f",
    "    dls lr, lr",
    "2:",
    ".rept 4",
    dot2x2_i16_vec!(),
    ".endr",
    "    le lr, 2b",
    "5:",
    "    ldr lr, [sp, #4]",
    "    wlstp.16 lr, lr, 6f",
    "7:",
    dot2x2_i16_vec!(),
    "    letp lr, 7b",
    "6:",
    "    ldr.w lr, [r12, #52]",
    "    strd r0, r8, [lr]",
    "    strd r2, r10, [lr, #16]",
    "    add.w lr, lr, #32",
    "    str.w lr, [r12, #52]",
    "    eor.w r1, r1, r0, asr #31",
    "    eor.w r3, r3, r2, asr #31",
    "    eor.w r9, r9, r8, asr #31",
    "    eor.w r11, r11, r10, asr #31",
    "    orrs r1, r3",
    "    orr.w r9, r9, r11",
    "    orr.w r1, r1, r9",
    "    ldr r0, [sp]",
    "    orrs r0, r1",
    "    str r0, [sp]",
    "    ldr.w r0, [r12, #48]",
    "    subs r0, #1",
    "    str.w r0, [r12, #48]",
    "    bne 1b",
    "    ldr r0, [sp]",
    "    add sp, #8",
    "    pop {{r4-r11, pc}}",
    ".size muir_mve_dots_i16, . - muir_mve_dots_i16",
);

unsafe extern "C" {
    fn muir_mve_dots_i16(args: *mut DotsArgs) -> u32;
}

/// The arguments of `muir_mve_dots3_i16`, which advances `a`, `w0`, `lens` and `out` part by
/// part (`zero`: six zero words, loaded into the sums by one `LDM` per chunk; `rem` and `more`
/// its scratch: the part's terms left and whether a chunk of the part was stored already).
#[repr(C)]
struct Dots3Args {
    zero: [u32; 6],
    a: *const i16,
    w0: *const i8,
    kl: usize,
    lens: *const u32,
    np: usize,
    out: *mut i32,
    rem: u32,
    more: u32,
}

/// Terms per chunk of `muir_mve_dots3_i16`: `504 * 2^22 < 2^31` (`|w x| <= 128 * 32768`), so a
/// chunk's 32-bit sum is exact; a multiple of 8, so only a part's last chunk has a predicated
/// tail and the pointers run on from one chunk to the next.
pub const DOTS3_CHUNK: usize = 504;

impl PartLens {
    /// The i32 dot products of a block of twelve output channels at two pixels, part by part:
    /// `d[24 p + c] = w_c . a_p` and `d[24 p + 12 + c] = w_c . b_p` for channel `c < 12` (weight
    /// row `c` of `w`, `kl` values each; parts and pair layout as [`PartLens::dots4`]). One call
    /// per three channels for all parts (`muir_mve_dots3_i16`): six 32-bit sums by `VMLADAVA`
    /// (12 instructions per 48 MACs, 45 per 192 for whole groups of 32 terms, four vectors an
    /// iteration; the 64-bit loop of [`PartLens::dots4`] takes 9 per 32), in
    /// chunks of [`DOTS3_CHUNK`] terms, each exact in i32, added by `QADD`. Returns false, with
    /// `d` partly written, when an add of chunks saturated (`APSR.Q`: then the sum may not fit in
    /// i32) or `w` or `pair` is shorter than `12 kl` and `2 kl`; true means every value is the
    /// exact dot product.
    #[inline]
    pub fn dots12(&self, w: &[i8], pair: &[i16], d: &mut [i32; 24 * MAX_PARTS]) -> bool {
        let kl = self.kl;
        if w.len() < 12 * kl || pair.len() < 2 * kl {
            return false;
        }
        let mut bad = 0;
        // Built once: the calls leave `zero` and `kl` as they are and set `rem` and `more` before
        // reading them; the fields they advance are reset per group.
        let mut args = Dots3Args { zero: [0; 6], a: pair.as_ptr(), w0: w.as_ptr(), kl, lens: self.lens.as_ptr(), np: self.np, out: d.as_mut_ptr(), rem: 0, more: 0 };
        for j in 0..4 {
            args.a = pair.as_ptr();
            args.w0 = w.as_ptr().wrapping_add(3 * j * kl);
            args.lens = self.lens.as_ptr();
            args.np = self.np;
            args.out = d.as_mut_ptr().wrapping_add(3 * j);
            // SAFETY: part `p` reads `lens[p] >= 1` values at `2 o_p` and `2 o_p + lens[p]` of
            // `pair` and at `o_p` of weight rows `3j .. 3j + 3` (`3 j kl + o_p`, `+ kl`, `+ 2 kl`),
            // all inside the slices since the lengths sum to `kl` (`PartLens::new`) and the
            // lengths were checked above; it reads and writes `d[24 p + 3 j + {0, 1, 2, 12, 13,
            // 14}]`, inside `d` for `p < np <= MAX_PARTS`, `j < 4`.
            bad |= unsafe { muir_mve_dots3_i16(&mut args) };
        }
        bad == 0
    }
}

core::arch::global_asm!(
    ".syntax unified",
    ".thumb",
    ".cpu cortex-m55",
    ".section .text.muir_mve_dots3_i16,\"ax\",%progbits",
    ".global muir_mve_dots3_i16",
    ".type muir_mve_dots3_i16,%function",
    ".p2align 2",
    ".thumb_func",
    // r0 = &mut Dots3Args (kept in r12). Sums (VMLADAVA takes even registers): pixel a's three
    // channels in r0, r2, r4, pixel b's in r6, r8, r10; weight rows in r1, r3, r5 (the widening
    // loads take low base registers); activations a in r7, b in r9; LR the chunk's length, then
    // the loop count; r11 scratch. Per part: the pointers from the arguments (a part's
    // predicated tail leaves them past its end), then chunks of at most 504 terms; a chunk's
    // sums go to `out` (pixel a at +0, +4, +8; b at +48, +52, +56), a later chunk's are first
    // added to what is there by QADD, which sets the sticky APSR.Q on saturation (cleared on
    // entry). Returns Q (1: some sum may not fit in i32).
    // One vector of eight terms: both pixels' activations, then each channel's widened weights
    // into its two sums (used by the unrolled and the tail-predicated loops).
    ".macro dots3_i16_vec",
    "    vldrh.u16 q0, [r7], #16",
    "    vldrh.u16 q1, [r9], #16",
    "    vldrb.s16 q2, [r1], #8",
    "    vmladava.s16 r0, q0, q2",
    "    vmladava.s16 r6, q1, q2",
    "    vldrb.s16 q2, [r3], #8",
    "    vmladava.s16 r2, q0, q2",
    "    vmladava.s16 r8, q1, q2",
    "    vldrb.s16 q2, [r5], #8",
    "    vmladava.s16 r4, q0, q2",
    "    vmladava.s16 r10, q1, q2",
    ".endm",
    "muir_mve_dots3_i16:",
    "    push {{r4-r11, lr}}",
    "    mov r12, r0",
    "    movs r0, #0",
    "    msr APSR_nzcvq, r0",
    "1:",
    "    ldr.w r0, [r12, #36]",
    "    ldr lr, [r0], #4",
    "    str.w r0, [r12, #36]",
    "    ldr.w r7, [r12, #24]",
    "    add.w r9, r7, lr, lsl #1",
    "    add.w r0, r9, lr, lsl #1",
    "    str.w r0, [r12, #24]",
    "    ldr.w r1, [r12, #28]",
    "    add.w r0, r1, lr",
    "    str.w r0, [r12, #28]",
    "    ldr.w r0, [r12, #32]",
    "    add.w r3, r1, r0",
    "    add.w r5, r3, r0",
    // A part of at most 504 terms (one chunk): the loop, then the sums stored, without the
    // chunk bookkeeping below.
    "    cmp.w lr, #504",
    "    bhi 8f",
    "    ldm.w r12, {{r0, r2, r4, r6, r8, r10}}",
    "    and r11, lr, #31",
    "    lsrs.w lr, lr, #5",
    "    beq 15f",
    "    dls lr, lr",
    "13:",
    ".rept 4",
    "    dots3_i16_vec",
    ".endr",
    "    le lr, 13b",
    "15:",
    "    wlstp.16 lr, r11, 16f",
    "17:",
    "    dots3_i16_vec",
    "    letp lr, 17b",
    "16:",
    "    ldr.w lr, [r12, #44]",
    "    strd r0, r2, [lr]",
    "    str.w r4, [lr, #8]",
    "    strd r6, r8, [lr, #48]",
    "    str.w r10, [lr, #56]",
    "    b 9f",
    "8:",
    "    str.w lr, [r12, #48]",
    "    movs r0, #0",
    "    str.w r0, [r12, #52]",
    "2:",
    "    ldr.w r11, [r12, #48]",
    "    cmp.w r11, #504",
    "    ite hi",
    "    movhi.w lr, #504",
    "    movls lr, r11",
    "    sub.w r11, r11, lr",
    "    str.w r11, [r12, #48]",
    "    ldm.w r12, {{r0, r2, r4, r6, r8, r10}}",
    // Whole groups of 32 terms unpredicated, four vectors an iteration (`LE`), then the last
    // `n % 32` by the tail-predicated loop (skipped by `WLSTP` when 0).
    "    and r11, lr, #31",
    "    lsrs.w lr, lr, #5",
    "    beq 5f",
    "    dls lr, lr",
    "3:",
    ".rept 4",
    "    dots3_i16_vec",
    ".endr",
    "    le lr, 3b",
    "5:",
    "    wlstp.16 lr, r11, 6f",
    "7:",
    "    dots3_i16_vec",
    "    letp lr, 7b",
    "6:",
    "    ldr.w lr, [r12, #44]",
    "    ldr.w r11, [r12, #52]",
    "    cmp.w r11, #0",
    "    beq 4f",
    "    ldr.w r11, [lr]",
    "    qadd r0, r0, r11",
    "    ldr.w r11, [lr, #4]",
    "    qadd r2, r2, r11",
    "    ldr.w r11, [lr, #8]",
    "    qadd r4, r4, r11",
    "    ldr.w r11, [lr, #48]",
    "    qadd r6, r6, r11",
    "    ldr.w r11, [lr, #52]",
    "    qadd r8, r8, r11",
    "    ldr.w r11, [lr, #56]",
    "    qadd r10, r10, r11",
    "4:",
    "    strd r0, r2, [lr]",
    "    str.w r4, [lr, #8]",
    "    strd r6, r8, [lr, #48]",
    "    str.w r10, [lr, #56]",
    "    str.w lr, [r12, #52]",
    "    ldr.w r11, [r12, #48]",
    "    cmp.w r11, #0",
    "    bne 2b",
    "9:",
    "    add.w lr, lr, #96",
    "    str.w lr, [r12, #44]",
    "    ldr.w r11, [r12, #40]",
    "    subs.w r11, r11, #1",
    "    str.w r11, [r12, #40]",
    "    bne 1b",
    "    mrs r0, apsr",
    "    ubfx r0, r0, #27, #1",
    "    pop {{r4-r11, pc}}",
    ".size muir_mve_dots3_i16, . - muir_mve_dots3_i16",
);

unsafe extern "C" {
    fn muir_mve_dots3_i16(args: *mut Dots3Args) -> u32;
}

/// The arguments of `muir_mve_dots3_u8`, which advances `a`, `w0`, `lens`, `sums` and `out` part
/// by part (`zero`: six zero words, loaded into the sums by one `LDM` per part).
#[repr(C)]
struct Dots3U8Args {
    zero: [u32; 6],
    a: *const u8,
    w0: *const i8,
    kl: usize,
    lens: *const u32,
    np: usize,
    out: *mut i32,
    sums: *const i32,
}

/// `128 sum(x)` of each part's two patches of a u8 pair (`s[2 p]`: patch `a_p`, `s[2 p + 1]`:
/// `b_p`; parts and pair layout as [`PartLens::dots4`]) for [`PartLens::dots12_u8`], by
/// `VADDVA.U8` (two instructions per sixteen values). False, with nothing written, when `pair`
/// is shorter than `2 kl` or `kl` reaches `2^16` (then `128 sum(x)` might leave i32).
#[inline]
pub fn pair_sums_u8(l: &PartLens, pair: &[u8], s: &mut [i32; 2 * MAX_PARTS]) -> bool {
    if pair.len() < 2 * l.kl || l.kl >= 1 << 16 {
        return false;
    }
    let mut x = pair.as_ptr();
    for (n, s) in l.lens.iter().take(l.np).zip(s.chunks_exact_mut(2)) {
        for v in s {
            let mut sum = 0u32;
            // SAFETY: `n >= 1` values at `x`, inside `pair` (the lengths sum to `kl`, `2 kl <=
            // pair.len()`); tail-predicated (disabled lanes are not added).
            unsafe {
                asm!(
                    "dlstp.8 lr, {n}",
                    "2:",
                    "vldrb.u8 q0, [{x}], #16",
                    "vaddva.u8 r0, q0",
                    "letp lr, 2b",
                    n = in(reg) *n,
                    x = inout(reg) x => _,
                    // (`VADDVA` takes an even register.)
                    inout("r0") sum,
                    out("lr") _,
                    out("d0") _, out("d1") _,
                    options(nostack, readonly),
                );
            }
            // `sum <= 255 n < 2^24`: `128 sum < 2^31`.
            *v = (sum << 7) as i32;
            x = x.wrapping_add(*n as usize);
        }
    }
    true
}

impl PartLens {
    /// [`PartLens::dots12`] for u8 activations: `d[24 p + c] = w_c . a_p`, `d[24 p + 12 + c] =
    /// w_c . b_p`, given `s` from [`pair_sums_u8`] for this `pair`. One call per three channels
    /// for all parts (`muir_mve_dots3_u8`): each weight vector flipped to `w + 128` in u8 (`VEOR`
    /// 0x80), `VMLADAVA.U8` of sixteen unsigned pairs into six 32-bit sums, then `w . x = (w +
    /// 128) . x - 128 sum(x)` (15 instructions per 96 MACs; the 2x2 loop takes 13 per 64). The
    /// 32-bit sums wrap, but the result `|w . x| < 2^15 n` is in i32 for `n < 2^16`, so it is
    /// exact. Returns false, having written nothing, when `w` or `pair` is shorter than `12 kl`
    /// and `2 kl`, or `kl` reaches `2^16`.
    #[inline]
    pub fn dots12_u8(&self, w: &[i8], pair: &[u8], s: &[i32; 2 * MAX_PARTS], d: &mut [i32; 24 * MAX_PARTS]) -> bool {
        let kl = self.kl;
        if w.len() < 12 * kl || pair.len() < 2 * kl || kl >= 1 << 16 {
            return false;
        }
        if self.np == 1 {
            // One part: the four groups of three channels in one call, the pointers and the
            // sums' corrections in registers between groups (the per-call and per-part setup
            // were 58 instructions per group, 22 loop iterations on average at 160x120).
            let [sa, sb, ..] = *s;
            let mut args = Dots12U8Args { zero: [0; 6], a: pair.as_ptr(), w0: w.as_ptr(), kl, out: d.as_mut_ptr(), sa, sb, tri: 4 };
            // SAFETY: group `j < 4` reads `kl` values at 0 and `kl` of `pair` and of weight rows
            // `3j .. 3j + 3` (`w[3 j kl ..]`), inside the slices by the lengths checked above;
            // it writes `d[3 j + {0, 1, 2, 12, 13, 14}]`, inside `d`.
            unsafe { muir_mve_dots12_u8_1(&mut args) };
            return true;
        }
        for j in 0..4 {
            let mut args = Dots3U8Args {
                zero: [0; 6],
                a: pair.as_ptr(),
                w0: w.as_ptr().wrapping_add(3 * j * kl),
                kl,
                lens: self.lens.as_ptr(),
                np: self.np,
                out: d.as_mut_ptr().wrapping_add(3 * j),
                sums: s.as_ptr(),
            };
            // SAFETY: part `p` reads `lens[p] >= 1` values at `2 o_p` and `2 o_p + lens[p]` of
            // `pair`, at `o_p` of weight rows `3j .. 3j + 3` and `s[2 p]`, `s[2 p + 1]`, all
            // inside the slices since the lengths sum to `kl` (`PartLens::new`), `np <=
            // MAX_PARTS` and the lengths were checked above; it writes `d[24 p + 3 j + {0, 1, 2,
            // 12, 13, 14}]`, inside `d`.
            unsafe { muir_mve_dots3_u8(&mut args) };
        }
        true
    }
}

core::arch::global_asm!(
    ".syntax unified",
    ".thumb",
    ".cpu cortex-m55",
    ".section .text.muir_mve_dots3_u8,\"ax\",%progbits",
    ".global muir_mve_dots3_u8",
    ".type muir_mve_dots3_u8,%function",
    ".p2align 2",
    ".thumb_func",
    // r0 = &mut Dots3U8Args (kept in r12). Sums (even registers for VMLADAVA): pixel a's three
    // channels in r0, r2, r4, pixel b's in r6, r8, r10; weight rows in r1, r3, r5; activations a
    // in r7, b in r9; q3 the flip mask 0x80; LR the part's length, then the loop count; r11 and
    // (after the loop) LR scratch. Per part: the pointers from the arguments (a predicated tail
    // leaves them past the part), the loop, `128 sum(a_p)` and `128 sum(b_p)` subtracted, the
    // sums stored at `out` (a at +0, +4, +8; b at +48, +52, +56).
    "muir_mve_dots3_u8:",
    "    push {{r4-r11, lr}}",
    "    mov r12, r0",
    "    vmov.i8 q3, #0x80",
    "1:",
    "    ldr.w r0, [r12, #36]",
    "    ldr lr, [r0], #4",
    "    str.w r0, [r12, #36]",
    "    ldr.w r7, [r12, #24]",
    "    add.w r9, r7, lr",
    "    add.w r0, r9, lr",
    "    str.w r0, [r12, #24]",
    "    ldr.w r1, [r12, #28]",
    "    add.w r0, r1, lr",
    "    str.w r0, [r12, #28]",
    "    ldr.w r0, [r12, #32]",
    "    add.w r3, r1, r0",
    "    add.w r5, r3, r0",
    "    ldm.w r12, {{r0, r2, r4, r6, r8, r10}}",
    "    dlstp.8 lr, lr",
    "2:",
    "    vldrb.u8 q0, [r7], #16",
    "    vldrb.u8 q1, [r9], #16",
    "    vldrb.u8 q2, [r1], #16",
    "    veor q2, q2, q3",
    "    vmladava.u8 r0, q0, q2",
    "    vmladava.u8 r6, q1, q2",
    "    vldrb.u8 q2, [r3], #16",
    "    veor q2, q2, q3",
    "    vmladava.u8 r2, q0, q2",
    "    vmladava.u8 r8, q1, q2",
    "    vldrb.u8 q2, [r5], #16",
    "    veor q2, q2, q3",
    "    vmladava.u8 r4, q0, q2",
    "    vmladava.u8 r10, q1, q2",
    "    letp lr, 2b",
    "    ldr.w lr, [r12, #48]",
    "    ldr r11, [lr], #4",
    "    sub.w r0, r0, r11",
    "    sub.w r2, r2, r11",
    "    sub.w r4, r4, r11",
    "    ldr r11, [lr], #4",
    "    sub.w r6, r6, r11",
    "    sub.w r8, r8, r11",
    "    sub.w r10, r10, r11",
    "    str.w lr, [r12, #48]",
    "    ldr.w lr, [r12, #44]",
    "    strd r0, r2, [lr]",
    "    str.w r4, [lr, #8]",
    "    strd r6, r8, [lr, #48]",
    "    str.w r10, [lr, #56]",
    "    add.w lr, lr, #96",
    "    str.w lr, [r12, #44]",
    "    ldr.w r11, [r12, #40]",
    "    subs.w r11, r11, #1",
    "    str.w r11, [r12, #40]",
    "    bne 1b",
    "    pop {{r4-r11, pc}}",
    ".size muir_mve_dots3_u8, . - muir_mve_dots3_u8",
);

unsafe extern "C" {
    fn muir_mve_dots3_u8(args: *mut Dots3U8Args);
}

/// The arguments of `muir_mve_dots12_u8_1` (one part): `sa`, `sb` are `128 sum(x)` of the
/// patches, `w0` and `out` advance group by group, `tri` counts the groups left.
#[repr(C)]
struct Dots12U8Args {
    zero: [u32; 6],
    a: *const u8,
    w0: *const i8,
    kl: usize,
    out: *mut i32,
    sa: i32,
    sb: i32,
    tri: u32,
}

core::arch::global_asm!(
    ".syntax unified",
    ".thumb",
    ".cpu cortex-m55",
    ".section .text.muir_mve_dots12_u8_1,\"ax\",%progbits",
    ".global muir_mve_dots12_u8_1",
    ".type muir_mve_dots12_u8_1,%function",
    ".p2align 2",
    ".thumb_func",
    // r0 = &mut Dots12U8Args (kept in r12). Registers in the loop as `muir_mve_dots3_u8`. Per
    // group of three channels: weight rows at `w0`, `+ kl`, `+ 2 kl` (the next group's `w0` at
    // `+ 3 kl`), the loop over the whole patch, `sa` and `sb` subtracted, the sums stored at `out`
    // (a at +0, +4, +8; b at +48, +52, +56), `out` 12 bytes on.
    "muir_mve_dots12_u8_1:",
    "    push {{r4-r11, lr}}",
    "    mov r12, r0",
    "    vmov.i8 q3, #0x80",
    "1:",
    "    ldr.w r7, [r12, #24]",
    "    ldrd r1, lr, [r12, #28]",
    "    add.w r9, r7, lr",
    "    add.w r3, r1, lr",
    "    add.w r5, r3, lr",
    "    add.w r0, r5, lr",
    "    str.w r0, [r12, #28]",
    "    ldm.w r12, {{r0, r2, r4, r6, r8, r10}}",
    "    dlstp.8 lr, lr",
    "2:",
    "    vldrb.u8 q0, [r7], #16",
    "    vldrb.u8 q1, [r9], #16",
    "    vldrb.u8 q2, [r1], #16",
    "    veor q2, q2, q3",
    "    vmladava.u8 r0, q0, q2",
    "    vmladava.u8 r6, q1, q2",
    "    vldrb.u8 q2, [r3], #16",
    "    veor q2, q2, q3",
    "    vmladava.u8 r2, q0, q2",
    "    vmladava.u8 r8, q1, q2",
    "    vldrb.u8 q2, [r5], #16",
    "    veor q2, q2, q3",
    "    vmladava.u8 r4, q0, q2",
    "    vmladava.u8 r10, q1, q2",
    "    letp lr, 2b",
    "    ldrd r11, lr, [r12, #40]",
    "    sub.w r0, r0, r11",
    "    sub.w r2, r2, r11",
    "    sub.w r4, r4, r11",
    "    sub.w r6, r6, lr",
    "    sub.w r8, r8, lr",
    "    sub.w r10, r10, lr",
    "    ldr.w lr, [r12, #36]",
    "    strd r0, r2, [lr]",
    "    str.w r4, [lr, #8]",
    "    strd r6, r8, [lr, #48]",
    "    str.w r10, [lr, #56]",
    "    add.w lr, lr, #12",
    "    str.w lr, [r12, #36]",
    "    ldr.w r11, [r12, #48]",
    "    subs.w r11, r11, #1",
    "    str.w r11, [r12, #48]",
    "    bne 1b",
    "    pop {{r4-r11, pc}}",
    ".size muir_mve_dots12_u8_1, . - muir_mve_dots12_u8_1",
);

unsafe extern "C" {
    fn muir_mve_dots12_u8_1(args: *mut Dots12U8Args);
}

/// Channels per call of [`dots_flipped`]: a pixel's sums fill half of a block's table
/// (`24 MAX_PARTS` values: pixel `a` at `0..FLIP_MAX`, pixel `b` at `FLIP_MAX..`).
pub const FLIP_MAX: usize = 12 * MAX_PARTS;

/// `x ^= 0x80` on every byte: u8 activations to `x - 128` in i8 and back (sixteen bytes per load,
/// flip and store, tail-predicated).
#[inline]
pub fn flip_u8(x: &mut [u8]) {
    if x.is_empty() {
        return;
    }
    // SAFETY: `x.len()` bytes at `x` (tail-predicated: disabled lanes are neither loaded nor
    // stored), read and written in place.
    unsafe {
        asm!(
            // Whole groups of 64 bytes four vectors an iteration (`LE`), the rest
            // tail-predicated (skipped by `WLSTP` when 0).
            "vmov.i8 q1, #0x80",
            "and {t}, {n}, #63",
            "lsrs {n}, {n}, #6",
            "beq 5f",
            "dls lr, {n}",
            "2:",
            "vldrb.u8 q0, [{p}]",
            "veor q0, q0, q1",
            "vstrb.8 q0, [{p}], #16",
            "vldrb.u8 q0, [{p}]",
            "veor q0, q0, q1",
            "vstrb.8 q0, [{p}], #16",
            "vldrb.u8 q0, [{p}]",
            "veor q0, q0, q1",
            "vstrb.8 q0, [{p}], #16",
            "vldrb.u8 q0, [{p}]",
            "veor q0, q0, q1",
            "vstrb.8 q0, [{p}], #16",
            "le lr, 2b",
            "5:",
            "wlstp.8 lr, {t}, 6f",
            "7:",
            "vldrb.u8 q0, [{p}]",
            "veor q0, q0, q1",
            "vstrb.8 q0, [{p}], #16",
            "letp lr, 7b",
            "6:",
            n = inout(reg) x.len() => _,
            t = out(reg) _,
            p = inout(reg) x.as_mut_ptr() => _,
            out("lr") _,
            out("d0") _, out("d1") _, out("d2") _, out("d3") _,
            options(nostack),
        );
    }
}

/// `sum(w)` of at most `2^24` int8 values by `VADDVA.S8` (sixteen a vector; exact in i32).
/// Longer slices: the first `2^24` values.
#[inline]
pub fn sum_i8(w: &[i8]) -> i32 {
    let n = w.len().min(1 << 24);
    if n == 0 {
        return 0;
    }
    let mut s = 0i32;
    // SAFETY: `n >= 1` bytes at `w` (tail-predicated: disabled lanes are not added).
    unsafe {
        asm!(
            // Whole groups of 64 bytes four vectors an iteration (`LE`), the rest
            // tail-predicated (skipped by `WLSTP` when 0).
            "and {t}, {n}, #63",
            "lsrs {n}, {n}, #6",
            "beq 5f",
            "dls lr, {n}",
            "2:",
            "vldrb.u8 q0, [{w}], #16",
            "vaddva.s8 r0, q0",
            "vldrb.u8 q0, [{w}], #16",
            "vaddva.s8 r0, q0",
            "vldrb.u8 q0, [{w}], #16",
            "vaddva.s8 r0, q0",
            "vldrb.u8 q0, [{w}], #16",
            "vaddva.s8 r0, q0",
            "le lr, 2b",
            "5:",
            "wlstp.8 lr, {t}, 6f",
            "7:",
            "vldrb.u8 q0, [{w}], #16",
            "vaddva.s8 r0, q0",
            "letp lr, 7b",
            "6:",
            n = inout(reg) n => _,
            t = out(reg) _,
            w = inout(reg) w.as_ptr() => _,
            inout("r0") s,
            out("lr") _,
            out("d0") _, out("d1") _,
            options(nostack, readonly),
        );
    }
    s
}

/// The arguments of `muir_mve_dots_s8_1` (one part, activations flipped to `x - 128`): `w0`, `ws`
/// and `out` advance group by group, `tri` counts the groups left.
#[repr(C)]
struct DotsS8Args {
    zero: [u32; 6],
    a: *const u8,
    w0: *const i8,
    kl: usize,
    out: *mut i32,
    ws: *const i32,
    tri: u32,
}

/// The i32 dot products of output channels `0..cout` at the two pixels of a one-part u8 pair:
/// `d[c] = w_c . a` and `d[FLIP_MAX + c] = w_c . b` (weight row `c` of `w`, `kl` values each;
/// `pair`: `a`, then `b`), given `ws[c] = 128 sum(w_c)` ([`sum_i8`], wrapping). The pair's first
/// `2 kl` values are flipped in place to `x - 128` ([`flip_u8`]) and stay so (the caller flips
/// them back where it reads them again). One call of
/// `muir_mve_dots_s8_1` for the whole groups of three channels (`VMLADAVA.S8` of sixteen signed
/// pairs into six 32-bit sums, 12 instructions per 96 MACs; whole groups of 64 terms four vectors
/// an iteration, 45 per 384), one more for channels `cout - 3 ..`
/// when `cout` is not a multiple of 3 (those values are written twice, the same both times).
/// `w . x = w . (x - 128) + 128 sum(w)`: the 32-bit sums wrap, but `|w . x| < 2^15 kl` is in i32
/// for `kl < 2^16`, so the wrapped result is the exact one. Returns false, having written
/// nothing, when `cout` is outside `3..=FLIP_MAX`, `kl` is 0 or reaches `2^16`, or `w`, `pair` or
/// `ws` is shorter than `cout kl`, `2 kl` and `cout`.
#[inline]
pub fn dots_flipped(ws: &[i32], w: &[i8], kl: usize, cout: usize, pair: &mut [u8], d: &mut [i32; 24 * MAX_PARTS]) -> bool {
    if !(3..=FLIP_MAX).contains(&cout) || kl == 0 || kl >= 1 << 16 || w.len() < cout * kl || ws.len() < cout {
        return false;
    }
    let Some(pair) = pair.get_mut(..2 * kl) else {
        return false;
    };
    flip_u8(pair);
    let (whole, rest) = (cout / 3, cout % 3);
    for (first, tri) in [(0, whole), (cout - 3, usize::from(rest != 0))] {
        if tri == 0 {
            continue;
        }
        let mut args = DotsS8Args {
            zero: [0; 6],
            a: pair.as_ptr(),
            w0: w.as_ptr().wrapping_add(first * kl),
            kl,
            out: d.as_mut_ptr().wrapping_add(first),
            ws: ws.as_ptr().wrapping_add(first),
            tri: tri as u32,
        };
        // SAFETY: group `j < tri` reads `kl` values at 0 and `kl` of `pair`, weight rows
        // `first + 3j .. first + 3j + 3 <= cout` of `w` and `ws[first + 3j .. + 3]`, inside the
        // slices by the lengths checked above; it writes `d[first + 3 j + {0, 1, 2}]` and
        // `d[FLIP_MAX + first + 3 j + {0, 1, 2}]`, inside `d` for `first + 3 j + 3 <= cout <=
        // FLIP_MAX`.
        unsafe { muir_mve_dots_s8_1(&mut args) };
    }
    true
}

const _: () = assert!(FLIP_MAX * 4 <= 1020 - 8 && 2 * FLIP_MAX == 24 * MAX_PARTS);

core::arch::global_asm!(
    ".syntax unified",
    ".thumb",
    ".cpu cortex-m55",
    ".section .text.muir_mve_dots_s8_1,\"ax\",%progbits",
    ".global muir_mve_dots_s8_1",
    ".type muir_mve_dots_s8_1,%function",
    ".p2align 2",
    ".thumb_func",
    // r0 = &mut DotsS8Args (kept in r12). Sums (even registers for VMLADAVA): pixel a's three
    // channels in r0, r2, r4, pixel b's in r6, r8, r10; weight rows in r1, r3, r5; activations a
    // in r7, b in r9; LR the patch length, then the loop count; r11 and (after the loop) LR
    // scratch. Per group of three channels: weight rows at `w0`, `+ kl`, `+ 2 kl` (the next
    // group's `w0` at `+ 3 kl`), the loop over the whole patch, `ws[0..3]` added to both pixels'
    // sums, the sums stored at `out` (a at +0, +4, +8; b at +288, +292, +296, i.e. FLIP_MAX
    // values on), `out` and `ws` 12 bytes on.
    "muir_mve_dots_s8_1:",
    "    push {{r4-r11, lr}}",
    "    mov r12, r0",
    "1:",
    "    ldr.w r7, [r12, #24]",
    "    ldrd r1, lr, [r12, #28]",
    "    add.w r9, r7, lr",
    "    add.w r3, r1, lr",
    "    add.w r5, r3, lr",
    "    add.w r0, r5, lr",
    "    str.w r0, [r12, #28]",
    "    ldm.w r12, {{r0, r2, r4, r6, r8, r10}}",
    // Whole groups of 64 terms unpredicated, four vectors an iteration (`LE`), then the last
    // `kl % 64` by the tail-predicated loop (skipped by `WLSTP` when 0).
    "    and r11, lr, #63",
    "    lsrs.w lr, lr, #6",
    "    beq 5f",
    "    dls lr, lr",
    "2:",
    ".rept 4",
    dots_s8_1_vec!(),
    ".endr",
    "    le lr, 2b",
    "5:",
    "    wlstp.8 lr, r11, 6f",
    "7:",
    dots_s8_1_vec!(),
    "    letp lr, 7b",
    "6:",
    "    ldr.w lr, [r12, #40]",
    "    ldr r11, [lr], #4",
    "    add.w r0, r0, r11",
    "    add.w r6, r6, r11",
    "    ldr r11, [lr], #4",
    "    add.w r2, r2, r11",
    "    add.w r8, r8, r11",
    "    ldr r11, [lr], #4",
    "    add.w r4, r4, r11",
    "    add.w r10, r10, r11",
    "    str.w lr, [r12, #40]",
    "    ldr.w lr, [r12, #36]",
    "    strd r0, r2, [lr]",
    "    str.w r4, [lr, #8]",
    "    strd r6, r8, [lr, #288]",
    "    str.w r10, [lr, #296]",
    "    add.w lr, lr, #12",
    "    str.w lr, [r12, #36]",
    "    ldr.w r11, [r12, #44]",
    "    subs.w r11, r11, #1",
    "    str.w r11, [r12, #44]",
    "    bne 1b",
    "    pop {{r4-r11, pc}}",
    ".size muir_mve_dots_s8_1, . - muir_mve_dots_s8_1",
);

unsafe extern "C" {
    fn muir_mve_dots_s8_1(args: *mut DotsS8Args);
}

/// The per-layer constants of [`requant4`]: four 32-bit lanes each.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(16))]
pub struct Requant4 {
    /// Byte offsets of four consecutive channels' multipliers of one part: `8 np i`.
    pub mult_offsets: [u32; 4],
    /// Lower clamp (the output type's minimum; 0 with a ReLU).
    pub lo: [i32; 4],
    /// Upper clamp (the output type's maximum).
    pub hi: [i32; 4],
    /// Byte offsets of four consecutive biases: `8 i`.
    pub bias_offsets: [u32; 4],
    /// Lower clamp of the output type after a table ([`requant4_lut`]).
    pub out_lo: [i32; 4],
    /// Upper clamp of the output type after a table.
    pub out_hi: [i32; 4],
}

impl Requant4 {
    /// The constants of a layer of `np` parts clamping to `lo..=hi`.
    pub const fn new(np: usize, lo: i32, hi: i32) -> Self {
        let s = 8 * np as u32;
        Requant4 { mult_offsets: [0, s, 2 * s, 3 * s], lo: [lo; 4], hi: [hi; 4], bias_offsets: [0, 8, 16, 24], out_lo: [lo; 4], out_hi: [hi; 4] }
    }

    /// The same with the output type's range `out_lo..=out_hi` for [`requant4_lut`] (`lo..=hi`
    /// is then the table's input range).
    pub const fn with_out(self, out_lo: i32, out_hi: i32) -> Self {
        Requant4 { out_lo: [out_lo; 4], out_hi: [out_hi; 4], ..self }
    }
}

/// A convolution output type [`requant4`] stores with a narrowing vector store.
pub trait Narrow: Copy {
    /// [`requant4`] for this output type.
    ///
    /// # Safety
    /// See [`requant4`].
    unsafe fn requant4_n(d: *const i32, mult: *const u8, k: &Requant4, np: usize, bias: *const u8, out: *mut Self);
    /// [`requant4_lut`] for this output type.
    ///
    /// # Safety
    /// See [`requant4_lut`].
    unsafe fn requant4_lut_n(d: *const i32, mult: *const u8, k: &Requant4, np: usize, bias: *const u8, table: &[i16; 1025], out: *mut Self);
    /// [`requant4_wide`] for this output type.
    ///
    /// # Safety
    /// See [`requant4_wide`].
    unsafe fn requant4w_n(d: *const i32, mult: *const u8, k: &Requant4, np: usize, bias: *const u8, out: *mut Self);
    /// [`requant4_lut_wide`] for this output type.
    ///
    /// # Safety
    /// See [`requant4_lut_wide`].
    unsafe fn requant4w_lut_n(d: *const i32, mult: *const u8, k: &Requant4, np: usize, bias: *const u8, table: &[i16; 1025], out: *mut Self);
    /// [`requant4_pair`] for this output type (parts 32 bytes apart).
    ///
    /// # Safety
    /// See [`requant4_pair`].
    unsafe fn requant4x2_n(d: [*const i32; 2], mult: *const u8, k: &Requant4, np: usize, bias: *const u8, table: Option<&[i16; 1025]>, out: [*mut Self; 2]);
    /// [`requant4_pair`] for this output type, parts 96 bytes apart.
    ///
    /// # Safety
    /// See [`requant4_pair`].
    unsafe fn requant4x2w_n(d: [*const i32; 2], mult: *const u8, k: &Requant4, np: usize, bias: *const u8, table: Option<&[i16; 1025]>, out: [*mut Self; 2]);
    /// [`requant4_groups`]' loop for this output type (parts 32 bytes apart).
    ///
    /// # Safety
    /// See [`requant4_groups`].
    unsafe fn requant4g_n(g: *mut GroupState, k: &Requant4, table: Option<&[i16; 1025]>);
    /// [`requant4_groups`]' loop for this output type, parts 96 bytes apart.
    ///
    /// # Safety
    /// See [`requant4_groups`].
    unsafe fn requant4gw_n(g: *mut GroupState, k: &Requant4, table: Option<&[i16; 1025]>);
    /// [`requant4_groups`]' loop for this output type, one part, no table.
    ///
    /// # Safety
    /// See [`requant4_groups`] (`np == 1`, no table).
    unsafe fn requant4g1_n(g: *mut GroupState, k: &Requant4);
}

/// The requantisation both [`Narrow`] kernels share, as one `asm!` template piece: the bias
/// gathered into q6, then per part the sums' multiply (`vmulh`/`vmul`), the rounding shifts and
/// the saturating adds, then the rounding by 8 bits and the clamp to `[k + 16, k + 32]`; `$stride`
/// is the byte distance between two parts' sums (32, or 96 in the twelve-channel table).
/// Registers as in [`narrow`].
macro_rules! requant4_sums {
    ($stride:literal) => {
        concat!(
            "vldrw.u32 q0, [{k}, #48]\n",
            "vldrw.u32 q6, [{bias}, q0]\n",
            "vldrw.u32 q7, [{k}]\n",
            "vmov.i32 q0, #4\n",
            "vadd.i32 q0, q7, q0\n",
            "vmov.i32 q5, #32\n",
            "2:\n",
            "vldrw.u32 q1, [{d}], #", $stride, "\n",
            "vldrw.u32 q2, [r1, q7]\n",
            "vldrb.u32 q3, [r1, q0]\n",
            "vmulh.s32 q4, q1, q2\n",
            "vmul.i32 q1, q1, q2\n",
            "vsub.i32 q2, q5, q3\n",
            "vneg.s32 q3, q3\n",
            "vrshl.u32 q1, q1, q3\n",
            "vqrshl.s32 q4, q4, q2\n",
            "vqadd.s32 q4, q4, q1\n",
            "vqadd.s32 q6, q6, q4\n",
            "add r1, r1, #8\n",
            "subs {n}, {n}, #1\n",
            "bne 2b\n",
            "vrshr.s32 q6, q6, #8\n",
            "vldrw.u32 q1, [{k}, #16]\n",
            "vmax.s32 q6, q6, q1\n",
            "vldrw.u32 q1, [{k}, #32]\n",
            "vmin.s32 q6, q6, q1\n",
        )
    };
}

/// The [`Narrow`] kernel of one output type: `$store` is the narrowing store of four 32-bit lanes
/// (a low base register, r0 here). Registers: q7 the multipliers' offsets, q0 those of the shift
/// bytes (4 further), q5 the constant 32, q6 the sums; q1-q4 temporaries.
macro_rules! narrow_fns {
    ($store:literal, $plain:ident, $lut:ident, $stride:literal) => {
            #[inline(always)]
            unsafe fn $plain(d: *const i32, mult: *const u8, k: &Requant4, np: usize, bias: *const u8, out: *mut Self) {
                // SAFETY: the caller's bounds (`requant4`); registers as listed.
                unsafe {
                    asm!(
                        requant4_sums!($stride),
                        concat!($store, " q6, [r0]"),
                        k = in(reg) k as *const Requant4,
                        bias = in(reg) bias,
                        d = inout(reg) d => _,
                        n = inout(reg) np => _,
                        inout("r1") mult => _,
                        in("r0") out,
                        out("d0") _, out("d1") _, out("d2") _, out("d3") _, out("d4") _, out("d5") _, out("d6") _, out("d7") _,
                        out("d8") _, out("d9") _, out("d10") _, out("d11") _, out("d12") _, out("d13") _, out("d14") _, out("d15") _,
                        options(nostack),
                    );
                }
            }
            #[inline(always)]
            unsafe fn $lut(d: *const i32, mult: *const u8, k: &Requant4, np: usize, bias: *const u8, table: &[i16; 1025], out: *mut Self) {
                // SAFETY: the caller's bounds (`requant4_lut`); the gathers read entries `i` and
                // `i + 1` of the 1025-entry table for `i = (x + 32768) >> 6 <= 1023`, `x` clamped
                // to `lo..=hi` within `-32768..=32767` first (`Requant4` of `requant4_lut`).
                unsafe {
                    asm!(
                        requant4_sums!($stride),
                        // The table: u = x + 32768, entries u >> 6 and the next, fraction u & 63.
                        "vmov.i32 q1, #0x8000",
                        "vadd.i32 q6, q6, q1",
                        "vshr.u32 q2, q6, #6",
                        "vmov.i32 q1, #63",
                        "vand q6, q6, q1",
                        "vldrh.s32 q3, [{tab}, q2, uxtw #1]",
                        "vldrh.s32 q4, [{tab1}, q2, uxtw #1]",
                        "vsub.i32 q4, q4, q3",
                        "vmul.i32 q4, q4, q6",
                        "vrshr.s32 q4, q4, #6",
                        "vadd.i32 q6, q3, q4",
                        "vldrw.u32 q1, [{k}, #64]",
                        "vmax.s32 q6, q6, q1",
                        "vldrw.u32 q1, [{k}, #80]",
                        "vmin.s32 q6, q6, q1",
                        concat!($store, " q6, [r0]"),
                        k = in(reg) k as *const Requant4,
                        bias = in(reg) bias,
                        d = inout(reg) d => _,
                        n = inout(reg) np => _,
                        tab = in(reg) table.as_ptr(),
                        tab1 = in(reg) table.as_ptr().wrapping_add(1),
                        inout("r1") mult => _,
                        in("r0") out,
                        out("d0") _, out("d1") _, out("d2") _, out("d3") _, out("d4") _, out("d5") _, out("d6") _, out("d7") _,
                        out("d8") _, out("d9") _, out("d10") _, out("d11") _, out("d12") _, out("d13") _, out("d14") _, out("d15") _,
                        options(nostack),
                    );
                }
            }
    };
}

/// [`requant4_sums`] for two pixels at once: the multipliers and shifts of each part gathered
/// once for both; pixel `a`'s sums in q6, `b`'s in q5 (both start from the gathered bias), its
/// dot products read through `{da}` and `{db}`; q7 the multipliers' offsets, `{m4}` the shift
/// bytes' base (`r1 + 4`), `{c32}` the constant 32; then both rounded by 8 bits and clamped to
/// `[k + 16, k + 32]`. Temporaries q0-q4.
macro_rules! requant4_sums_pair {
    ($stride:literal) => {
        concat!(
            "vldrw.u32 q0, [{k}, #48]\n",
            "vldrw.u32 q6, [{c32}, q0]\n",
            "vmov q5, q6\n",
            "vldrw.u32 q7, [{k}]\n",
            "mov.w {c32}, #32\n",
            "2:\n",
            "vldrw.u32 q2, [r1, q7]\n",
            "vldrb.u32 q3, [{m4}, q7]\n",
            "vneg.s32 q3, q3\n",
            "vadd.i32 q4, q3, {c32}\n",
            requant4_part!("{da}", $stride, "q6"),
            requant4_part!("{db}", $stride, "q5"),
            "add r1, r1, #8\n",
            "add {m4}, {m4}, #8\n",
            "subs {n}, {n}, #1\n",
            "bne 2b\n",
            "vrshr.s32 q6, q6, #8\n",
            "vrshr.s32 q5, q5, #8\n",
            clamp_pair!("16", "32"),
        )
    };
}

/// One part's requantised sum of one pixel added to `$acc` (`q6` or `q5`): its four dot products
/// loaded through `$d` (`{da}` or `{db}`, advanced by `$stride` bytes), then
/// `VQRSHL(h, 32 - s) + VRSHL_u(l, -s)` from the product's high and low words (q2 the multipliers,
/// q3 `-s`, q4 `32 - s`). Temporaries q0, q1.
macro_rules! requant4_part {
    ($d:literal, $stride:literal, $acc:literal) => {
        concat!(
            "vldrw.u32 q0, [", $d, "], #", $stride, "\n",
            "vmulh.s32 q1, q0, q2\n",
            "vmul.i32 q0, q0, q2\n",
            "vrshl.u32 q0, q0, q3\n",
            "vqrshl.s32 q1, q1, q4\n",
            "vqadd.s32 q1, q1, q0\n",
            "vqadd.s32 ", $acc, ", ", $acc, ", q1\n",
        )
    };
}

/// Both pixels' q6 and q5 clamped to `[k + $lo, k + $hi]` (byte offsets in [`Requant4`]).
/// Temporary q1.
macro_rules! clamp_pair {
    ($lo:literal, $hi:literal) => {
        concat!(
            "vldrw.u32 q1, [{k}, #", $lo, "]\n",
            "vmax.s32 q6, q6, q1\n",
            "vmax.s32 q5, q5, q1\n",
            "vldrw.u32 q1, [{k}, #", $hi, "]\n",
            "vmin.s32 q6, q6, q1\n",
            "vmin.s32 q5, q5, q1\n",
        )
    };
}

/// The table of [`requant4_lut`] on the clamped q-register `$q` (temporaries q0-q4, `{tab}` the
/// table, `$next` a register holding the table one entry on: `{tab1}`, or `{da}` in the group
/// loops, where `{da}` is free by then).
macro_rules! lut_pair_piece {
    ($q:literal, $next:literal) => {
        concat!(
            "vmov.i32 q1, #0x8000\n",
            "vadd.i32 ", $q, ", ", $q, ", q1\n",
            "vshr.u32 q2, ", $q, ", #6\n",
            "vmov.i32 q1, #63\n",
            "vand ", $q, ", ", $q, ", q1\n",
            "vldrh.s32 q3, [{tab}, q2, uxtw #1]\n",
            "vldrh.s32 q4, [", $next, ", q2, uxtw #1]\n",
            "vsub.i32 q4, q4, q3\n",
            "vmul.i32 q4, q4, ", $q, "\n",
            "vrshr.s32 q4, q4, #6\n",
            "vadd.i32 ", $q, ", q3, q4\n",
        )
    };
}

/// The two-pixel kernels of one output type ([`requant4_pair`]): `$store` the narrowing store
/// (low base registers r0 and r2 here).
macro_rules! narrow_pair_fn {
    ($store:literal, $name:ident, $stride:literal) => {
        #[inline(always)]
        unsafe fn $name(d: [*const i32; 2], mult: *const u8, k: &Requant4, np: usize, bias: *const u8, table: Option<&[i16; 1025]>, out: [*mut Self; 2]) {
            // SAFETY: the caller's bounds (`requant4_pair`); registers as listed.
            unsafe {
                match table {
                    None => asm!(
                        requant4_sums_pair!($stride),
                        concat!($store, " q6, [r0]"),
                        concat!($store, " q5, [r2]"),
                        k = in(reg) k as *const Requant4,
                        c32 = inout(reg) bias => _,
                        da = inout(reg) d[0] => _,
                        db = inout(reg) d[1] => _,
                        n = inout(reg) np => _,
                        m4 = inout(reg) mult.wrapping_add(4) => _,
                        inout("r1") mult => _,
                        in("r0") out[0],
                        in("r2") out[1],
                        out("d0") _, out("d1") _, out("d2") _, out("d3") _, out("d4") _, out("d5") _, out("d6") _, out("d7") _,
                        out("d8") _, out("d9") _, out("d10") _, out("d11") _, out("d12") _, out("d13") _, out("d14") _, out("d15") _,
                        options(nostack),
                    ),
                    // The table's clamp before it is `-32768..=32767` (`Requant4` of
                    // `requant4_lut`): entries `i`, `i + 1` for `i <= 1023`.
                    Some(t) => asm!(
                        requant4_sums_pair!($stride),
                        "add.w {tab1}, {tab}, #2",
                        lut_pair_piece!("q6", "{tab1}"),
                        lut_pair_piece!("q5", "{tab1}"),
                        clamp_pair!("64", "80"),
                        concat!($store, " q6, [r0]"),
                        concat!($store, " q5, [r2]"),
                        k = in(reg) k as *const Requant4,
                        c32 = inout(reg) bias => _,
                        da = inout(reg) d[0] => _,
                        db = inout(reg) d[1] => _,
                        n = inout(reg) np => _,
                        m4 = inout(reg) mult.wrapping_add(4) => _,
                        tab = in(reg) t.as_ptr(),
                        tab1 = out(reg) _,
                        inout("r1") mult => _,
                        in("r0") out[0],
                        in("r2") out[1],
                        out("d0") _, out("d1") _, out("d2") _, out("d3") _, out("d4") _, out("d5") _, out("d6") _, out("d7") _,
                        out("d8") _, out("d9") _, out("d10") _, out("d11") _, out("d12") _, out("d13") _, out("d14") _, out("d15") _,
                        options(nostack),
                    ),
                }
            }
        }
    };
}

/// The state of [`requant4_groups`]' loop over groups of four channels, advanced in place (built
/// by [`requant4_groups`] only).
#[repr(C)]
pub struct GroupState {
    /// Pixel `a`'s and `b`'s dot products of the group (part 0).
    da: *const i32,
    db: *const i32,
    /// The group's multipliers and biases.
    mult: *const u8,
    bias: *const u8,
    /// Pixel `a`'s and `b`'s four outputs of the group.
    oa: usize,
    ob: usize,
    /// Groups left; the parts; bit `g` set when group `g` saturated; the current group's bit.
    left: u32,
    np: u32,
    mask: u32,
    bit: u32,
}

/// [`groups_loop`]'s store of a group's two pixels (q6, q5) and the advance of the output and
/// dot-product pointers in the state `{g}` ([`GroupState`]).
macro_rules! group_store {
    ($store:literal, $size:literal) => {
        concat!(
            "ldrd r0, r2, [{g}, #16]\n",
            $store, " q6, [r0]\n",
            $store, " q5, [r2]\n",
            "adds r0, r0, #", $size, "\n",
            "adds r2, r2, #", $size, "\n",
            "strd r0, r2, [{g}, #16]\n",
            "ldrd {da}, {db}, [{g}]\n",
            "adds {da}, {da}, #16\n",
            "adds {db}, {db}, #16\n",
            "strd {da}, {db}, [{g}]\n",
        )
    };
}

/// [`groups_loop`]'s saturation test: `FPSCR.QC` tested and cleared, the current group's bit
/// added to the mask where it was set, the bit moved on to the next group (state in `{g}`).
macro_rules! group_saturation {
    () => {
        concat!(
            "vmrs {n}, fpscr\n",
            "tst.w {n}, #0x8000000\n",
            "beq 3f\n",
            "bic {n}, {n}, #0x8000000\n",
            "vmsr fpscr, {n}\n",
            "ldrd {n}, {da}, [{g}, #32]\n",
            "orrs {n}, {n}, {da}\n",
            "str.w {n}, [{g}, #32]\n",
            "3:\n",
            "ldr.w {n}, [{g}, #36]\n",
            "lsls {n}, {n}, #1\n",
            "str.w {n}, [{g}, #36]\n",
        )
    };
}

/// The per-group loop of [`requant4_groups`] around [`requant4_sums_pair`]: `$size` is the output
/// bytes of four values, `$lut` the table piece (empty without a table). State in `{g}`
/// ([`GroupState`]), `{da}`/`{db}`/`{c32}` reloaded per group.
macro_rules! groups_loop {
    ($store:literal, $size:literal, $stride:literal, $lut:expr) => {
        concat!(
            "1:\n",
            "ldrd {da}, {db}, [{g}]\n",
            "ldrd r1, {c32}, [{g}, #8]\n",
            "add.w {m4}, r1, #4\n",
            "ldr.w {n}, [{g}, #28]\n",
            requant4_sums_pair!($stride),
            $lut,
            group_store!($store, $size),
            "ldrd r1, {c32}, [{g}, #8]\n",
            "ldr.w {n}, [{g}, #28]\n",
            "add.w r1, r1, {n}, lsl #5\n",
            "adds {c32}, {c32}, #32\n",
            "strd r1, {c32}, [{g}, #8]\n",
            group_saturation!(),
            "ldr.w {n}, [{g}, #24]\n",
            "subs {n}, {n}, #1\n",
            "str.w {n}, [{g}, #24]\n",
            "bne 1b\n",
        )
    };
}

/// [`groups_loop`] without a table, two registers spare: the parts in `{np}` and the groups
/// left in `{left}` instead of the state's fields (three loads and a store fewer per group).
macro_rules! groups_loop_reg {
    ($store:literal, $size:literal, $stride:literal) => {
        concat!(
            "1:\n",
            "ldrd {da}, {db}, [{g}]\n",
            "ldrd r1, {c32}, [{g}, #8]\n",
            "add.w {m4}, r1, #4\n",
            "mov {n}, {np}\n",
            requant4_sums_pair!($stride),
            group_store!($store, $size),
            "ldrd r1, {c32}, [{g}, #8]\n",
            "add.w r1, r1, {np}, lsl #5\n",
            "adds {c32}, {c32}, #32\n",
            "strd r1, {c32}, [{g}, #8]\n",
            group_saturation!(),
            "subs {left}, {left}, #1\n",
            "bne 1b\n",
        )
    };
}

/// [`groups_loop_reg`] for one part: no part loop, the multipliers 32 bytes a group, every
/// pointer in a register (the caller reads nothing back) and no saturation test: with one part a
/// saturation cannot change the outputs (`conv_helium`'s `channels`), so the mask stays 0 and
/// `FPSCR.QC` may be left set. The multipliers' offsets (`q7`) are loaded once; `{n}` holds 32.
macro_rules! groups_loop_reg1 {
    ($store:literal, $size:literal) => {
        concat!(
            "vldrw.u32 q7, [{k}]\n",
            "mov.w {n}, #32\n",
            "1:\n",
            "vldrw.u32 q0, [{k}, #48]\n",
            "vldrw.u32 q6, [{c32}, q0]\n",
            "vmov q5, q6\n",
            "add.w {m4}, r1, #4\n",
            "vldrw.u32 q2, [r1, q7]\n",
            "vldrb.u32 q3, [{m4}, q7]\n",
            "vneg.s32 q3, q3\n",
            "vadd.i32 q4, q3, {n}\n",
            requant4_part!("{da}", "16", "q6"),
            requant4_part!("{db}", "16", "q5"),
            "vrshr.s32 q6, q6, #8\n",
            "vrshr.s32 q5, q5, #8\n",
            clamp_pair!("16", "32"),
            $store, " q6, [r0], #", $size, "\n",
            $store, " q5, [r2], #", $size, "\n",
            "adds r1, r1, #32\n",
            "adds {c32}, {c32}, #32\n",
            "subs {left}, {left}, #1\n",
            "bne 1b\n",
        )
    };
}

/// The table piece of [`groups_loop`] (after the clamp to `[k + 16, k + 32]`): both pixels
/// through the sigmoid or tanh table (`{da}` as the table one entry on), then the clamp to
/// `[k + 64, k + 80]`.
macro_rules! groups_lut {
    () => {
        concat!(
            "add.w {da}, {tab}, #2\n",
            lut_pair_piece!("q6", "{da}"),
            lut_pair_piece!("q5", "{da}"),
            clamp_pair!("64", "80"),
        )
    };
}

/// The group loops of one output type (parts `$stride` bytes apart), with and without a table.
macro_rules! narrow_groups_fn {
    ($store:literal, $size:literal, $name:ident, $stride:literal) => {
        #[inline(always)]
        unsafe fn $name(g: *mut GroupState, k: &Requant4, table: Option<&[i16; 1025]>) {
            // SAFETY: the caller's bounds (`requant4_groups`); registers as listed.
            unsafe {
                match table {
                    None => asm!(
                        groups_loop_reg!($store, $size, $stride),
                        g = in(reg) g,
                        k = in(reg) k as *const Requant4,
                        np = in(reg) (*g).np,
                        left = inout(reg) (*g).left => _,
                        c32 = out(reg) _,
                        da = out(reg) _,
                        db = out(reg) _,
                        n = out(reg) _,
                        m4 = out(reg) _,
                        out("r0") _,
                        out("r1") _,
                        out("r2") _,
                        out("d0") _, out("d1") _, out("d2") _, out("d3") _, out("d4") _, out("d5") _, out("d6") _, out("d7") _,
                        out("d8") _, out("d9") _, out("d10") _, out("d11") _, out("d12") _, out("d13") _, out("d14") _, out("d15") _,
                        options(nostack),
                    ),
                    Some(t) => asm!(
                        groups_loop!($store, $size, $stride, groups_lut!()),
                        g = in(reg) g,
                        k = in(reg) k as *const Requant4,
                        tab = in(reg) t.as_ptr(),
                        c32 = out(reg) _,
                        da = out(reg) _,
                        db = out(reg) _,
                        n = out(reg) _,
                        m4 = out(reg) _,
                        out("r0") _,
                        out("r1") _,
                        out("r2") _,
                        out("d0") _, out("d1") _, out("d2") _, out("d3") _, out("d4") _, out("d5") _, out("d6") _, out("d7") _,
                        out("d8") _, out("d9") _, out("d10") _, out("d11") _, out("d12") _, out("d13") _, out("d14") _, out("d15") _,
                        options(nostack),
                    ),
                }
            }
        }
    };
}

/// The [`Narrow`] kernels of one output type: [`requant4`]'s and [`requant4_lut`]'s, parts 32
/// bytes apart, and their twins for the twelve-channel block's table (parts 96 bytes apart,
/// [`requant4_wide`]).
macro_rules! narrow {
    ($t:ty, $store:literal, $size:literal) => {
        impl Narrow for $t {
            narrow_fns!($store, requant4_n, requant4_lut_n, "32");
            narrow_fns!($store, requant4w_n, requant4w_lut_n, "96");
            narrow_pair_fn!($store, requant4x2_n, "32");
            narrow_pair_fn!($store, requant4x2w_n, "96");
            narrow_groups_fn!($store, $size, requant4g_n, "32");
            narrow_groups_fn!($store, $size, requant4gw_n, "96");
            #[inline(always)]
            unsafe fn requant4g1_n(g: *mut GroupState, k: &Requant4) {
                // SAFETY: the caller's bounds (`requant4_groups`, one part); registers as listed;
                // `g` is read before the loop and not written (its mask stays 0).
                unsafe {
                    let g = &*g;
                    asm!(
                        groups_loop_reg1!($store, $size),
                        k = in(reg) k as *const Requant4,
                        left = inout(reg) g.left => _,
                        c32 = inout(reg) g.bias => _,
                        da = inout(reg) g.da => _,
                        db = inout(reg) g.db => _,
                        n = out(reg) _,
                        m4 = out(reg) _,
                        inout("r0") g.oa => _,
                        inout("r1") g.mult => _,
                        inout("r2") g.ob => _,
                        out("d0") _, out("d1") _, out("d2") _, out("d3") _, out("d4") _, out("d5") _, out("d6") _, out("d7") _,
                        out("d8") _, out("d9") _, out("d10") _, out("d11") _, out("d12") _, out("d13") _, out("d14") _, out("d15") _,
                        options(nostack),
                    )
                }
            }
        }
    };
}

narrow!(u8, "vstrb.32", "4");
narrow!(i8, "vstrb.32", "4");
narrow!(i16, "vstrh.32", "8");

/// The convolution epilogue of four output channels `c .. c + 4` at one pixel, on 32-bit lanes:
/// `out[i] = clamp(rshift_round(bias[c + i] + sum_p requantize_i32(d[8 p + i], mult(c + i, p)),
/// 8), lo, hi)` over the parts `p < np`, where `mult(c, p)` is the `MultRef` entry at byte
/// `8 (c np + p)` of `mult` (multiplier word, shift byte) and the bias the low word of the
/// `BiasRef` entry at byte `8 c` of `bias`.
///
/// Each `requantize_i32(x, m)` with shift `s` is computed from the product's high word `h` and
/// low word `l` (`VMULH`, `VMUL`): `h 2^(32-s) + rshift_round_u(l, s)` for `s <= 32` (`h 2^32` is
/// a multiple of `2^s`, so the rounding only sees `l`), `rshift_round(h, s - 32)` for `s > 32`
/// (then `l < 2^32 <= 2^(s-1)`: its rounded term is 0 and it cannot carry into the result): one
/// formula, `VQRSHL(h, 32 - s) + VRSHL_u(l, -s)`. `VRSHL`, `VQRSHL` and `VRSHR` round in full
/// precision. Every step is exact unless a saturating instruction (`VQRSHL`, `VQADD`) saturates,
/// and then it sets `FPSCR.QC`: the result equals the portable epilogue's (`conv`'s
/// `finish_short` of the summed `requantize_i32`s, then the clamp) whenever [`take_qc`] reports
/// no saturation afterwards; the caller recomputes the outputs otherwise.
///
/// # Safety
/// `d` points at `8 (np - 1) + 4` readable `i32`s (four per part, parts 32 bytes apart); `mult`
/// is 4-byte aligned with `8 (4 np)` readable bytes; `k` is `Requant4::new(np, ..)`; `bias` is
/// 4-byte aligned with 32 readable bytes; `out` points at four writable values (2-byte aligned
/// for i16); `np >= 1`. The caller checks once per layer that every shift byte is in `8..=62`
/// and every bias within `i32` (otherwise the result is not the portable one, but nothing
/// outside these bounds is read or written).
#[inline(always)]
pub unsafe fn requant4<O: Narrow>(d: *const i32, mult: *const u8, k: &Requant4, np: usize, bias: *const u8, out: *mut O) {
    // SAFETY: forwarded.
    unsafe { O::requant4_n(d, mult, k, np, bias, out) }
}

/// [`requant4`] followed by a sigmoid or tanh table (`arith::lut`'s `table16`: entries `i` and
/// `i + 1` of `table` at `u = x + 32768`, `i = u >> 6`, `a + rshift_round((b - a) (u & 63), 6)`)
/// of the clamped value `x`, then the clamp to `k.out_lo..=k.out_hi` (the output type's range,
/// [`Requant4::with_out`]) and the narrowing store: `out[i] = clamp(f(requant4's value))`.
///
/// # Safety
/// As [`requant4`], and `k.lo..=k.hi` within `-32768..=32767` (the table's input range).
#[inline(always)]
pub unsafe fn requant4_lut<O: Narrow>(d: *const i32, mult: *const u8, k: &Requant4, np: usize, bias: *const u8, table: &[i16; 1025], out: *mut O) {
    // SAFETY: forwarded.
    unsafe { O::requant4_lut_n(d, mult, k, np, bias, table, out) }
}

/// [`requant4`] reading the dot products of a twelve-channel block's table
/// ([`PartLens::dots12`]): four values per part, parts 96 bytes apart.
///
/// # Safety
/// As [`requant4`], with `d` pointing at `24 (np - 1) + 4` readable `i32`s.
#[inline(always)]
pub unsafe fn requant4_wide<O: Narrow>(d: *const i32, mult: *const u8, k: &Requant4, np: usize, bias: *const u8, out: *mut O) {
    // SAFETY: forwarded.
    unsafe { O::requant4w_n(d, mult, k, np, bias, out) }
}

/// [`requant4_lut`] reading a twelve-channel block's table (as [`requant4_wide`]).
///
/// # Safety
/// As [`requant4_lut`], with `d` pointing at `24 (np - 1) + 4` readable `i32`s.
#[inline(always)]
pub unsafe fn requant4_lut_wide<O: Narrow>(d: *const i32, mult: *const u8, k: &Requant4, np: usize, bias: *const u8, table: &[i16; 1025], out: *mut O) {
    // SAFETY: forwarded.
    unsafe { O::requant4w_lut_n(d, mult, k, np, bias, table, out) }
}

/// [`requant4`] (`table` `None`) or [`requant4_lut`] (`Some`) of two pixels at once: pixel `i`'s
/// dot products at `d[i]` (four per part, parts 32 bytes apart, or 96 with `wide`), its four
/// outputs at `out[i]`; the same multipliers and biases. Each part's multipliers and shifts are
/// gathered once for both pixels. The same values as two calls, the same `FPSCR.QC` semantics.
///
/// # Safety
/// As [`requant4`] (or [`requant4_lut`] with a table) for each pixel; `out[0]` and `out[1]` do
/// not overlap.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub unsafe fn requant4_pair<O: Narrow>(d: [*const i32; 2], mult: *const u8, k: &Requant4, np: usize, bias: *const u8, table: Option<&[i16; 1025]>, wide: bool, out: [*mut O; 2]) {
    // SAFETY: forwarded.
    unsafe {
        if wide {
            O::requant4x2w_n(d, mult, k, np, bias, table, out)
        } else {
            O::requant4x2_n(d, mult, k, np, bias, table, out)
        }
    }
}

/// [`requant4_pair`] for `groups` consecutive groups of four channels in one call: group `g`'s
/// dot products at `d[i] + 4 g` (pixel `i`; parts 32 or, with `wide`, 96 bytes apart), its
/// multipliers at `mult + 32 np g`, biases at `bias + 32 g`, outputs at `out[i] + 4 g`. Returns
/// the groups whose epilogue saturated (`FPSCR.QC` tested and cleared after each group: bit `g`);
/// the outputs are [`requant4_pair`]'s. With one part and no table nothing is tested (a one-part
/// saturation cannot change the outputs): the mask is 0 and `FPSCR.QC` may be left set.
///
/// # Safety
/// As [`requant4_pair`] for every group (`d[i] + 4 g`, ..., each within its bounds); `1 <=
/// groups <= 32`; the outputs of all groups of both pixels do not overlap.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub unsafe fn requant4_groups<O: Narrow>(d: [*const i32; 2], mult: *const u8, k: &Requant4, np: usize, bias: *const u8, table: Option<&[i16; 1025]>, wide: bool, out: [*mut O; 2], groups: usize) -> u32 {
    let mut g = GroupState { da: d[0], db: d[1], mult, bias, oa: out[0] as usize, ob: out[1] as usize, left: groups as u32, np: np as u32, mask: 0, bit: 1 };
    // SAFETY: forwarded; `g` lives across the call.
    unsafe {
        if np == 1 && table.is_none() {
            O::requant4g1_n(&mut g, k)
        } else if wide {
            O::requant4gw_n(&mut g, k, table)
        } else {
            O::requant4g_n(&mut g, k, table)
        }
    }
    g.mask
}

/// Whether a saturating vector instruction saturated since the flag was last cleared
/// (`FPSCR.QC`), clearing it.
#[inline(always)]
pub fn take_qc() -> bool {
    let fpscr: u32;
    // SAFETY: reads the floating-point status and control register.
    unsafe { asm!("vmrs {0}, fpscr", out(reg) fpscr, options(nomem, nostack, preserves_flags)) };
    let qc = fpscr & (1 << 27) != 0;
    if qc {
        // SAFETY: writes back the same register with QC cleared (LTPSIZE and the rest unchanged).
        unsafe { asm!("vmsr fpscr, {0}", in(reg) fpscr & !(1 << 27), options(nomem, nostack)) };
    }
    qc
}

/// The sum of the population counts of the twenty words of `w` (the full-resolution refinement's
/// census Hamming distances: nine 64-bit codes and a zero pair): Cortex-M has no population
/// count, and the compiler's 64-bit bit trick took about 26 instructions per code. Here four
/// words a vector: the bit trick's 2-bit and 4-bit sums on 32-bit lanes, byte counts (at most 8
/// per byte and vector, so at most 40 after five vectors: no carry between bytes), one `VADDV.U8`
/// at the end. The same integer as `w.iter().map(|x| x.count_ones()).sum()`.
#[inline]
pub fn popcount20(w: &[u32; 20]) -> u32 {
    let n: u32;
    // Four words' counts added to q4, written out five times (not `.rept`: the compiler sizes an
    // `asm!` block by its lines, and a block larger than it thinks can put branches or literal
    // pools around it out of place).
    macro_rules! four_words {
        () => {
            "vldrw.u32 q0, [{p}], #16\nvshr.u32 q1, q0, #1\nvand q1, q1, q7\nvsub.i32 q0, q0, q1\nvshr.u32 q1, q0, #2\nvand q1, q1, q6\nvand q0, q0, q6\nvadd.i32 q0, q0, q1\nvshr.u32 q1, q0, #4\nvadd.i32 q0, q0, q1\nvand q0, q0, q5\nvadd.i32 q4, q4, q0"
        };
    }
    // SAFETY: reads the 80 bytes of `w`; the sum in an even register (`VADDV`).
    unsafe {
        asm!(
            "vmov.i8 q7, #0x55",
            "vmov.i8 q6, #0x33",
            "vmov.i8 q5, #0x0f",
            "vmov.i32 q4, #0",
            four_words!(),
            four_words!(),
            four_words!(),
            four_words!(),
            four_words!(),
            "vaddv.u8 r0, q4",
            p = inout(reg) w.as_ptr() => _,
            out("r0") n,
            out("d0") _, out("d1") _, out("d2") _, out("d3") _, out("d8") _, out("d9") _, out("d10") _, out("d11") _,
            out("d12") _, out("d13") _, out("d14") _, out("d15") _,
            options(nostack, readonly),
        );
    }
    n
}

/// Census codes of the interior pixels of one image row (the full-resolution refinement's
/// `fullres::census_row`): `grey` holds the seven grey rows `y - 3 ..= y + 3` (`w` bytes each),
/// and for every `x` in `3 .. w - 3` (no clamped neighbour) `out[x]` gets the 48-bit code (bit
/// `b` set when the `b`-th neighbour of the 7x7 window, row-major without the centre, is darker
/// than the centre). Sixteen pixels per vector: per bit one load of the sixteen neighbours,
/// `VHSUB.U8` (`(n - c) >> 1` in full precision: bit 7 set exactly when `n < c`) and `VSRI.8 #1`,
/// which shifts the byte being built right and inserts that bit at the top, so after eight bits a
/// byte lane holds one byte of a code; a scatter store (`VSTRB.8` with offsets `8 i + k`) puts byte
/// `k` of the sixteen codes in place (bytes 6 and 7 are 0). Tail-predicated: no scalar tail.
/// Nothing happens unless `w >= 7`, `grey.len() >= 7 w` and `out.len() >= w`; `out[..3]` and
/// `out[w - 3..]` are left as they are.
pub fn census(grey: &[u8], w: usize, out: &mut [u64]) {
    if w < 7 || grey.len() < 7 * w || out.len() < w {
        return;
    }
    let rows: [*const u8; 7] = core::array::from_fn(|k| grey.as_ptr().wrapping_add(k * w));
    // SAFETY: pixel `x` in `3 .. w - 3` reads bytes `x - 3 ..= x + 3` of each of the seven rows
    // (inside `grey` by the check above; the last vector is tail-predicated, so no lane past
    // `w - 4` is read) and writes the eight bytes of `out[x]` (inside `out`).
    unsafe { muir_mve_census(&rows, w - 6, out.as_mut_ptr().wrapping_add(3)) };
}

core::arch::global_asm!(
    ".syntax unified",
    ".thumb",
    ".cpu cortex-m55",
    ".section .text.muir_mve_census,\"ax\",%progbits",
    ".global muir_mve_census",
    ".type muir_mve_census,%function",
    ".p2align 2",
    ".thumb_func",
    // r0 = the seven row pointers (column 0 = the first pixel's left neighbour at dx = -3),
    // r1 = pixels, r2 = out. Rows in r0-r6, out in r8, q7 the scatter offsets 0, 8, .., 120, q6
    // the centres, q5 zero; the code byte being built alternates between q0 and q1.
    "muir_mve_census:",
    "    push {{r4-r11, lr}}",
    "    mov r12, r0",
    "    mov r10, r1",
    "    mov r8, r2",
    "    ldr r0, [r12]",
    "    ldr r1, [r12, #4]",
    "    ldr r2, [r12, #8]",
    "    ldr r3, [r12, #12]",
    "    ldr r4, [r12, #16]",
    "    ldr r5, [r12, #20]",
    "    ldr r6, [r12, #24]",
    "    mov.w r12, #0",
    "    vidup.u8 q7, r12, #8",
    "    vmov.i8 q5, #0",
    "    dlstp.8 lr, r10",
    "1:",
    "    vldrb.u8 q6, [r3, #3]",
    "    vldrb.u8 q1, [r0, #0]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r0, #1]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r0, #2]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r0, #3]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r0, #4]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r0, #5]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r0, #6]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r1, #0]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    add.w r9, r8, #0",
    "    vstrb.8 q0, [r9, q7]",
    "    vldrb.u8 q1, [r1, #1]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r1, #2]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r1, #3]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r1, #4]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r1, #5]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r1, #6]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r2, #0]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r2, #1]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    add.w r9, r8, #1",
    "    vstrb.8 q0, [r9, q7]",
    "    vldrb.u8 q1, [r2, #2]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r2, #3]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r2, #4]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r2, #5]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r2, #6]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r3, #0]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r3, #1]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r3, #2]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    add.w r9, r8, #2",
    "    vstrb.8 q0, [r9, q7]",
    "    vldrb.u8 q1, [r3, #4]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r3, #5]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r3, #6]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r4, #0]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r4, #1]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r4, #2]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r4, #3]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r4, #4]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    add.w r9, r8, #3",
    "    vstrb.8 q0, [r9, q7]",
    "    vldrb.u8 q1, [r4, #5]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r4, #6]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r5, #0]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r5, #1]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r5, #2]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r5, #3]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r5, #4]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r5, #5]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    add.w r9, r8, #4",
    "    vstrb.8 q0, [r9, q7]",
    "    vldrb.u8 q1, [r5, #6]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r6, #0]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r6, #1]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r6, #2]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r6, #3]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r6, #4]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    vldrb.u8 q1, [r6, #5]",
    "    vhsub.u8 q1, q1, q6",
    "    vsri.8 q1, q0, #1",
    "    vldrb.u8 q0, [r6, #6]",
    "    vhsub.u8 q0, q0, q6",
    "    vsri.8 q0, q1, #1",
    "    add.w r9, r8, #5",
    "    vstrb.8 q0, [r9, q7]",
    "    add.w r9, r8, #6",
    "    vstrb.8 q5, [r9, q7]",
    "    add.w r9, r8, #7",
    "    vstrb.8 q5, [r9, q7]",
    "    add.w r8, r8, #128",
    "    adds r0, #16",
    "    adds r1, #16",
    "    adds r2, #16",
    "    adds r3, #16",
    "    adds r4, #16",
    "    adds r5, #16",
    "    adds r6, #16",
    "    letp lr, 1b",
    "    pop {{r4-r11, pc}}",
    ".size muir_mve_census, . - muir_mve_census",
);

/// Population counts of the bytes 0..=255 (a gather load counts sixteen bytes at once).
// Evaluated at compile time: an index out of range would be a build error, not a panic.
#[allow(clippy::indexing_slicing)]
static POPCOUNT8: [u8; 256] = {
    let mut t = [0u8; 256];
    let mut i = 0;
    while i < 256 {
        t[i] = (i as u32).count_ones() as u8;
        i += 1;
    }
    t
};

/// Arguments of `muir_mve_cost_pairs` (one pointer for the assembly function).
#[repr(C)]
struct CostArgs {
    /// The nine left codes, each twice (`[L, L]`, 16 bytes), rows then columns.
    ld: *const u64,
    /// Per census row, the right code at column `x - 2 - d` of the first pair.
    right: [*const u64; 3],
    tab: *const u8,
    out: *mut u16,
    pairs: usize,
}

/// The refinement's costs (`fullres::cost`: the 3x3 box sum of census Hamming distances between
/// the left codes at columns `x - 1 ..= x + 1` and the right codes `d` columns to the left) of the
/// candidates `d0 .. d0 + 2 pairs` of pixel `x` into `out[..2 pairs]`, for `1 <= x`,
/// `x + 1 < w` and `d0 + 2 pairs <= x` (no clamped column). Two candidates per vector: sixteen
/// bytes of right codes `[R(q - d - 1), R(q - d)]` XOR the left code twice, the bytes' population
/// counts by one gather load from a 256-entry table, nine such byte vectors summed (at most 72 a
/// byte); `VADDV` and `VMLADAV` with a mask of the low eight lanes split the two sums. The same
/// integers as the portable cost. `left` and `right` are the three census rows (`w` codes each
/// at least); returns `false`, having done nothing, when a precondition fails.
pub fn cost_pairs(left: [&[u64]; 3], right: [&[u64]; 3], w: usize, x: usize, d0: usize, pairs: usize, out: &mut [u16]) -> bool {
    if pairs == 0 || x == 0 || x + 1 >= w || d0.saturating_add(2 * pairs) > x || out.len() < 2 * pairs || left.iter().chain(right.iter()).any(|r| r.len() < w) {
        return false;
    }
    let mut ld = [0u64; 18];
    for (slots, row) in ld.chunks_exact_mut(6).zip(left) {
        if let Some(cols) = row.get(x - 1..x + 2) {
            for (slot, c) in slots.chunks_exact_mut(2).zip(cols) {
                slot.fill(*c);
            }
        }
    }
    let args = CostArgs {
        ld: ld.as_ptr(),
        right: right.map(|r| r.as_ptr().wrapping_add(x - 2 - d0)),
        tab: POPCOUNT8.as_ptr(),
        out: out.as_mut_ptr(),
        pairs,
    };
    // SAFETY: pair `i` reads right codes `x - 2 - d0 - 2 i ..= x - d0 - 2 i + 1 <= x + 1 < w`,
    // the lowest `x - d0 - 2 pairs >= 0`, inside each row (`w` codes at least); the table's
    // gathers index bytes (at most 255); it writes `out[..2 pairs]`.
    unsafe { muir_mve_cost_pairs(&args) };
    true
}

core::arch::global_asm!(
    ".syntax unified",
    ".thumb",
    ".cpu cortex-m55",
    ".section .text.muir_mve_cost_pairs,\"ax\",%progbits",
    ".global muir_mve_cost_pairs",
    ".type muir_mve_cost_pairs,%function",
    ".p2align 2",
    ".thumb_func",
    // r0 = `CostArgs`. r4 the doubled left codes, r5-r7 the right rows, r8 the table, r10 out,
    // q7 the mask of lanes 0..7 (ones), q3 the byte sums. Lanes 0..7 hold candidate d + 1, lanes
    // 8..15 candidate d.
    "muir_mve_cost_pairs:",
    "    push {{r4-r11, lr}}",
    "    ldr r4, [r0]",
    "    ldr r5, [r0, #4]",
    "    ldr r6, [r0, #8]",
    "    ldr r7, [r0, #12]",
    "    ldr r8, [r0, #16]",
    "    ldr r10, [r0, #20]",
    "    ldr r11, [r0, #24]",
    "    movs r9, #0",
    "    vmov.i8 q7, #1",
    "    vmov.32 q7[2], r9",
    "    vmov.32 q7[3], r9",
    "    dls lr, r11",
    "1:",
    "    vldrw.u32 q0, [r4, #0]",
    "    vldrw.u32 q1, [r5, #0]",
    "    veor q1, q1, q0",
    "    vldrb.u8 q3, [r8, q1]",
    "    vldrw.u32 q0, [r4, #16]",
    "    vldrw.u32 q1, [r5, #8]",
    "    veor q1, q1, q0",
    "    vldrb.u8 q2, [r8, q1]",
    "    vadd.i8 q3, q3, q2",
    "    vldrw.u32 q0, [r4, #32]",
    "    vldrw.u32 q1, [r5, #16]",
    "    veor q1, q1, q0",
    "    vldrb.u8 q2, [r8, q1]",
    "    vadd.i8 q3, q3, q2",
    "    vldrw.u32 q0, [r4, #48]",
    "    vldrw.u32 q1, [r6, #0]",
    "    veor q1, q1, q0",
    "    vldrb.u8 q2, [r8, q1]",
    "    vadd.i8 q3, q3, q2",
    "    vldrw.u32 q0, [r4, #64]",
    "    vldrw.u32 q1, [r6, #8]",
    "    veor q1, q1, q0",
    "    vldrb.u8 q2, [r8, q1]",
    "    vadd.i8 q3, q3, q2",
    "    vldrw.u32 q0, [r4, #80]",
    "    vldrw.u32 q1, [r6, #16]",
    "    veor q1, q1, q0",
    "    vldrb.u8 q2, [r8, q1]",
    "    vadd.i8 q3, q3, q2",
    "    vldrw.u32 q0, [r4, #96]",
    "    vldrw.u32 q1, [r7, #0]",
    "    veor q1, q1, q0",
    "    vldrb.u8 q2, [r8, q1]",
    "    vadd.i8 q3, q3, q2",
    "    vldrw.u32 q0, [r4, #112]",
    "    vldrw.u32 q1, [r7, #8]",
    "    veor q1, q1, q0",
    "    vldrb.u8 q2, [r8, q1]",
    "    vadd.i8 q3, q3, q2",
    "    vldrw.u32 q0, [r4, #128]",
    "    vldrw.u32 q1, [r7, #16]",
    "    veor q1, q1, q0",
    "    vldrb.u8 q2, [r8, q1]",
    "    vadd.i8 q3, q3, q2",
    "    vaddv.u8 r0, q3",
    "    vmladav.u8 r2, q3, q7",
    "    subs r0, r0, r2",
    "    strh r0, [r10], #2",
    "    strh r2, [r10], #2",
    "    subs r5, #16",
    "    subs r6, #16",
    "    subs r7, #16",
    "    le lr, 1b",
    "    pop {{r4-r11, pc}}",
    ".size muir_mve_cost_pairs, . - muir_mve_cost_pairs",
);

unsafe extern "C" {
    fn muir_mve_census(rows: *const [*const u8; 7], n: usize, out: *mut u64);
    fn muir_mve_cost_pairs(args: *const CostArgs);
}

/// The least of `s`'s values (`None` when empty): eight lanes per `VMINV.U16`, tail-predicated.
#[inline]
pub fn min_u16(s: &[u16]) -> Option<u16> {
    if s.is_empty() {
        return None;
    }
    let mut m = u16::MAX as u32;
    // SAFETY: reads `s.len()` values (tail-predicated: disabled lanes are neither loaded nor
    // compared).
    unsafe {
        asm!(
            "dlstp.16 lr, {n}",
            "2:",
            "vldrh.u16 q0, [{p}], #16",
            "vminv.u16 {m}, q0",
            "letp lr, 2b",
            n = in(reg) s.len(),
            p = inout(reg) s.as_ptr() => _,
            m = inout(reg) m,
            out("lr") _,
            out("d0") _, out("d1") _,
            options(nostack, readonly),
        );
    }
    Some(m as u16)
}

/// One step of a semi-global matching path on eight candidates a vector (the refinement's
/// `fullres::path_step` once its predecessor's costs are laid out as a window):
/// `out[k] = cost[k] + min(win[k + 1], min(win[k], win[k + 2], mp2) + p1, mp2) - m` in wrapping
/// `u16` arithmetic, for `k < min(cost.len(), out.len(), win.len() - 2)`. With `mp2 + p1 <= 0xFFFF`
/// no step overflows: it is `min(mp2, win[k + 1], win[k] + p1, win[k + 2] + p1)` computed exactly
/// (adding `p1` to the smaller neighbour after capping it at `mp2`, which changes nothing since
/// `mp2 + p1 > mp2`). Tail-predicated, no saturating instruction.
#[inline]
pub fn path_update(win: &[u16], cost: &[u16], p1: u16, m: u16, mp2: u16, out: &mut [u16]) {
    let n = cost.len().min(out.len()).min(win.len().saturating_sub(2));
    if n == 0 {
        return;
    }
    // SAFETY: lane `k < n` reads `win[k ..= k + 2]` (`k + 2 < win.len()`), `cost[k]` and writes
    // `out[k]` (tail-predicated: disabled lanes are neither loaded nor stored).
    unsafe {
        asm!(
            "vdup.16 q3, {mp2}",
            "dlstp.16 lr, {n}",
            "2:",
            "vldrh.u16 q1, [{w}, #4]",
            "vldrh.u16 q2, [{w}, #2]",
            "vldrh.u16 q0, [{w}], #16",
            "vmin.u16 q0, q0, q1",
            "vmin.u16 q0, q0, q3",
            "vadd.i16 q0, q0, {p1}",
            "vmin.u16 q0, q0, q2",
            "vmin.u16 q0, q0, q3",
            "vsub.i16 q0, q0, {m}",
            "vldrh.u16 q1, [{c}], #16",
            "vadd.i16 q0, q0, q1",
            "vstrh.16 q0, [{o}], #16",
            "letp lr, 2b",
            n = in(reg) n,
            mp2 = in(reg) mp2 as u32,
            p1 = in(reg) p1 as u32,
            m = in(reg) m as u32,
            w = inout(reg) win.as_ptr() => _,
            c = inout(reg) cost.as_ptr() => _,
            o = inout(reg) out.as_mut_ptr() => _,
            out("lr") _,
            out("d0") _, out("d1") _, out("d2") _, out("d3") _, out("d4") _, out("d5") _, out("d6") _, out("d7") _,
            options(nostack),
        );
    }
}

/// The MGA softmax weights, four keys a vector, in place: each `e[k]`, the logit minus the
/// query's maximum, becomes `exp_q11(clamp(requantize_i32(e[k], m), -32768, 0))`, for shifts
/// `2..=62` (other shifts: nothing is written, `None`). Returns the largest weight and the sum
/// of the weights.
///
/// The requantisation is [`requant4`]'s formula, `VQRSHL(h, 32 - s) + VRSHL_u(l, -s)` on the
/// product's high and low words. It is exact where nothing saturates; where `VQRSHL` or `VQADD`
/// saturates the exact value lies beyond `i32` on the same side (the shifted high word is a
/// multiple of `2^(32 - s)` and the rounded low word is in `0 ..= 2^(32 - s) <= 2^30`), so after
/// the clamp to `-32768 ..= 0` both give the same value. `FPSCR.QC` is cleared afterwards (the
/// convolution epilogue reads it). The table read is `exp_q11`'s: index `i = min(u >> 5, 1023)`
/// and fraction `u - 32 i` (32 at `u = 32768`, which gives the last entry exactly), two gather
/// loads and `a + rshift_round((b - a) f, 5)`.
#[inline]
pub fn exp_weights(e: &mut [i32], m: i32, shift: u8) -> Option<(i32, i64)> {
    let n = e.len();
    if !(2..=62).contains(&shift) {
        return None;
    }
    if n == 0 {
        return Some((0, 0));
    }
    let t = crate::arith::lut::exp_table();
    let (mut max, mut lo, mut hi) = (0i32, 0u32, 0u32);
    // SAFETY: lane `k < n` reads and then writes `e[k]` (tail-predicated: disabled lanes are
    // neither loaded nor stored) and gathers table entries `i` and `i + 1` with `i <= 1023`
    // (1025 entries). VADDLVA takes an even/odd register pair (r0/r1).
    unsafe {
        asm!(
            "vdup.32 q7, {m}",
            "vmov.i32 q6, #0x8000",
            "vneg.s32 q6, q6",
            "vmov.i32 q5, #0",
            "mov {m}, #1023",
            "vdup.32 q4, {m}",
            "dlstp.32 lr, {n}",
            "2:",
            "vldrw.u32 q0, [{d}], #16",
            "vmulh.s32 q1, q0, q7",
            "vmul.i32 q0, q0, q7",
            "vqrshl.s32 q1, {sl}",
            "vrshl.u32 q0, {sr}",
            "vqadd.s32 q0, q1, q0",
            "vmax.s32 q0, q0, q6",
            "vmin.s32 q0, q0, q5",
            "vsub.i32 q0, q0, q6",
            "vshr.u32 q1, q0, #5",
            "vmin.u32 q1, q1, q4",
            "vshl.i32 q2, q1, #5",
            "vsub.i32 q0, q0, q2",
            "vldrh.u32 q2, [{tab}, q1, uxtw #1]",
            "vldrh.u32 q3, [{tab1}, q1, uxtw #1]",
            "vsub.i32 q3, q3, q2",
            "vmul.i32 q3, q3, q0",
            "vrshr.s32 q3, q3, #5",
            "vadd.i32 q2, q2, q3",
            "vmaxv.s32 {max}, q2",
            "vaddlva.s32 r0, r1, q2",
            "vstrw.32 q2, [{e}], #16",
            "letp lr, 2b",
            m = inout(reg) m => _,
            n = in(reg) n,
            d = inout(reg) e.as_ptr() => _,
            e = inout(reg) e.as_mut_ptr() => _,
            sl = in(reg) 32 - shift as i32,
            sr = in(reg) -(shift as i32),
            tab = in(reg) t.as_ptr(),
            tab1 = in(reg) t.as_ptr().wrapping_add(1),
            max = inout(reg) max,
            inout("r0") lo,
            inout("r1") hi,
            out("lr") _,
            out("d0") _, out("d1") _, out("d2") _, out("d3") _, out("d4") _, out("d5") _, out("d6") _, out("d7") _,
            out("d8") _, out("d9") _, out("d10") _, out("d11") _, out("d12") _, out("d13") _, out("d14") _, out("d15") _,
            options(nostack),
        );
    }
    take_qc();
    Some((max, ((hi as u64) << 32 | lo as u64) as i64))
}

/// The post-pooled correlation lookup's samples of one level in i32 (`corr::lookup_with`'s i32
/// path), four samples a vector: `out[t] = sat_i16(requantize_i32((256 - a) (x1 - x0) + a (y1 -
/// y0), mult))` in wrapping i32 arithmetic, where `x0`, `x1`, `y0`, `y1` are the low words of
/// `pre[t sl]`, `pre[t sl + sl]`, `pre[t sl + 1]` and `pre[t sl + 1 + sl]`, for `t < out.len()`.
/// Returns false, with nothing written, where `sl` is 0 or above 2^20, `pre` is too short (it
/// needs `(out.len() - 1) sl + sl + 2` values) or the shift is outside `1..=62`.
///
/// The low words are read by four word gathers from two vectors of addresses (lane `t`: `pre[t
/// sl]` and `pre[t sl + sl]`, the `y` words 8 bytes further), stepped by `32 sl` bytes; the
/// numerator as `256 (x1 - x0) + a ((y1 - y0) - (x1 - x0))` (the same value modulo `2^32`); the
/// requantisation is [`exp_weights`]'s `VQRSHL(h, 32 - s) + VRSHL_u(l, -s)` on the product's
/// high and low words, exact where nothing saturates; where `VQRSHL` or `VQADD` saturates the
/// exact value lies beyond `i32` on the same side, so after the saturating narrowing to i16
/// (`VQMOVNB`) both give the same value. `FPSCR.QC` is cleared afterwards (the convolution
/// epilogue reads it).
#[inline]
pub fn lookup_samples(pre: &[i64], sl: usize, a: i32, mult: crate::arith::Multiplier, out: &mut [i16]) -> bool {
    let k = out.len();
    if k == 0 {
        return true;
    }
    if sl == 0 || sl > 1 << 20 || !(1..=62).contains(&mult.shift) || pre.len() < (k - 1) * sl + sl + 2 {
        return false;
    }
    let s = mult.shift as i32;
    // SAFETY: lane `t < k` gathers the low words of `pre[t sl + {0, sl, 1, 1 + sl}]`, all below
    // `(k - 1) sl + sl + 2 <= pre.len()` (checked; 8-byte aligned), and writes `out[t]`
    // (tail-predicated: disabled lanes are neither loaded nor stored).
    unsafe {
        asm!(
            "vdup.32 q7, {m}",
            "vidup.u32 q4, r0, #1",
            "vmul.i32 q4, q4, {bsl}",
            "vadd.i32 q4, q4, {base}",
            "vadd.i32 q5, q4, {bsl}",
            "lsl {bsl}, {bsl}, #2",
            "dlstp.32 lr, {n}",
            "2:",
            "vldrw.u32 q0, [q4]",
            "vldrw.u32 q1, [q5]",
            "vldrw.u32 q2, [q4, #8]",
            "vldrw.u32 q3, [q5, #8]",
            "vsub.i32 q1, q1, q0",
            "vsub.i32 q3, q3, q2",
            "vsub.i32 q3, q3, q1",
            "vshl.i32 q1, q1, #8",
            "vmla.i32 q1, q3, {a}",
            "vmulh.s32 q0, q1, q7",
            "vmul.i32 q1, q1, q7",
            "vqrshl.s32 q0, {sl}",
            "vrshl.u32 q1, {sr}",
            "vqadd.s32 q0, q0, q1",
            "vqmovnb.s32 q0, q0",
            "vstrh.32 q0, [r1], #8",
            "vadd.i32 q4, q4, {bsl}",
            "vadd.i32 q5, q5, {bsl}",
            "letp lr, 2b",
            m = in(reg) mult.m,
            inout("r0") 0u32 => _,
            bsl = inout(reg) 8 * sl as u32 => _,
            base = in(reg) pre.as_ptr(),
            n = in(reg) k,
            a = in(reg) a,
            sl = in(reg) 32 - s,
            sr = in(reg) -s,
            inout("r1") out.as_mut_ptr() => _,
            out("lr") _,
            out("d0") _, out("d1") _, out("d2") _, out("d3") _, out("d4") _, out("d5") _, out("d6") _, out("d7") _,
            out("d8") _, out("d9") _, out("d10") _, out("d11") _, out("d14") _, out("d15") _,
            options(nostack),
        );
    }
    take_qc();
    true
}

/// The correlation window's in-row columns: `win[i] = f1 . col_i` (i8 x i8, sixteen products per
/// `VMLADAVA.S8`, tail-predicated) for `i < win.len()`, where `col_i` is `f2[i c .. (i + 1) c]`
/// and `c = f1.len()`; one assembly loop over the columns (a column's pointer stepped by `c`,
/// not by the loads' write-back, which a predicated tail runs past). Returns false, with nothing
/// written, when `c` is 0 or at least 2^16 (then `|sum| < 2^14 c` might leave i32) or `f2` holds
/// fewer than `win.len() c` values.
#[inline]
pub fn corr_window(f1: &[i8], f2: &[i8], win: &mut [i32]) -> bool {
    let (c, n) = (f1.len(), win.len());
    if c == 0 || c >= 1 << 16 || f2.len() < n * c {
        return false;
    }
    if n == 0 {
        return true;
    }
    // SAFETY: column `i < n` reads `f2[i c .. i c + c]` (inside: checked) and `f1` (`c` values),
    // tail-predicated (disabled lanes are not loaded), and writes `win[i]`.
    unsafe {
        asm!(
            "2:",
            "mov {x}, {f1}",
            "mov {y}, {col}",
            "add {col}, {col}, {c}",
            "movs r0, #0",
            "dlstp.8 lr, {c}",
            "3:",
            "vldrb.u8 q0, [{x}], #16",
            "vldrb.u8 q1, [{y}], #16",
            "vmlava.s8 r0, q0, q1",
            "letp lr, 3b",
            "str r0, [{o}], #4",
            "subs {n}, {n}, #1",
            "bne 2b",
            f1 = in(reg) f1.as_ptr(),
            col = inout(reg) f2.as_ptr() => _,
            c = in(reg) c,
            n = inout(reg) n => _,
            o = inout(reg) win.as_mut_ptr() => _,
            x = out(reg) _,
            y = out(reg) _,
            out("r0") _,
            out("lr") _,
            out("d0") _, out("d1") _, out("d2") _, out("d3") _,
            options(nostack),
        );
    }
    true
}

/// `eltwise::blend_q15` four lanes a vector: `h = sat_i16(h + rshift_round(z (q - h), 15))` for
/// the first `min` of the three lengths, in 32-bit lanes (`|z (q - h)| <= 2^15 (2^16 - 1) <
/// 2^31`; `VRSHR` rounds as `rshift_round` does; `VQMOVNB` saturates as `sat_i16`). `FPSCR.QC` is
/// cleared afterwards (the convolution epilogue reads it).
#[inline]
pub fn blend_q15(h: &mut [i16], z: &[i16], q: &[i16]) {
    let n = h.len().min(z.len()).min(q.len());
    if n == 0 {
        return;
    }
    // SAFETY: lane `i < n` reads `h[i]`, `z[i]`, `q[i]` and writes `h[i]` (tail-predicated:
    // disabled lanes are neither loaded nor stored).
    unsafe {
        asm!(
            "dlstp.32 lr, {n}",
            "2:",
            "vldrh.s32 q0, [r0]",
            "vldrh.s32 q1, [r1], #8",
            "vldrh.s32 q2, [r2], #8",
            "vsub.i32 q1, q1, q0",
            "vmul.i32 q1, q1, q2",
            "vrshr.s32 q1, q1, #15",
            "vadd.i32 q0, q0, q1",
            "vqmovnb.s32 q0, q0",
            "vstrh.32 q0, [r0], #8",
            "letp lr, 2b",
            n = in(reg) n,
            inout("r0") h.as_mut_ptr() => _,
            inout("r1") q.as_ptr() => _,
            inout("r2") z.as_ptr() => _,
            out("lr") _,
            out("d0") _, out("d1") _, out("d2") _, out("d3") _, out("d4") _, out("d5") _,
            options(nostack),
        );
    }
    take_qc();
}

/// `eltwise::mul_q15` four lanes a vector: `out = sat_i16(rshift_round(x m, 15))` for the first
/// `min` of the three lengths (`|x m| <= 2^30`); `FPSCR.QC` cleared afterwards.
#[inline]
pub fn mul_q15(x: &[i16], m: &[i16], out: &mut [i16]) {
    let n = out.len().min(x.len()).min(m.len());
    if n == 0 {
        return;
    }
    // SAFETY: lane `i < n` reads `x[i]`, `m[i]` and writes `out[i]` (tail-predicated).
    unsafe {
        asm!(
            "dlstp.32 lr, {n}",
            "2:",
            "vldrh.s32 q0, [r0], #8",
            "vldrh.s32 q1, [r1], #8",
            "vmul.i32 q0, q0, q1",
            "vrshr.s32 q0, q0, #15",
            "vqmovnb.s32 q0, q0",
            "vstrh.32 q0, [r2], #8",
            "letp lr, 2b",
            n = in(reg) n,
            inout("r0") x.as_ptr() => _,
            inout("r1") m.as_ptr() => _,
            inout("r2") out.as_mut_ptr() => _,
            out("lr") _,
            out("d0") _, out("d1") _, out("d2") _, out("d3") _,
            options(nostack),
        );
    }
    take_qc();
}

/// [`mul_q15`] by one Q0.15 scalar (`eltwise::mul_plane_q15`'s pixel): `out = sat_i16(
/// rshift_round(x m, 15))` for the first `min` of the two lengths; `FPSCR.QC` cleared afterwards.
#[inline]
pub fn mul_q15_by(x: &[i16], m: i16, out: &mut [i16]) {
    let n = out.len().min(x.len());
    if n == 0 {
        return;
    }
    // SAFETY: lane `i < n` reads `x[i]` and writes `out[i]` (tail-predicated).
    unsafe {
        asm!(
            "dlstp.32 lr, {n}",
            "2:",
            "vldrh.s32 q0, [r0], #8",
            "vmul.i32 q0, q0, {m}",
            "vrshr.s32 q0, q0, #15",
            "vqmovnb.s32 q0, q0",
            "vstrh.32 q0, [r1], #8",
            "letp lr, 2b",
            n = in(reg) n,
            m = in(reg) m as i32,
            inout("r0") x.as_ptr() => _,
            inout("r1") out.as_mut_ptr() => _,
            out("lr") _,
            out("d0") _, out("d1") _,
            options(nostack),
        );
    }
    take_qc();
}

/// `eltwise::residual_relu` four lanes a vector: `out = clamp(y + qrshl(x, shift), 0, lim)` for
/// the first `n` elements, in 32-bit lanes with saturating rounding shift (`VQRSHL`: a left
/// shift saturates to i32, a right one rounds half up as `rshift_round`) and saturating add, so
/// every lane equals `O::from_i64_sat((y + rescale(x)).max(0))` of the i64 reference (the
/// saturated lanes are beyond `lim` or below 0 both ways). `$ld` loads four skip values widened
/// to 32 bits from `r1`, `$st` stores four outputs narrowed from 32 bits to `r2`.
macro_rules! residual_relu_kernel {
    ($name:ident, $x:ty, $o:ty, $ld:literal, $st:literal, $lim:expr) => {
        /// See [`residual_relu_kernel`]: `n <= y.len()`, `n <= x.len()`, `n <= out.len()` lanes;
        /// `shift` is `out_frac - frac`; `FPSCR.QC` cleared afterwards.
        #[inline]
        pub fn $name(y: &[i16], x: &[$x], shift: i32, out: &mut [$o]) {
            let n = out.len().min(x.len()).min(y.len());
            if n == 0 {
                return;
            }
            // Shifts beyond 40 either way give the same lanes (saturated or 0) as the exact
            // ones, and the register form reads only the bottom byte.
            let sh = shift.clamp(-40, 40);
            // SAFETY: lane `i < n` reads `y[i]`, `x[i]` and writes `out[i]` (tail-predicated).
            unsafe {
                asm!(
                    "vmov.i32 q2, #0",
                    "vdup.32 q3, {lim}",
                    "dlstp.32 lr, {n}",
                    "2:",
                    "vldrh.s32 q0, [r0], #8",
                    $ld,
                    "vqrshl.s32 q1, {sh}",
                    "vqadd.s32 q0, q0, q1",
                    "vmax.s32 q0, q0, q2",
                    "vmin.s32 q0, q0, q3",
                    $st,
                    "letp lr, 2b",
                    n = in(reg) n,
                    sh = in(reg) sh,
                    lim = in(reg) $lim,
                    inout("r0") y.as_ptr() => _,
                    inout("r1") x.as_ptr() => _,
                    inout("r2") out.as_mut_ptr() => _,
                    out("lr") _,
                    out("d0") _, out("d1") _, out("d2") _, out("d3") _,
                    out("d4") _, out("d5") _, out("d6") _, out("d7") _,
                    options(nostack),
                );
            }
            take_qc();
        }
    };
}

residual_relu_kernel!(residual_relu_u8_u8, u8, u8, "vldrb.u32 q1, [r1], #4", "vstrb.32 q0, [r2], #4", 255i32);
residual_relu_kernel!(residual_relu_i16_u8, i16, u8, "vldrh.s32 q1, [r1], #8", "vstrb.32 q0, [r2], #4", 255i32);
residual_relu_kernel!(residual_relu_u8_i16, u8, i16, "vldrb.u32 q1, [r1], #4", "vstrh.32 q0, [r2], #8", 32767i32);
residual_relu_kernel!(residual_relu_i16_i16, i16, i16, "vldrh.s32 q1, [r1], #8", "vstrh.32 q0, [r2], #8", 32767i32);

/// `x` as a slice of `U` when `T` is `U`.
#[inline(always)]
fn cast<T: 'static, U: 'static>(x: &[T]) -> Option<&[U]> {
    if core::any::TypeId::of::<T>() == core::any::TypeId::of::<U>() {
        // SAFETY: `T` and `U` are the same type.
        Some(unsafe { core::slice::from_raw_parts(x.as_ptr().cast::<U>(), x.len()) })
    } else {
        None
    }
}

/// `x` as a mutable slice of `U` when `T` is `U`.
#[inline(always)]
fn cast_mut<T: 'static, U: 'static>(x: &mut [T]) -> Option<&mut [U]> {
    if core::any::TypeId::of::<T>() == core::any::TypeId::of::<U>() {
        // SAFETY: `T` and `U` are the same type; the borrow moves into the result.
        Some(unsafe { core::slice::from_raw_parts_mut(x.as_mut_ptr().cast::<U>(), x.len()) })
    } else {
        None
    }
}

/// `eltwise::residual_relu` on Helium for skip values `X` in `{u8, i16}` and outputs `O` in
/// `{u8, i16}` (`shift = out_frac - frac`, 0 for a projected skip): `false` (nothing written)
/// for other types and for shifts outside `-255..=24` (the i64 reference `y + (x << shift)` can
/// wrap beyond; the model's shifts are a few bits).
#[inline(always)]
pub fn residual_relu<X: 'static, O: 'static>(y: &[i16], x: &[X], shift: i32, out: &mut [O]) -> bool {
    if !(-255..=24).contains(&shift) {
        return false;
    }
    if let Some(x) = cast::<X, u8>(x) {
        if let Some(o) = cast_mut::<O, u8>(out) {
            residual_relu_u8_u8(y, x, shift, o);
            return true;
        }
        if let Some(o) = cast_mut::<O, i16>(out) {
            residual_relu_u8_i16(y, x, shift, o);
            return true;
        }
    } else if let Some(x) = cast::<X, i16>(x) {
        if let Some(o) = cast_mut::<O, u8>(out) {
            residual_relu_i16_u8(y, x, shift, o);
            return true;
        }
        if let Some(o) = cast_mut::<O, i16>(out) {
            residual_relu_i16_i16(y, x, shift, o);
            return true;
        }
    }
    false
}

/// The largest `|v|` of `v` as unsigned (`|i32::MIN| = 2^31`; 0 for an empty slice), four
/// lanes a vector by `VMAXAV.S32`: below `2^k` exactly when the OR of the magnitudes is (the
/// correlation lookup's test for its i32 path).
#[inline]
pub fn max_abs_i32(v: &[i32]) -> u32 {
    let n = v.len();
    if n == 0 {
        return 0;
    }
    let mut m = 0u32;
    // SAFETY: lane `i < n` reads `v[i]` (tail-predicated).
    unsafe {
        asm!(
            "dlstp.32 lr, {n}",
            "2:",
            "vldrw.u32 q0, [{p}], #16",
            "vmaxav.s32 {m}, q0",
            "letp lr, 2b",
            n = in(reg) n,
            p = inout(reg) v.as_ptr() => _,
            m = inout(reg) m,
            out("lr") _,
            out("d0") _, out("d1") _,
            options(nostack, readonly),
        );
    }
    m
}
