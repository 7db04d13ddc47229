//! The dot-product kernels of this build (Helium with feature `mve`, else the DSP ones) against
//! the plain integer loops, on the target: random and extreme weights and activations (u8, i8,
//! i16), lengths 0..=40 and around the 256-term chunks and the 8-lane vectors, both patches of the
//! pair layout. The host cannot run these kernels, so `run-tests.sh` runs this before the frame.
//!
//! Prints `MUIR-KERNELS ok cases=N` and exits 0, or prints the first mismatch and exits 1.

#![no_std]
#![no_main]

use cortex_m_rt::entry;
use muir::kernels::{Elem, dot_plain};
use semihosting::{println, process};

/// Longest patch tested (the largest layer patch, 9 x 640, is 5,760 values).
const MAX_N: usize = 5760;

/// xorshift64* (the generator of the crate's kernel tests).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545F4914F6CDD1D)
    }
}

/// How to fill a test vector.
#[derive(Clone, Copy)]
enum Fill {
    Random,
    Min,
    Max,
}

trait Sample: Elem {
    fn sample(r: &mut Rng, fill: Fill) -> Self;
}

impl Sample for u8 {
    fn sample(r: &mut Rng, fill: Fill) -> Self {
        match fill {
            Fill::Random => (r.next() >> 56) as u8,
            Fill::Min => 0,
            Fill::Max => u8::MAX,
        }
    }
}

impl Sample for i8 {
    fn sample(r: &mut Rng, fill: Fill) -> Self {
        match fill {
            Fill::Random => (r.next() >> 56) as i8,
            Fill::Min => i8::MIN,
            Fill::Max => i8::MAX,
        }
    }
}

impl Sample for i16 {
    fn sample(r: &mut Rng, fill: Fill) -> Self {
        match fill {
            Fill::Random => (r.next() >> 48) as i16,
            Fill::Min => i16::MIN,
            Fill::Max => i16::MAX,
        }
    }
}

/// Scratch: two weight rows, two patches, their pair layout (static: no large stack frames).
struct Buffers<T: 'static> {
    w0: &'static mut [i8; MAX_N],
    w1: &'static mut [i8; MAX_N],
    a: &'static mut [T; MAX_N],
    b: &'static mut [T; MAX_N],
    pair: &'static mut [T; 2 * MAX_N],
}

fn fail(what: &str, n: usize, got: &[i64], want: &[i64]) -> ! {
    println!("MUIR-KERNELS FAILED {what} n={n}: kernel {got:?}, plain {want:?}");
    process::exit(1)
}

/// Checks `Elem::dot` and `Elem::dot2x2` for `T` at length `n`; returns the cases checked.
fn check<T: Sample>(name: &str, buf: &mut Buffers<T>, r: &mut Rng, n: usize, wf: Fill, xf: Fill) -> usize {
    for i in 0..n {
        buf.w0[i] = i8::sample(r, wf);
        buf.w1[i] = i8::sample(r, if matches!(wf, Fill::Random) { wf } else { Fill::Max });
        buf.a[i] = T::sample(r, xf);
        buf.b[i] = T::sample(r, if matches!(xf, Fill::Random) { xf } else { Fill::Min });
    }
    let (w0, w1, a, b) = (&buf.w0[..n], &buf.w1[..n], &buf.a[..n], &buf.b[..n]);
    for j in 0..n {
        buf.pair[T::pair_at(n, j, false)] = a[j];
        buf.pair[T::pair_at(n, j, true)] = b[j];
    }
    let pair = &buf.pair[..2 * n];

    let want = [dot_plain(w0, a), dot_plain(w1, a), dot_plain(w0, b), dot_plain(w1, b)];
    let got = [T::dot(w0, a), T::dot(w1, a), T::dot(w0, b), T::dot(w1, b)];
    if got != want {
        fail(name, n, &got, &want);
    }
    let got = T::dot2x2(w0, w1, pair);
    if got != want {
        fail(name, n, &got, &want);
    }
    // Unaligned starts (the engine slices patches at any offset of a part).
    if n > 1 {
        let got = T::dot(&w0[1..], &a[1..]);
        let want = dot_plain(&w0[1..], &a[1..]);
        if got != want {
            fail(name, n - 1, &[got], &[want]);
        }
    }
    3
}

static mut W0: [i8; MAX_N] = [0; MAX_N];
static mut W1: [i8; MAX_N] = [0; MAX_N];
static mut A8: [u8; MAX_N] = [0; MAX_N];
static mut B8: [u8; MAX_N] = [0; MAX_N];
static mut P8: [u8; 2 * MAX_N] = [0; 2 * MAX_N];
static mut A16: [i16; MAX_N] = [0; MAX_N];
static mut B16: [i16; MAX_N] = [0; MAX_N];
/// Word-aligned, as the engine's patch buffers are: the DSP build's i16 `dot2x2` loop loads
/// pairs of words (`LDRD`) and takes its assembly path only on aligned patches.
#[repr(C, align(8))]
struct Aligned16([i16; 2 * MAX_N]);
static mut P16: Aligned16 = Aligned16([0; 2 * MAX_N]);

/// The Helium MGA kernels (`mve::dot_i16_i64`, the logits; `mve::aggregate`, the value sums of a
/// block of keys) against plain loops: lengths around the 8- and 4-lane vectors, key blocks of 1
/// to 33 (the engine's are up to 32) with odd and even channel counts, random and extreme
/// values (softmax weights up to 32768 = exp(0), values at i16's limits).
#[cfg(feature = "mve")]
fn check_attention(q: &mut [i16; MAX_N], k: &mut [i16; MAX_N], r: &mut Rng) -> usize {
    use muir::kernels::mve;
    let mut cases = 0;
    for n in lengths() {
        for fill in [Fill::Random, Fill::Min, Fill::Max] {
            for i in 0..n {
                q[i] = i16::sample(r, fill);
                k[i] = i16::sample(r, if matches!(fill, Fill::Max) { Fill::Min } else { fill });
            }
            let want: i64 = q[..n].iter().zip(&k[..n]).map(|(a, b)| *a as i64 * *b as i64).sum();
            let got = mve::dot_i16_i64(&q[..n], &k[..n]);
            if got != want {
                fail("logit", n, &[got], &[want]);
            }
            cases += 1;
        }
    }
    let v = q;
    for cv in [1usize, 2, 3, 5, 64, 128] {
        for nb in 1..=33usize {
            for fill in [Fill::Random, Fill::Max, Fill::Min] {
                let mut e = [0i32; 33];
                for (j, w) in e.iter_mut().enumerate().take(nb) {
                    *w = match fill {
                        Fill::Random => (r.next() % 32769) as i32,
                        _ if j % 3 == 0 => 0,
                        _ => 32768,
                    };
                }
                for x in v.iter_mut().take(nb * cv) {
                    *x = i16::sample(r, fill);
                }
                let mut got = [0i64; 128];
                let mut want = [0i64; 128];
                for (g, w) in got.iter_mut().zip(want.iter_mut()).take(cv) {
                    let start = (r.next() >> 40) as i64 - (1 << 23);
                    (*g, *w) = (start, start);
                }
                for (ch, w) in want.iter_mut().enumerate().take(cv) {
                    *w += (0..nb).map(|j| e[j] as i64 * v[j * cv + ch] as i64).sum::<i64>();
                }
                mve::aggregate(&e[..nb], &v[..nb * cv], cv, &mut got[..cv]);
                if got[..cv] != want[..cv] {
                    fail("aggregate", nb * 1000 + cv, &got[..cv], &want[..cv]);
                }
                cases += 1;
            }
        }
    }
    cases
}

fn lengths() -> impl Iterator<Item = usize> {
    (0..=40).chain([63, 64, 65, 72, 127, 128, 129, 255, 256, 257, 260, 507, 508, 509, 511, 512, 513, 576, 1000, 1016, 1017, 1152, 2304, 5760])
}

#[entry]
fn main() -> ! {
    // SAFETY: `main` runs once and is the only user of these statics; the u8 and i8 buffers are
    // used one type after the other through the same memory.
    let (w0, w1, a8, b8, p8, a16, b16, p16) = unsafe {
        use core::ptr::addr_of_mut;
        (
            &mut *addr_of_mut!(W0),
            &mut *addr_of_mut!(W1),
            &mut *addr_of_mut!(A8),
            &mut *addr_of_mut!(B8),
            &mut *addr_of_mut!(P8),
            &mut *addr_of_mut!(A16),
            &mut *addr_of_mut!(B16),
            &mut (*addr_of_mut!(P16)).0,
        )
    };
    let mut r = Rng(0x9E37_79B9_7F4A_7C15);
    let mut cases = 0;
    let fills = [(Fill::Random, Fill::Random), (Fill::Min, Fill::Max), (Fill::Min, Fill::Min), (Fill::Max, Fill::Max)];

    let mut u8s = Buffers { w0, w1, a: a8, b: b8, pair: p8 };
    for n in lengths() {
        for &(wf, xf) in &fills {
            cases += check("u8", &mut u8s, &mut r, n, wf, xf);
        }
    }
    // SAFETY: the same bytes, reinterpreted as i8 (same size, alignment, validity).
    let mut i8s: Buffers<i8> = unsafe {
        Buffers {
            w0: u8s.w0,
            w1: u8s.w1,
            a: &mut *(u8s.a as *mut [u8; MAX_N] as *mut [i8; MAX_N]),
            b: &mut *(u8s.b as *mut [u8; MAX_N] as *mut [i8; MAX_N]),
            pair: &mut *(u8s.pair as *mut [u8; 2 * MAX_N] as *mut [i8; 2 * MAX_N]),
        }
    };
    for n in lengths() {
        for &(wf, xf) in &fills {
            cases += check("i8", &mut i8s, &mut r, n, wf, xf);
        }
    }
    let mut i16s = Buffers { w0: i8s.w0, w1: i8s.w1, a: a16, b: b16, pair: p16 };
    for n in lengths() {
        for &(wf, xf) in &fills {
            cases += check("i16", &mut i16s, &mut r, n, wf, xf);
        }
    }
    #[cfg(feature = "mve")]
    {
        cases += check_attention(i16s.a, i16s.b, &mut r);
    }
    println!("MUIR-KERNELS ok cases={cases}");
    process::exit(0)
}
