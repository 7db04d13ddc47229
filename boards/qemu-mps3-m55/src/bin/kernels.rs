//! The dot-product kernels of this build (Helium with feature `mve`, else the DSP ones) against
//! the plain integer loops, on the target: random and extreme weights and activations (u8, i8,
//! i16), lengths 0..=40 and around the 256-term chunks and the 8-lane vectors, both patches of the
//! pair layout; with Helium also the MGA sums and the convolution epilogue (`mve::requant4`); whole
//! convolution rows through the engine's entry against the plain twin. The host cannot run these
//! kernels, so `run-tests.sh` runs this before the frame.
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

/// The DSP build's i16 pair loop against weights widened beforehand (`dsp::widen_weights`,
/// `dsp::dot2x2_w16`, the convolution rows' `conv_row_w16`) on the vectors `check` just filled
/// (lengths up to 5,760: several 508-term chunks, odd group counts, tails of 1 to 3 values; the
/// extreme fills), against the plain dot products.
#[cfg(not(feature = "mve"))]
fn check_w16(buf: &Buffers<i16>, ww: &mut [u32; MAX_N], n: usize) -> usize {
    use muir::kernels::dsp;
    let (w0, w1, a, b) = (&buf.w0[..n], &buf.w1[..n], &buf.a[..n], &buf.b[..n]);
    let want = [dot_plain(w0, a), dot_plain(w1, a), dot_plain(w0, b), dot_plain(w1, b)];
    ww.fill(0x5A5A_5A5A);
    dsp::widen_weights(w0, w1, n / 4, ww);
    untouched("dsp::widen_weights", &ww[..], 4 * (n / 4));
    // One chunk of whole groups: the i32 sums of `dot2x2_w16_i32` (one-part layers).
    let q = n / 4;
    if n % 4 == 0 && (1..=127).contains(&q) {
        match dsp::dot2x2_w16_i32(ww, &buf.pair[..2 * n], q) {
            Some(got) if got.map(i64::from) == want => {}
            Some(got) => fail("i16 dot2x2_w16_i32", n, &got.map(i64::from), &want),
            None => fail("i16 dot2x2_w16_i32 (no result)", n, &[], &want),
        }
        // The same pair as the only one of `dot2x2_w16_i32_n` (several pairs: `check_conv`'s
        // one-part layers through `run_conv`).
        let mut got = [[0x5A5A_5A5Ai32; 4]; 2];
        if !dsp::dot2x2_w16_i32_n(ww, &buf.pair[..2 * n], q, &mut got[..1]) || got[0].map(i64::from) != want || got[1] != [0x5A5A_5A5A; 4] {
            fail("i16 dot2x2_w16_i32_n", n, &got[0].map(i64::from), &want);
        }
    }
    // Whole groups in chunks of up to 127 (`dot2x2_w16_i32_chunks`, the 576-value layers and
    // parts): the plain sums where it gives them; a refusal wherever a sum leaves i32.
    if n % 4 == 0 && q >= 1 {
        let (mut got, mut tmp) = ([[0i32; 4]; 1], [[0i32; 4]; 1]);
        let ok = dsp::dot2x2_w16_i32_chunks(ww, &buf.pair[..2 * n], q, 2 * n, &mut got, &mut tmp);
        let fits = want.iter().all(|w| i32::try_from(*w).is_ok());
        if (ok && got[0].map(i64::from) != want) || (!fits && ok) || (q <= 127 && fits && !ok) {
            fail("i16 dot2x2_w16_i32_chunks", n, &got[0].map(i64::from), &want);
        }
    }
    match dsp::dot2x2_w16(ww, w0, w1, &buf.pair[..2 * n], n) {
        Some(got) if got == want => 1,
        Some(got) => fail("i16 dot2x2_w16", n, &got, &want),
        None => fail("i16 dot2x2_w16 (no result)", n, &[], &want),
    }
}

/// A widening wrote nothing past its `end` words: the rest of `ww` still holds the fill.
#[cfg(not(feature = "mve"))]
fn untouched(what: &str, ww: &[u32], end: usize) {
    if let Some(i) = ww.iter().skip(end).position(|&w| w != 0x5A5A_5A5A) {
        println!("MUIR-KERNELS FAILED {what}: word {} written past the {end} widened words", end + i);
        process::exit(1)
    }
}

/// Widened weights of `check_w16`.
#[cfg(not(feature = "mve"))]
static mut WW: [u32; MAX_N] = [0; MAX_N];

static mut W0: [i8; MAX_N] = [0; MAX_N];
/// Twelve weight rows of up to `W12_KL` values for `check_dots12` (parts beyond its 504-term
/// chunks).
#[cfg(feature = "mve")]
static mut W12: [i8; 12 * W12_KL] = [0; 12 * W12_KL];
#[cfg(feature = "mve")]
const W12_KL: usize = 1536;
/// A copy of the pair `check_dots_flipped` flips.
#[cfg(feature = "mve")]
static mut ORIG8: [u8; 2 * MAX_N + 1] = [0; 2 * MAX_N + 1];
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
/// to 33 and around 64 and 128 (the engine's are up to 128) with odd and even channel counts, random and extreme
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
    for cv in [1usize, 2, 3, 4, 5, 6, 7, 44, 64, 128] {
        for nb in (1..=33usize).chain([63, 64, 65, 127, 128, 129, 130]).filter(|nb| nb * cv <= MAX_N) {
            for fill in [Fill::Random, Fill::Max, Fill::Min] {
                let mut e = [0i32; 130];
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

/// The DSP build's correlation of one feature vector with four consecutive columns
/// (`dsp::dot_i8_4cols`, the lookup's window) against plain sums: vector lengths 0 to 140 (whole
/// quads and not), random values and all -128, rows one value short (its per-column fallback:
/// the incomplete column is 0).
#[cfg(not(feature = "mve"))]
fn check_corr4(r: &mut Rng) -> usize {
    let mut f1 = [0i8; 140];
    let mut f2 = [0i8; 4 * 140];
    let mut cases = 0;
    for c in 0..=140usize {
        for extreme in [false, true] {
            for v in f1.iter_mut().take(c).chain(f2.iter_mut().take(4 * c)) {
                *v = if extreme { i8::MIN } else { (r.next() >> 56) as i8 };
            }
            for short in [0usize, 1] {
                let row = &f2[..(4 * c).saturating_sub(short)];
                let got = muir::kernels::dsp::dot_i8_4cols(&f1[..c], row, c);
                for (j, g) in got.iter().enumerate() {
                    // (a column the row does not hold whole is 0, as `corr::corr_at` has it)
                    let col = row.get(j * c..(j + 1) * c).unwrap_or(&[]);
                    let want: i32 = f1[..c].iter().zip(col).map(|(a, b)| *a as i32 * *b as i32).sum();
                    if *g != want {
                        println!("MUIR-KERNELS FAILED corr4 c={c} extreme={extreme} short={short} column {j}: kernel {g}, plain {want}");
                        process::exit(1);
                    }
                    cases += 1;
                }
            }
        }
    }
    cases
}

/// The DSP build's correlation on a right row widened once (`dsp::widen_i8_quads`,
/// `dsp::dot_w8_4cols`: the assembly loop for 128 values, the compiled one for other multiples
/// of 4) against plain sums: lengths 0 to 140 in steps of 4, random values, all -128, -128
/// against 127; refusals (a length not a multiple of 4, short slices); and whole windows
/// (`corr::window_wide` against `corr::window` inside the row, nothing written outside it) over
/// rows of 1 to 9 columns of 128 values at offsets -6 ..= 9.
#[cfg(not(feature = "mve"))]
fn check_corr4w(r: &mut Rng) -> usize {
    use muir::kernels::{corr, dsp};
    let mut f1 = [0i8; 144];
    let mut f2 = [0i8; 9 * 140];
    let mut wide = [0u32; 9 * 70];
    let mut cases = 0;
    for c in (0..=140usize).step_by(4) {
        for fill in 0..3 {
            for (k, v) in f1.iter_mut().take(c).enumerate() {
                *v = match fill {
                    0 => (r.next() >> 56) as i8,
                    1 => i8::MIN,
                    _ if k % 3 == 0 => i8::MAX,
                    _ => i8::MIN,
                };
            }
            for v in f2.iter_mut().take(4 * c) {
                *v = if fill == 0 { (r.next() >> 56) as i8 } else { i8::MIN };
            }
            let q = dsp::widen_i8_quads(&f2[..4 * c], &mut wide[..2 * c]);
            let got = dsp::dot_w8_4cols(&f1[..c], &wide[..2 * c], c);
            for j in 0..4 {
                let want: i32 = f1[..c].iter().zip(&f2[j * c..(j + 1) * c]).map(|(a, b)| *a as i32 * *b as i32).sum();
                if q != c || got.map(|g| g[j]) != Some(want) {
                    println!("MUIR-KERNELS FAILED corr4w c={c} fill={fill} column {j}: quads {q}, kernel {got:?}, plain {want}");
                    process::exit(1);
                }
                cases += 1;
            }
            if c == 0 {
                continue;
            }
            // Refusals: a length not a multiple of 4, a short f1, short columns.
            let refused = [
                dsp::dot_w8_4cols(&f1[..c + 1], &wide[..2 * c + 2], c + 1),
                dsp::dot_w8_4cols(&f1[..c - 1], &wide[..2 * c], c),
                dsp::dot_w8_4cols(&f1[..c], &wide[..2 * c - 1], c),
            ];
            for (k, g) in refused.iter().enumerate() {
                if g.is_some() {
                    println!("MUIR-KERNELS FAILED corr4w c={c} refusal {k} computed {g:?}");
                    process::exit(1);
                }
                cases += 1;
            }
        }
    }
    let c = 128;
    for w in 1..=9usize {
        for v in f1.iter_mut().take(c).chain(f2.iter_mut().take(w * c)) {
            *v = (r.next() >> 56) as i8;
        }
        let f2 = &f2[..w * c];
        dsp::widen_i8_quads(f2, &mut wide[..w * c / 2]);
        for lo in -6i64..=9 {
            for n in [1usize, 5, 12, 17] {
                let (mut a, mut b) = ([7i32; 17], [9i32; 17]);
                corr::window_wide(&f1[..c], f2, &wide[..w * c / 2], w, lo, &mut a[..n]);
                corr::window(&f1[..c], f2, w, lo, &mut b[..n]);
                // (only the columns inside the row are written: the others keep their 7)
                let inside = |t: usize| (0..w as i64).contains(&(lo + t as i64));
                let differs = (0..17).any(|t| if t < n && inside(t) { a[t] != b[t] } else { a[t] != 7 });
                if differs {
                    println!("MUIR-KERNELS FAILED corr4w window w={w} lo={lo} n={n}: {:?} against {:?}", &a[..n], &b[..n]);
                    process::exit(1);
                }
                cases += 1;
            }
        }
    }
    cases
}

/// The DSP build's lookup (`corr::lookup_pixel`: the window by `dsp::dot_i8_4cols`, the
/// post-pooling samples by `samples_i32` with `dsp::ssat16` where the numerators fit i32) against
/// `corr::lookup_pixel_plain`: 4 levels of radius 4, rows of 1 to 24 columns of 128 values,
/// random and extreme features (all -128: every correlation 2^21, the i64 path), flows across
/// and past the row, multipliers of shifts 20 to 62 (the i32 path's two requantisations).
#[cfg(not(feature = "mve"))]
fn check_lookup_dsp(f1: &mut [i8; MAX_N], f2: &mut [i8; MAX_N], r: &mut Rng) -> usize {
    use muir::arith::Multiplier;
    use muir::kernels::corr::{self, LookupParams, LookupScratch};
    const C: usize = 128;
    let (levels, radius) = (4, 4);
    let n = corr::window_len(levels, radius);
    let mut win = [0i32; 96];
    let mut pre = [0i64; 97];
    let mut cases = 0;
    for case in 0..600usize {
        let w = 1 + case % 24;
        if w * C > MAX_N {
            continue;
        }
        let extreme = case % 7 == 3;
        for v in f1.iter_mut().take(C).chain(f2.iter_mut().take(w * C)) {
            *v = if extreme { i8::MIN } else { (r.next() >> 56) as i8 };
        }
        let mut mults = [Multiplier { m: 0, shift: 1 }; 4];
        for m in mults.iter_mut() {
            *m = Multiplier { m: (1 << 30) + (r.next() >> 34) as i32, shift: 20 + (r.next() % 43) as u8 };
        }
        if case % 5 == 0 {
            mults[0].shift = 33;
            mults[1].shift = 62;
            mults[2].shift = 32;
        }
        let p = LookupParams { levels, radius, post_pool: true, mults: &mults };
        for x in [0, w / 2, w - 1] {
            let flow = -((r.next() % (64 * 256)) as i16) + if case % 3 == 0 { 2000 } else { 0 };
            let (mut got, mut want) = ([0i16; 36], [0i16; 36]);
            let mut s = LookupScratch { window: &mut win[..n], prefix: &mut pre[..n + 1] };
            corr::lookup_pixel(&p, &f1[..C], &f2[..w * C], w, x, flow, &mut s, &mut got);
            corr::lookup_pixel_plain(&p, &f1[..C], &f2[..w * C], w, x, flow, &mut want);
            if got != want {
                println!("MUIR-KERNELS FAILED lookup dsp case {case} w={w} x={x} flow={flow}: {got:?} against {want:?}");
                process::exit(1);
            }
            cases += 1;
        }
    }
    cases
}

/// The DSP build's refinement decision (`fullres::sum_decide`: the five paths' sums two
/// candidates a word, `path_sums_dsp`) against the sums value by value and `decide`: bands of 0
/// to `SLOTS` candidates, path costs below `432 + P2` (random, all equal, the least at every
/// position, ties), paths shorter than the band.
#[cfg(not(feature = "mve"))]
fn check_decide(r: &mut Rng) -> usize {
    use muir::kernels::fullres::{self, Band, SLOTS};
    let mut paths = [[0u16; SLOTS]; 5];
    let mut cases = 0;
    for case in 0..4000usize {
        let len = (case % (SLOTS + 1)) as i16;
        let band = Band { first: (r.next() % 64) as i16, len };
        let kind = case % 5;
        let least = (r.next() % SLOTS as u64) as usize;
        for (p, path) in paths.iter_mut().enumerate() {
            for (k, v) in path.iter_mut().enumerate() {
                *v = match kind {
                    0 => (r.next() % 2480) as u16,
                    1 => 1000,
                    2 => if k == least { 100 } else { 300 + (r.next() % 2000) as u16 },
                    3 => if k == least || k == (least + 3) % SLOTS { 50 } else { 400 + ((k * 37 + p) % 700) as u16 },
                    _ => (k as u16 * 97 + p as u16 * 13) % 2479,
                };
            }
        }
        let short = if case % 7 == 6 { 3 } else { SLOTS };
        let p = [&paths[0][..], &paths[1][..short.max(len as usize).min(SLOTS)], &paths[2][..], &paths[3][..], &paths[4][..short]];
        let (got, want) = fullres::sum_decide_twins(p, band);
        if got != want {
            println!("MUIR-KERNELS FAILED decide case {case} {band:?} kind {kind}: kernel {got:?}, plain {want:?}");
            process::exit(1);
        }
        cases += 1;
    }
    cases
}

/// The DSP build's MGA logit (`dsp::dot_i16_i64`: `LDRD` and `SMLALD`, eight products a step,
/// when both slices are word-aligned; else the plain loop) against the plain sum: the usual
/// lengths, random and extreme values (`i16::MIN` squared at every product, the largest sums),
/// both slices aligned, and each or both starting one value later (misaligned: the plain path).
#[cfg(not(feature = "mve"))]
fn check_logit_dsp(q: &mut [i16; MAX_N], k: &mut [i16; MAX_N], r: &mut Rng) -> usize {
    use muir::kernels::dsp;
    let mut cases = 0;
    // The first word-aligned value of each buffer (the statics are only 2-byte aligned).
    let (aq, ak) = ((q.as_ptr() as usize / 2) % 2, (k.as_ptr() as usize / 2) % 2);
    for n in lengths().filter(|n| n + 2 <= MAX_N) {
        for fill in [Fill::Random, Fill::Min, Fill::Max] {
            for i in 0..n + 2 {
                q[i] = i16::sample(r, fill);
                k[i] = i16::sample(r, if matches!(fill, Fill::Max) { Fill::Min } else { fill });
            }
            for (oq, ok) in [(aq, ak), (aq + 1, ak), (aq, ak + 1), (aq + 1, ak + 1)] {
                let (qs, ks) = (&q[oq..oq + n], &k[ok..ok + n]);
                let want: i64 = qs.iter().zip(ks).map(|(a, b)| *a as i64 * *b as i64).sum();
                let got = dsp::dot_i16_i64(qs, ks);
                if got != want {
                    fail("dsp logit", n * 10 + 2 * (oq - aq) + ok - ak, &[got], &[want]);
                }
                cases += 1;
            }
        }
    }
    // Two keys a call (`dsp::logits2`): query lengths 32 and 64 (others refused), both slices
    // aligned or either misaligned (refused), keys stored one after the other.
    for c in [32usize, 64, 16, 33, 0] {
        for fill in [Fill::Random, Fill::Min, Fill::Max] {
            for i in 0..2 * c + 2 {
                q[i] = i16::sample(r, fill);
                k[i] = i16::sample(r, if matches!(fill, Fill::Max) { Fill::Min } else { fill });
            }
            for (oq, ok) in [(aq, ak), (aq + 1, ak), (aq, ak + 1)] {
                let (qs, ks) = (&q[oq..oq + c], &k[ok..ok + 2 * c]);
                let plain = |kk: &[i16]| qs.iter().zip(kk).map(|(a, b)| *a as i64 * *b as i64).sum::<i64>();
                let want = ((c == 32 || c == 64) && (oq, ok) == (aq, ak)).then(|| (plain(&ks[..c]), plain(&ks[c..])));
                let got = dsp::logits2(qs, ks);
                if got != want {
                    let (g, w) = (got.unwrap_or((-1, -1)), want.unwrap_or((-1, -1)));
                    fail("dsp logits2", c * 10 + 2 * (oq - aq) + ok - ak, &[g.0, g.1], &[w.0, w.1]);
                }
                cases += 1;
            }
            // A second key one value short: refused.
            if c == 32 && dsp::logits2(&q[aq..aq + c], &k[ak..ak + 2 * c - 1]).is_some() {
                fail("dsp logits2 short", c, &[], &[]);
            }
        }
    }
    cases
}

/// The softmax weights of one value-sum case of kind `kind` (0..5) for a block of `nb <= 130`
/// keys, and the fill of its values: random weights, zeros and 32767, one 32768 (exp(0)) in the
/// middle, one every 29 keys (`check_aggregate_dsp`, `check_aggregate_cm`).
#[cfg(not(feature = "mve"))]
fn agg_weights(r: &mut Rng, kind: usize, nb: usize) -> ([i32; 130], Fill) {
    let mut e = [0i32; 130];
    for (j, w) in e.iter_mut().enumerate().take(nb) {
        *w = match kind {
            0 => (r.next() % 32768) as i32,
            1 if j % 3 == 0 => 0,
            1 | 2 => 32767,
            3 if j == nb / 2 => 32768,
            4 if j % 29 == 0 => 32768,
            _ => (r.next() % 32769) as i32,
        };
    }
    (e, [Fill::Random, Fill::Max, Fill::Min, Fill::Random, Fill::Max][kind])
}

/// The DSP build's MGA value sums (`dsp::aggregate`: two keys and two channels per `SMLALD`,
/// weights of 32768 by a per-key pass, the plain loop for a block with more than four of them or
/// over 128 keys) against a plain loop: blocks of 1 to 34 keys and around 64 and 128 (the
/// engine's blocks), odd and even channel counts, weights random, 0 and 32767, blocks with one
/// 32768 and with one every 29 keys, values at i16's limits, random starting sums.
#[cfg(not(feature = "mve"))]
fn check_aggregate_dsp(v: &mut [i16; MAX_N], r: &mut Rng) -> usize {
    use muir::kernels::dsp;
    let mut cases = 0;
    for cv in [1usize, 2, 3, 5, 44, 64, 128] {
        for nb in (1..=34usize).chain([63, 64, 65, 127, 128, 129, 130]).filter(|nb| nb * cv <= MAX_N) {
            for kind in 0..5 {
                let (e, fill) = agg_weights(r, kind, nb);
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
                dsp::aggregate(&e[..nb], &v[..nb * cv], cv, &mut got[..cv]);
                if got[..cv] != want[..cv] {
                    fail("dsp aggregate", nb * 1000 + cv, &got[..cv], &want[..cv]);
                }
                cases += 1;
            }
        }
    }
    cases
}

/// The DSP build's least value of a path step's predecessor (`dsp::min_u16`, two words a step by
/// `USUB16`/`SEL`) against `iter().min()`: lengths 0 to 40 and 63-65, random values, values at
/// 0 and `u16::MAX`, the least one at each position (in either half of a word, in the tail).
#[cfg(not(feature = "mve"))]
fn check_min_dsp(r: &mut Rng) -> usize {
    let mut v = [0u16; 65];
    let mut cases = 0;
    for n in (0..=40usize).chain([63, 64, 65]) {
        for kind in 0..4 {
            for x in v.iter_mut().take(n) {
                *x = match kind {
                    0 => (r.next() >> 48) as u16,
                    1 => u16::MAX - (r.next() % 3) as u16,
                    2 => (r.next() % 3) as u16,
                    _ => 1000 + (r.next() % 60000) as u16,
                };
            }
            for at in 0..n.max(1) {
                if kind == 3 && at < n {
                    v[at] = 7; // the least value, at every position in turn
                }
                let got = muir::kernels::dsp::min_u16(&v[..n]);
                let want = v[..n].iter().min().copied();
                if got != want {
                    fail("dsp min_u16", n * 100 + at, &[got.map_or(-1, |g| g as i64)], &[want.map_or(-1, |w| w as i64)]);
                }
                cases += 1;
                if kind == 3 && at < n {
                    v[at] = 1000;
                }
                if kind != 3 {
                    break;
                }
            }
        }
    }
    cases
}

/// The DSP build's MGA value sums with the values channel-major (`dsp::aggregate_cm`: channel
/// `ch` of key `j` at `ch n + j`, a block of keys from `j0` on; two keys of a channel a word, four
/// key pairs a step, weights of 32768 by a per-key pass, the plain loop past four of them or 128
/// keys) against a plain loop: blocks of 1 to 34 keys and around 64 and 128 at key offsets 0, 1
/// and 3 of planes with 0 to 5 keys more (odd strides: rows at odd addresses), odd and even
/// channel counts, weights as in `check_aggregate_dsp`, random starting sums; a block past the
/// plane's keys must leave the sums as they are.
#[cfg(not(feature = "mve"))]
fn check_aggregate_cm(v: &mut [i16; MAX_N], r: &mut Rng) -> usize {
    use muir::kernels::dsp;
    let mut cases = 0;
    for cv in [1usize, 2, 3, 5, 44, 64] {
        for nb in (1..=34usize).chain([63, 64, 65, 127, 128, 129, 130]) {
            for (j0, more) in [(0usize, 0usize), (1, 2), (3, 5)] {
                let n = j0 + nb + more;
                if n * cv > MAX_N {
                    continue;
                }
                for kind in 0..5 {
                    let (e, fill) = agg_weights(r, kind, nb);
                    for x in v.iter_mut().take(n * cv) {
                        *x = i16::sample(r, fill);
                    }
                    let mut got = [0i64; 64];
                    let mut want = [0i64; 64];
                    for (g, w) in got.iter_mut().zip(want.iter_mut()).take(cv) {
                        let start = (r.next() >> 40) as i64 - (1 << 23);
                        (*g, *w) = (start, start);
                    }
                    for (ch, w) in want.iter_mut().enumerate().take(cv) {
                        *w += (0..nb).map(|j| e[j] as i64 * v[ch * n + j0 + j] as i64).sum::<i64>();
                    }
                    dsp::aggregate_cm(&e[..nb], &v[..n * cv], n, j0, cv, &mut got[..cv]);
                    if got[..cv] != want[..cv] {
                        fail("dsp aggregate_cm", (nb * 1000 + cv) * 10 + j0, &got[..cv], &want[..cv]);
                    }
                    cases += 1;
                    if kind == 0 {
                        // The block one key past the plane: refused, nothing added.
                        let before = got;
                        dsp::aggregate_cm(&e[..nb], &v[..n * cv], n, j0 + more + 1, cv, &mut got[..cv]);
                        if got[..cv] != before[..cv] {
                            fail("dsp aggregate_cm past the plane", nb * 1000 + cv, &got[..cv], &before[..cv]);
                        }
                        cases += 1;
                    }
                }
            }
        }
    }
    cases
}

/// The twelve-channel i16 block (`mve::PartLens::dots12`: twelve weight rows, three per call,
/// 32-bit sums in chunks of `mve::DOTS3_CHUNK` added by `QADD`) against the plain dot products:
/// 1 to 6 parts of random lengths 1..=140, some of 1..=8, in most cases one of the chunk edges
/// (503, 504, 505, 1007, 1008, 1009) or 500..=1100; random fills, all-extreme fills and one
/// extreme channel and patch of one part. The reported flag must be exactly the plain model's
/// (some chunk add leaves i32), and `true` must mean every value equals the plain dot product.
/// Both outcomes must occur; short slices are refused.
#[cfg(feature = "mve")]
fn check_dots12(pair: &mut [i16; 2 * MAX_N], r: &mut Rng) -> usize {
    use muir::kernels::mve::{DOTS3_CHUNK, PartLens};
    use muir::model::graph::MAX_PARTS;
    // SAFETY: the only user of `W12`, in the single thread of this program.
    let w12 = unsafe { &mut *core::ptr::addr_of_mut!(W12) };
    let (mut fits, mut over) = (0, 0);
    for case in 0..300u32 {
        let np = 1 + (r.next() % MAX_PARTS as u64) as usize;
        let mut lens = [0usize; MAX_PARTS];
        for l in lens.iter_mut().take(np) {
            *l = match r.next() % 4 {
                0 => 1 + (r.next() % 8) as usize,
                _ => 1 + (r.next() % 140) as usize,
            };
        }
        let hot = (r.next() % np as u64) as usize;
        if case % 5 != 0 {
            const EDGES: [usize; 6] = [503, 504, 505, 1007, 1008, 1009];
            lens[hot] = match r.next() % 3 {
                0 => 500 + (r.next() % 601) as usize,
                _ => EDGES[(r.next() % 6) as usize],
            };
        }
        let kl: usize = lens[..np].iter().sum();
        if kl > W12_KL || 2 * kl > 2 * MAX_N {
            continue;
        }
        let mode = case % 4; // 0, 1 random; 2 all extreme; 3 one extreme channel and patch
        let (hc, hb) = ((r.next() % 12) as usize, r.next() % 2 == 0);
        let ext_sign = r.next() % 2 == 0;
        let mut o = 0;
        for (p, &n) in lens[..np].iter().enumerate() {
            let ext = |one: bool| match (mode == 2 || (mode == 3 && p == hot && one), ext_sign) {
                (true, true) => Fill::Min,
                (true, false) => Fill::Max,
                _ => Fill::Random,
            };
            for c in 0..12 {
                let f = ext(c == hc);
                for v in &mut w12[c * kl + o..c * kl + o + n] {
                    *v = i8::sample(r, f);
                }
            }
            for (i, v) in pair[2 * o..2 * o + 2 * n].iter_mut().enumerate() {
                *v = i16::sample(r, ext((i >= n) == hb));
            }
            o += n;
        }
        let Some(l) = PartLens::new(lens[..np].iter().copied(), kl) else {
            println!("MUIR-KERNELS FAILED dots12 case {case}: PartLens::new refused {:?}", &lens[..np]);
            process::exit(1)
        };
        let mut d = [0i32; 24 * MAX_PARTS];
        let ok = l.dots12(&w12[..12 * kl], &pair[..2 * kl], &mut d);
        // The plain model of the flag: chunk sums (exact), added with saturation to i32.
        let mut want_ok = true;
        let mut o = 0;
        for (p, &n) in lens[..np].iter().enumerate() {
            let (a, b) = (&pair[2 * o..2 * o + n], &pair[2 * o + n..2 * o + 2 * n]);
            for c in 0..12 {
                let w = &w12[c * kl + o..c * kl + o + n];
                for (x, at) in [(a, 24 * p + c), (b, 24 * p + 12 + c)] {
                    let want = dot_plain(w, x);
                    let mut run: Option<i64> = None;
                    for (wc, xc) in w.chunks(DOTS3_CHUNK).zip(x.chunks(DOTS3_CHUNK)) {
                        let s = dot_plain(wc, xc);
                        let t = run.map_or(s, |r| r + s);
                        if i32::try_from(t).is_err() {
                            want_ok = false;
                        }
                        run = Some(t.clamp(i32::MIN as i64, i32::MAX as i64));
                    }
                    if ok && d[at] as i64 != want {
                        fail("dots12", kl, &[d[at] as i64], &[want]);
                    }
                }
            }
            o += n;
        }
        if ok != want_ok {
            println!("MUIR-KERNELS FAILED dots12 case {case}: reported fit {ok}, plain model {want_ok}");
            process::exit(1);
        }
        if ok {
            fits += 1;
        } else {
            over += 1;
        }
    }
    // Short slices are refused.
    let l = PartLens::new([3usize, 5].into_iter(), 8);
    let mut d = [0i32; 24 * MAX_PARTS];
    if fits == 0 || over == 0 || l.is_none_or(|l| l.dots12(&w12[..95], &pair[..16], &mut d) || l.dots12(&w12[..96], &pair[..15], &mut d)) {
        println!("MUIR-KERNELS FAILED dots12: fits {fits}, beyond i32 {over}, or a short slice accepted");
        process::exit(1);
    }
    fits + over
}

/// The twelve-channel u8 block (`mve::PartLens::dots12_u8` with `mve::pair_sums_u8`: weights
/// flipped to `w + 128`, `VMLADAVA.U8`, `128 sum(x)` subtracted) against the plain dot products:
/// 1 to 6 parts of random lengths 1..=140, some of 1..=8 or 15..=17, in some cases one of
/// 500..=1100; random fills, all-extreme fills of either sign (weights -128 or 127, activations
/// 0 or 255) and one extreme channel and patch of one part (one part: `muir_mve_dots12_u8_1`,
/// else `muir_mve_dots3_u8`). Every value must equal the plain dot product; short slices are
/// refused.
#[cfg(feature = "mve")]
fn check_dots12_u8(pair: &mut [u8; 2 * MAX_N], r: &mut Rng) -> usize {
    use muir::kernels::mve::{PartLens, pair_sums_u8};
    use muir::model::graph::MAX_PARTS;
    // SAFETY: the only user of `W12` at this time, in the single thread of this program.
    let w12 = unsafe { &mut *core::ptr::addr_of_mut!(W12) };
    let mut cases = 0;
    for case in 0..300u32 {
        let np = 1 + (r.next() % MAX_PARTS as u64) as usize;
        let mut lens = [0usize; MAX_PARTS];
        for l in lens.iter_mut().take(np) {
            *l = match r.next() % 5 {
                0 => 1 + (r.next() % 8) as usize,
                1 => 15 + (r.next() % 3) as usize,
                _ => 1 + (r.next() % 140) as usize,
            };
        }
        let hot = (r.next() % np as u64) as usize;
        if case % 3 == 0 {
            lens[hot] = 500 + (r.next() % 601) as usize;
        }
        let kl: usize = lens[..np].iter().sum();
        if kl > W12_KL {
            continue;
        }
        let mode = case % 4; // 0, 1 random; 2 all extreme; 3 one extreme channel and patch
        let (hc, hb) = ((r.next() % 12) as usize, r.next() % 2 == 0);
        let (wf, xf) = match r.next() % 4 {
            0 => (Fill::Min, Fill::Max),
            1 => (Fill::Max, Fill::Max),
            2 => (Fill::Min, Fill::Min),
            _ => (Fill::Max, Fill::Min),
        };
        let mut o = 0;
        for (p, &n) in lens[..np].iter().enumerate() {
            let ext = |one: bool, f: Fill| if mode == 2 || (mode == 3 && p == hot && one) { f } else { Fill::Random };
            for c in 0..12 {
                let f = ext(c == hc, wf);
                for v in &mut w12[c * kl + o..c * kl + o + n] {
                    *v = i8::sample(r, f);
                }
            }
            for (i, v) in pair[2 * o..2 * o + 2 * n].iter_mut().enumerate() {
                *v = u8::sample(r, ext((i >= n) == hb, xf));
            }
            o += n;
        }
        let Some(l) = PartLens::new(lens[..np].iter().copied(), kl) else {
            println!("MUIR-KERNELS FAILED dots12_u8 case {case}: PartLens::new refused {:?}", &lens[..np]);
            process::exit(1)
        };
        let mut s = [0i32; 2 * MAX_PARTS];
        let mut d = [0i32; 24 * MAX_PARTS];
        if !pair_sums_u8(&l, &pair[..2 * kl], &mut s) || !l.dots12_u8(&w12[..12 * kl], &pair[..2 * kl], &s, &mut d) {
            println!("MUIR-KERNELS FAILED dots12_u8 case {case}: refused");
            process::exit(1);
        }
        let mut o = 0;
        for (p, &n) in lens[..np].iter().enumerate() {
            let (a, b) = (&pair[2 * o..2 * o + n], &pair[2 * o + n..2 * o + 2 * n]);
            for c in 0..12 {
                let w = &w12[c * kl + o..c * kl + o + n];
                for (x, at) in [(a, 24 * p + c), (b, 24 * p + 12 + c)] {
                    let want = dot_plain(w, x);
                    if d[at] as i64 != want {
                        fail("dots12_u8", kl, &[d[at] as i64], &[want]);
                    }
                }
            }
            o += n;
        }
        cases += 1;
    }
    // Short slices are refused.
    let l = PartLens::new([3usize, 5].into_iter(), 8);
    let (mut s, mut d) = ([0i32; 2 * MAX_PARTS], [0i32; 24 * MAX_PARTS]);
    if l.is_none_or(|l| pair_sums_u8(&l, &pair[..15], &mut s) || l.dots12_u8(&w12[..95], &pair[..16], &s, &mut d) || l.dots12_u8(&w12[..96], &pair[..15], &s, &mut d)) {
        println!("MUIR-KERNELS FAILED dots12_u8: a short slice accepted");
        process::exit(1);
    }
    cases
}

/// Multiplier and bias tables of one block of four channels, aligned as the blob's are.
/// The i16 convolution block's dot products in one call per channel pair (`mve::PartLens::dots4`:
/// four weight rows, 1 to 6 parts of random lengths 1..=140, one of 500..=699 in some extreme
/// cases, the split pair layout) against the plain dot products: random fills, all-extreme fills
/// (sums beyond i32, which must be reported) and one extreme channel and patch of one part among
/// random values. `true` must
/// mean every sum fits in i32 and equals the plain one; `false` that some sum does not fit. Both
/// outcomes must occur.
#[cfg(feature = "mve")]
fn check_dots4(buf: &mut Buffers<i16>, r: &mut Rng) -> usize {
    use muir::kernels::mve::PartLens;
    use muir::model::graph::MAX_PARTS;
    let (mut fits, mut over) = (0, 0);
    for case in 0..400u32 {
        let np = 1 + (r.next() % MAX_PARTS as u64) as usize;
        let mut lens = [0usize; MAX_PARTS];
        for l in lens.iter_mut().take(np) {
            *l = match r.next() % 4 {
                0 => 1 + (r.next() % 8) as usize,
                _ => 1 + (r.next() % 140) as usize,
            };
        }
        let mode = case % 4; // 0, 1 random; 2 all extreme; 3 one extreme part
        let hot = (r.next() % np as u64) as usize;
        if mode >= 2 && case % 8 < 6 {
            // Long enough for an extreme sum beyond i32 (2^22 per term).
            lens[hot] = 500 + (r.next() % 200) as usize;
        }
        let kl: usize = lens[..np].iter().sum();
        // In mode 3 only one channel's weights and one patch of the extreme part are extreme:
        // a single sum of the eight goes beyond i32.
        let (hc, hb) = ((r.next() % 4) as usize, r.next() % 2 == 0);
        let mut o = 0;
        for (p, &n) in lens[..np].iter().enumerate() {
            let ext = |one: bool| if mode == 2 || (mode == 3 && p == hot && one) { Fill::Min } else { Fill::Random };
            for c in 0..4 {
                let f = ext(c == hc);
                for v in &mut buf.w0[c * kl + o..c * kl + o + n] {
                    *v = i8::sample(r, f);
                }
            }
            for (i, v) in buf.pair[2 * o..2 * o + 2 * n].iter_mut().enumerate() {
                *v = i16::sample(r, ext((i >= n) == hb));
            }
            o += n;
        }
        let Some(l) = PartLens::new(lens[..np].iter().copied(), kl) else {
            println!("MUIR-KERNELS FAILED dots4 case {case}: PartLens::new refused {:?}", &lens[..np]);
            process::exit(1)
        };
        let mut d = [0i32; 8 * MAX_PARTS];
        let ok = l.dots4(&buf.w0[..4 * kl], &buf.pair[..2 * kl], &mut d);
        let mut all_fit = true;
        let mut o = 0;
        for (p, &n) in lens[..np].iter().enumerate() {
            let (a, b) = (&buf.pair[2 * o..2 * o + n], &buf.pair[2 * o + n..2 * o + 2 * n]);
            for c in 0..4 {
                let w = &buf.w0[c * kl + o..c * kl + o + n];
                for (x, at) in [(a, 8 * p + c), (b, 8 * p + 4 + c)] {
                    let want = dot_plain(w, x);
                    all_fit &= i32::try_from(want).is_ok();
                    if ok && d[at] as i64 != want {
                        fail("dots4", kl, &[d[at] as i64], &[want]);
                    }
                }
            }
            o += n;
        }
        if ok != all_fit {
            println!("MUIR-KERNELS FAILED dots4 case {case}: reported fit {ok}, plain sums fit {all_fit}");
            process::exit(1);
        }
        if ok {
            fits += 1;
        } else {
            over += 1;
        }
    }
    // Short slices are refused.
    let l = PartLens::new([3usize, 5].into_iter(), 8);
    let mut d = [0i32; 8 * MAX_PARTS];
    if fits == 0 || over == 0 || l.is_none_or(|l| l.dots4(&buf.w0[..31], &buf.pair[..16], &mut d) || l.dots4(&buf.w0[..32], &buf.pair[..15], &mut d)) {
        println!("MUIR-KERNELS FAILED dots4: fits {fits}, beyond i32 {over}, or a short slice accepted");
        process::exit(1);
    }
    if PartLens::new([3usize, 0, 5].into_iter(), 8).is_some() || PartLens::new([3usize, 5].into_iter(), 9).is_some() {
        println!("MUIR-KERNELS FAILED dots4: PartLens::new accepted a zero length or a wrong sum");
        process::exit(1);
    }
    400
}

#[cfg(feature = "mve")]
#[repr(C, align(8))]
struct Tables {
    mult: [u8; 8 * 4 * 6],
    bias: [u8; 32],
}

/// The Helium convolution epilogue (`mve::requant4`, four channels of one pixel on 32-bit lanes)
/// against the portable formula (`rshift_round(bias + sum_p requantize_i32(d, m), 8)`, clamped):
/// 1 to 6 parts, shifts 8 to 62, random and extreme dot products, multipliers and biases, every
/// output type. Where `FPSCR.QC` reports a saturation the engine recomputes the block, so only
/// the unsaturated results must match; both kinds of case must occur (counted), and small
/// operands must never report one. The same operands through `mve::requant4_lut` (sigmoid or
/// tanh table, then the output type's clamp) against the scalar `sigmoid_q12` / `tanh_q12`.
#[cfg(feature = "mve")]
fn check_requant(r: &mut Rng) -> usize {
    use muir::arith::{Multiplier, requantize_i32, rshift_round};
    use muir::arith::lut;
    use muir::kernels::mve::{self, Requant4};
    let mut t = Tables { mult: [0; 8 * 4 * 6], bias: [0; 32] };
    let (mut exact, mut saturated) = (0usize, 0usize);
    let (mut lut_exact, mut lut_mid) = (0usize, 0usize);
    let _ = mve::take_qc();
    for case in 0..6000u32 {
        let np = 1 + (case % 6) as usize;
        let kind = (case / 6) % 5;
        let mut d = [0i32; 48];
        let mut ms = [Multiplier { m: 0, shift: 8 }; 24];
        for ch in 0..4 {
            for p in 0..np {
                let shift = 8 + (r.next() % 55) as u8;
                let m = match kind {
                    0 => i32::MIN,
                    1 => i32::MAX,
                    _ => (r.next() >> 32) as i32,
                };
                ms[ch * np + p] = Multiplier { m, shift };
                let e = &mut t.mult[8 * (ch * np + p)..8 * (ch * np + p + 1)];
                e[..4].copy_from_slice(&m.to_le_bytes());
                e[4] = shift;
                e[5..].fill(0);
                d[8 * p + ch] = match kind {
                    0 | 1 => if r.next() % 2 == 0 { i32::MIN } else { i32::MAX },
                    2 => ((r.next() >> 32) as i32) >> 12,
                    3 => (r.next() % 2001) as i32 - 1000,
                    _ => (r.next() >> 32) as i32,
                };
            }
            let b = ((r.next() >> 33) as i64) - (1 << 30) + 1;
            let b = if kind == 3 { b >> 12 } else { b };
            t.bias[8 * ch..8 * ch + 8].copy_from_slice(&b.to_le_bytes());
        }
        // Small operands (kind 3): products below 2^31, shifts >= 8, nothing can saturate.
        if kind == 3 {
            for ch in 0..4 {
                for p in 0..np {
                    ms[ch * np + p].m >>= 12;
                    let m = ms[ch * np + p].m;
                    t.mult[8 * (ch * np + p)..8 * (ch * np + p) + 4].copy_from_slice(&m.to_le_bytes());
                }
            }
        }
        let (lo, hi) = [(0, 255), (-128, 127), (-32768, 32767), (0, 32767)][(case % 4) as usize];
        let mut want = [0i64; 4];
        for (ch, w) in want.iter_mut().enumerate() {
            let s: i64 = (0..np).map(|p| requantize_i32(d[8 * p + ch], ms[ch * np + p])).sum();
            let b = i64::from_le_bytes(t.bias[8 * ch..8 * ch + 8].try_into().unwrap_or_default());
            *w = rshift_round(s + b, 8).clamp(lo as i64, hi as i64);
        }
        let k = Requant4::new(np, lo, hi);
        let got: [i64; 4] = match lo {
            -128 => {
                let mut o = [0i8; 4];
                // SAFETY: `d` holds 48 values, the tables 4 channels of `np` parts, `o` four.
                unsafe { mve::requant4(d.as_ptr(), t.mult.as_ptr(), &k, np, t.bias.as_ptr(), o.as_mut_ptr()) };
                o.map(i64::from)
            }
            0 if hi == 255 => {
                let mut o = [0u8; 4];
                // SAFETY: as above.
                unsafe { mve::requant4(d.as_ptr(), t.mult.as_ptr(), &k, np, t.bias.as_ptr(), o.as_mut_ptr()) };
                o.map(i64::from)
            }
            _ => {
                let mut o = [0i16; 4];
                // SAFETY: as above.
                unsafe { mve::requant4(d.as_ptr(), t.mult.as_ptr(), &k, np, t.bias.as_ptr(), o.as_mut_ptr()) };
                o.map(i64::from)
            }
        };
        if mve::take_qc() {
            if kind == 3 {
                println!("MUIR-KERNELS FAILED requant4 case {case}: saturation reported for small operands");
                process::exit(1);
            }
            // One part: saturated lanes end at the clamp's bound, as the exact values do
            // (`conv_helium`'s `qc`: no recompute for one-part layers).
            if np == 1 && got != want {
                fail("requant4 (one part, saturated)", case as usize, &got, &want);
            }
            saturated += 1;
        } else {
            if got != want {
                fail("requant4", case as usize, &got, &want);
            }
            exact += 1;
        }
        // The same operands with a sigmoid or tanh table after the clamp to i16
        // (`mve::requant4_lut`), into each output type (saturating to it, as `OutRow::set`).
        let (f, table): (fn(i16) -> i16, _) = if case % 2 == 0 { (lut::sigmoid_q12, lut::sigmoid_table()) } else { (lut::tanh_q12, lut::tanh_table()) };
        let (olo, ohi) = [(0i64, 255i64), (-128, 127), (-32768, 32767)][(case / 2 % 3) as usize];
        let k = Requant4::new(np, -32768, 32767).with_out(olo as i32, ohi as i32);
        for (ch, w) in want.iter_mut().enumerate() {
            let s: i64 = (0..np).map(|p| requantize_i32(d[8 * p + ch], ms[ch * np + p])).sum();
            let b = i64::from_le_bytes(t.bias[8 * ch..8 * ch + 8].try_into().unwrap_or_default());
            *w = (f(rshift_round(s + b, 8).clamp(-32768, 32767) as i16) as i64).clamp(olo, ohi);
        }
        let got: [i64; 4] = match olo {
            -128 => {
                let mut o = [0i8; 4];
                // SAFETY: as above; the table's input range.
                unsafe { mve::requant4_lut(d.as_ptr(), t.mult.as_ptr(), &k, np, t.bias.as_ptr(), table, o.as_mut_ptr()) };
                o.map(i64::from)
            }
            0 => {
                let mut o = [0u8; 4];
                // SAFETY: as above.
                unsafe { mve::requant4_lut(d.as_ptr(), t.mult.as_ptr(), &k, np, t.bias.as_ptr(), table, o.as_mut_ptr()) };
                o.map(i64::from)
            }
            _ => {
                let mut o = [0i16; 4];
                // SAFETY: as above.
                unsafe { mve::requant4_lut(d.as_ptr(), t.mult.as_ptr(), &k, np, t.bias.as_ptr(), table, o.as_mut_ptr()) };
                o.map(i64::from)
            }
        };
        if mve::take_qc() {
            if kind == 3 {
                println!("MUIR-KERNELS FAILED requant4_lut case {case}: saturation reported for small operands");
                process::exit(1);
            }
            if np == 1 && got != want {
                fail("requant4_lut (one part, saturated)", case as usize, &got, &want);
            }
        } else {
            if got != want {
                fail("requant4_lut", case as usize, &got, &want);
            }
            lut_exact += 1;
            lut_mid += want.iter().filter(|&&w| w > olo && w < ohi).count();
        }
    }
    if lut_exact < 1000 || lut_mid < 1000 {
        println!("MUIR-KERNELS FAILED requant4_lut: {lut_exact} exact cases, {lut_mid} outputs inside the type's range");
        process::exit(1);
    }
    if exact < 1000 || saturated < 100 {
        println!("MUIR-KERNELS FAILED requant4: {exact} exact and {saturated} saturated cases (both kinds must occur)");
        process::exit(1);
    }
    exact + saturated + lut_exact
}

/// `mve::popcount20` (the refinement's census distances) against `count_ones`: random words,
/// all ones, single bits.
#[cfg(feature = "mve")]
fn check_popcount(r: &mut Rng) -> usize {
    let mut cases = 0;
    for case in 0..2000u32 {
        let mut w = [0u32; 20];
        for (i, x) in w.iter_mut().enumerate() {
            *x = match case % 4 {
                0 => u32::MAX,
                1 => 1 << ((r.next() % 32) as u32),
                2 if i % 3 == 0 => 0,
                _ => (r.next() >> 32) as u32,
            };
        }
        let want: u32 = w.iter().map(|x| x.count_ones()).sum();
        let got = muir::kernels::mve::popcount20(&w);
        if got != want {
            fail("popcount20", case as usize, &[got as i64], &[want as i64]);
        }
        cases += 1;
    }
    cases
}

/// The MGA softmax weights on Helium (`mve::exp_weights`, four keys a vector) against the
/// portable `attention::weight`: logit distances across `i32` (0, small, near the limits),
/// multipliers of both signs and at the limits, every shift 0 to 64 (those outside `2..=62` must
/// be refused), lengths 0 to 33; the largest weight and the sum it returns, and `FPSCR.QC` clear
/// afterwards. Then whole queries (`query_stats`, `aggregate_query`, which take the vector weights
/// per block of keys) against plain loops over `weight`, with key counts that leave partial
/// blocks and logits whose distance to the maximum does not fit `i32` (the scalar fallback).
///
/// The DSP build (`dsp::exp_weights`, shifts `1..=62`, no `FPSCR`) takes the same cases, and its
/// whole queries also through `attention::aggregate_query_cm` with the values read channel-major.
fn check_weights(r: &mut Rng, keys: &mut [i16; MAX_N], vals: &mut [i16; MAX_N]) -> usize {
    use muir::arith::Multiplier;
    use muir::kernels::attention;
    #[cfg(feature = "mve")]
    use muir::kernels::mve::exp_weights;
    #[cfg(not(feature = "mve"))]
    use muir::kernels::dsp::exp_weights;
    // Shifts each kernel takes (the others it must refuse).
    let takes = |s: u8| if cfg!(feature = "mve") { (2..=62).contains(&s) } else { (1..=62).contains(&s) };
    let mut cases = 0;
    for case in 0..6000u32 {
        let n = (case % 34) as usize;
        let shift = (r.next() % 65) as u8;
        let m = match case % 7 {
            0 => i32::MIN,
            1 => i32::MAX,
            2 => 0,
            3 => (1 << 30) + (r.next() % (1 << 30)) as i32,
            _ => (r.next() >> 32) as i32,
        };
        let mut d = [0i32; 33];
        for v in d.iter_mut().take(n) {
            let x = r.next();
            *v = match (x >> 60) % 6 {
                0 => 0,
                1 => -((x % 100000) as i32),
                2 => i32::MIN + (x % 3) as i32,
                3 => i32::MAX - (x % 3) as i32,
                4 => ((x >> 8) as i32) >> (x % 31),
                _ => (x >> 32) as i32,
            };
        }
        let mut e = [-7i32; 34];
        e[..n].copy_from_slice(&d[..n]);
        let got = exp_weights(&mut e[..n], m, shift);
        #[cfg(feature = "mve")]
        if muir::kernels::mve::take_qc() {
            println!("MUIR-KERNELS FAILED exp_weights case {case}: FPSCR.QC left set");
            process::exit(1);
        }
        let mult = Multiplier { m, shift };
        match got {
            None if takes(shift) => fail("exp_weights refused", case as usize, &[shift as i64], &[]),
            None => {
                if e[..n] != d[..n] {
                    fail("exp_weights wrote", case as usize, &[], &[]);
                }
            }
            Some((most, sum)) => {
                if !takes(shift) {
                    fail("exp_weights accepted", case as usize, &[shift as i64], &[]);
                }
                let want: [i64; 34] = core::array::from_fn(|k| if k < n { attention::weight(d[k] as i64, 0, mult) as i64 } else { -7 });
                let have: [i64; 34] = core::array::from_fn(|k| e[k] as i64);
                if have != want {
                    println!("MUIR-KERNELS FAILED exp_weights m={m} shift={shift}");
                    fail("exp_weights", case as usize, &have, &want);
                }
                let (wm, ws) = (want[..n].iter().copied().max().unwrap_or(0), want[..n].iter().sum::<i64>());
                if most as i64 != wm || sum != ws {
                    fail("exp_weights max/sum", case as usize, &[most as i64, sum], &[wm, ws]);
                }
            }
        }
        cases += 1;
    }
    // Whole queries.
    for case in 0..40u32 {
        let c = [8usize, 16, 32, 5][(case % 4) as usize];
        let cv = [4usize, 7, 64][(case % 3) as usize];
        let n = 1 + (r.next() % 90) as usize;
        let big = case % 5 == 4;
        for k in keys.iter_mut().take((n + 1) * c) {
            *k = if big { (r.next() >> 48) as i16 } else { ((r.next() >> 48) as i16) >> 6 };
        }
        for v in vals.iter_mut().take(n * cv) {
            *v = (r.next() >> 48) as i16;
        }
        let (q, ks) = (&keys[n * c..(n + 1) * c], &keys[..n * c]);
        let mult = match case % 3 {
            0 => Multiplier { m: 1 << 30, shift: 26 },
            1 => Multiplier { m: (1 << 30) + (r.next() % (1 << 30)) as i32, shift: 20 + (r.next() % 20) as u8 },
            _ => Multiplier { m: i32::MAX, shift: 1 },
        };
        let logit = |k: &[i16]| q.iter().zip(k).map(|(a, b)| *a as i64 * *b as i64).sum::<i64>();
        let max = ks.chunks_exact(c).map(logit).max().unwrap_or(0);
        let sum: i64 = ks.chunks_exact(c).map(|k| attention::weight(logit(k), max, mult) as i64).sum();
        let st = attention::query_stats(q, ks, mult);
        if st != (max, sum) {
            fail("query_stats", case as usize, &[st.0, st.1], &[max, sum]);
        }
        let mut acc = [0i64; 64];
        let mut got = [0i16; 64];
        attention::aggregate_query(q, ks, &vals[..n * cv], cv, st, mult, -1, &mut acc, &mut got[..cv]);
        let mut want = [0i64; 64];
        for (ch, w) in want.iter_mut().enumerate().take(cv) {
            let a: i64 = ks.chunks_exact(c).enumerate().map(|(j, k)| attention::weight(logit(k), max, mult) as i64 * vals[j * cv + ch] as i64).sum();
            *w = muir::arith::sat_i16(muir::arith::div_round(muir::arith::shift_round(a, -1), sum)) as i64;
        }
        let have: [i64; 64] = core::array::from_fn(|k| got[k] as i64);
        if have[..cv] != want[..cv] {
            fail("aggregate_query", case as usize, &have[..cv], &want[..cv]);
        }
        cases += 1;
        // The same values read channel-major (channel `ch` of key `j` at `ch n + j`).
        #[cfg(not(feature = "mve"))]
        {
            attention::aggregate_query_cm(q, ks, &vals[..n * cv], n, cv, st, mult, -1, &mut acc, &mut got[..cv]);
            for (ch, w) in want.iter_mut().enumerate().take(cv) {
                let a: i64 = ks.chunks_exact(c).enumerate().map(|(j, k)| attention::weight(logit(k), max, mult) as i64 * vals[ch * n + j] as i64).sum();
                *w = muir::arith::sat_i16(muir::arith::div_round(muir::arith::shift_round(a, -1), sum)) as i64;
            }
            let have: [i64; 64] = core::array::from_fn(|k| got[k] as i64);
            if have[..cv] != want[..cv] {
                fail("aggregate_query_cm", case as usize, &have[..cv], &want[..cv]);
            }
            cases += 1;
        }
    }
    cases
}

/// Widest image of the refinement checks.
const REF_W: usize = 160;

/// Buffers of the refinement checks (static: no large stack frames).
struct RefineBufs {
    img: [u8; REF_W * 9 * 3],
    grey: [u8; 7 * REF_W],
    got: [u64; REF_W + 1],
    want: [u64; REF_W + 1],
    codes: [[u64; REF_W]; 6],
}

static mut REFINE: RefineBufs = RefineBufs {
    img: [0; REF_W * 9 * 3],
    grey: [0; 7 * REF_W],
    got: [0; REF_W + 1],
    want: [0; REF_W + 1],
    codes: [[0; REF_W]; 6],
};

/// `row_costs`' output in the refinement checks.
static mut ROW_COSTS: [u16; muir::kernels::fullres::SLOTS * REF_W] = [0; muir::kernels::fullres::SLOTS * REF_W];

/// The refinement's kernels against their portable twins (`muir::kernels::fullres`): with
/// Helium the vector ones, without it the DSP census (`census_interior_dsp`) and a row's costs
/// from shared column sums (`row_costs`). Census rows (`mve::census`) of grey and RGB images of widths 1 to 40 and up to 160, rows
/// inside and outside the image, random, two-level (equal neighbours) and constant pixels, a
/// grey scratch too short for the vector path; the costs of a pixel's band (`mve::cost_pairs`) on
/// random, all-ones and zero codes at every column with bands starting left and right of the
/// clamping limit; path steps (`mve::path_update`) with shifted bands, random and extreme costs
/// and penalties (the portable fallback beyond the u16 lanes), sentinels past the written values.
fn check_refine(r: &mut Rng) -> usize {
    use muir::input::{ImageView, PixelFormat};
    use muir::kernels::fullres::{self, Band, SLOTS};
    // SAFETY: called once, the only user of `REFINE`.
    let b = unsafe { &mut *core::ptr::addr_of_mut!(REFINE) };
    let mut cases = 0;
    let widths = (1..=40usize).chain([63, 64, 65, 100, 127, 160]);
    for (i, w) in widths.enumerate() {
        for h in [1usize, 2, 5, 9] {
            for fmt in [PixelFormat::Gray8, PixelFormat::Rgb8] {
                let len = w * h * fmt.channels();
                let kind = (i + h) % 4;
                for v in b.img.iter_mut().take(len) {
                    let x = (r.next() >> 56) as u8;
                    *v = match kind {
                        0 => x,
                        1 => if x & 1 == 0 { 0 } else { 255 },
                        2 => 77,
                        _ => x & 3,
                    };
                }
                let Ok(img) = ImageView::new(w, h, fmt, &b.img[..len]) else {
                    println!("MUIR-KERNELS FAILED census: image {w}x{h}");
                    process::exit(1)
                };
                for y in -4..(h as isize + 4) {
                    for grey_rows in [7usize, 3] {
                        let sentinel = r.next();
                        b.got.fill(sentinel);
                        b.want.fill(sentinel);
                        fullres::census_row(&img, y, &mut b.grey[..grey_rows * w], &mut b.got[..w]);
                        fullres::census_row_portable(&img, y, &mut b.grey[..grey_rows * w], &mut b.want[..w]);
                        if b.got != b.want {
                            let at = b.got.iter().zip(&b.want).position(|(g, x)| g != x).unwrap_or(0);
                            println!("MUIR-KERNELS FAILED census {w}x{h} y={y} rows={grey_rows} x={at}: kernel {:#x}, plain {:#x}", b.got[at], b.want[at]);
                            process::exit(1);
                        }
                        cases += 1;
                    }
                }
            }
        }
    }
    // Costs.
    for case in 0..60u32 {
        let w = match case % 6 {
            0 => 2 + (r.next() % 6) as usize,
            1 => REF_W,
            _ => 3 + (r.next() % 60) as usize,
        };
        for row in b.codes.iter_mut() {
            for c in row.iter_mut().take(w) {
                *c = match case % 5 {
                    0 => u64::MAX,
                    1 => 0,
                    2 => r.next() >> 16,
                    _ => r.next(),
                };
            }
        }
        let [l0, l1, l2, r0, r1, r2] = &b.codes;
        let left: [&[u64]; 3] = [&l0[..w], &l1[..w], &l2[..w]];
        let right: [&[u64]; 3] = [&r0[..w], &r1[..w], &r2[..w]];
        for x in 0..w {
            for _ in 0..4 {
                let first = (x as i64 + 3 - (r.next() % 40) as i64) as i16;
                let len = (r.next() % (SLOTS as u64 + 3)) as i16;
                let band = Band { first, len };
                let (mut got, mut want) = ([0xA5A5u16; SLOTS + 2], [0xA5A5u16; SLOTS + 2]);
                fullres::pixel_costs(&left, &right, w, x, band, &mut got);
                fullres::pixel_costs_portable(&left, &right, w, x, band, &mut want);
                if got != want {
                    let g: [i64; SLOTS + 2] = core::array::from_fn(|k| got[k] as i64);
                    let p: [i64; SLOTS + 2] = core::array::from_fn(|k| want[k] as i64);
                    println!("MUIR-KERNELS FAILED costs w={w} x={x} first={first} len={len}");
                    fail("costs", x, &g, &p);
                }
                cases += 1;
            }
        }
    }
    // A row's costs from shared column sums (`row_costs`, the DSP build's path) against the
    // candidates' own: neighbouring bands that overlap, jump apart or are empty.
    for case in 0..200u32 {
        let w = 1 + (r.next() % REF_W as u64) as usize;
        for row in b.codes.iter_mut() {
            for c in row.iter_mut().take(w) {
                *c = if case % 7 == 0 { u64::MAX } else { r.next() >> 16 };
            }
        }
        let [l0, l1, l2, r0, r1, r2] = &b.codes;
        let left: [&[u64]; 3] = [&l0[..w], &l1[..w], &l2[..w]];
        let right: [&[u64]; 3] = [&r0[..w], &r1[..w], &r2[..w]];
        let mut bands = [0i16; 2 * REF_W];
        for x in 0..w {
            let (first, len) = match r.next() % 8 {
                0 => (0, 0),
                1 => ((r.next() % 200) as i16, (r.next() % (SLOTS as u64 + 1)) as i16),
                _ => ((10 + x / 3 + (r.next() % 3) as usize) as i16, (8 + r.next() % 12) as i16),
            };
            (bands[x], bands[w + x]) = (first, len);
        }
        // SAFETY: called once, the only user of `ROW_COSTS`.
        let got = unsafe { &mut *core::ptr::addr_of_mut!(ROW_COSTS) };
        got.fill(0xA5A5);
        fullres::row_costs(&left, &right, w, &bands[..2 * w], &mut got[..SLOTS * w]);
        for x in 0..w {
            let band = Band { first: bands[x], len: bands[w + x] };
            let mut want = [0xA5A5u16; SLOTS];
            fullres::pixel_costs_portable(&left, &right, w, x, band, &mut want);
            let n = (band.len.max(0) as usize).min(SLOTS);
            if got[x * SLOTS..x * SLOTS + n] != want[..n] {
                println!("MUIR-KERNELS FAILED row costs w={w} x={x} first={} len={}", band.first, band.len);
                process::exit(1);
            }
            cases += 1;
        }
    }
    // Path steps.
    for case in 0..20000u32 {
        let kind = case % 6;
        let mut prev = [0u16; SLOTS + 4];
        let mut cost = [0u16; SLOTS + 4];
        for (p, c) in prev.iter_mut().zip(cost.iter_mut()) {
            let x = r.next();
            (*p, *c) = match kind {
                0 => ((x % 4096) as u16, ((x >> 20) % 433) as u16),
                1 => (u16::MAX, u16::MAX),
                2 => ((x >> 48) as u16, (x >> 32) as u16),
                3 => (65000 + (x % 536) as u16, (x >> 40) as u16),
                _ => ((x % 1500) as u16, ((x >> 20) % 433) as u16),
            };
        }
        let pband = Band { first: (r.next() % 60) as i16 - 5, len: (r.next() % (SLOTS as u64 + 4)) as i16 - 1 };
        let band = Band { first: pband.first + (r.next() % 80) as i16 - 40, len: (r.next() % (SLOTS as u64 + 4)) as i16 - 1 };
        let band = if kind == 5 { Band { first: pband.first + (r.next() % 5) as i16 - 2, len: pband.len } } else { band };
        let p2 = match case % 7 {
            0 => (r.next() % 70000) as u32,
            1 => u16::MAX as u32 - 256 - prev.iter().take(pband.len.max(0) as usize).min().copied().unwrap_or(0) as u32,
            _ => fullres::penalty2((r.next() >> 56) as u8, (r.next() >> 56) as u8),
        };
        let plen = (r.next() % (SLOTS as u64 + 4)) as usize;
        let olen = (r.next() % (SLOTS as u64 + 4)) as usize;
        let (mut got, mut want) = ([0x5A5Au16; SLOTS + 4], [0x5A5Au16; SLOTS + 4]);
        fullres::path_step(&prev[..plen], pband, &cost, band, p2, &mut got[..olen]);
        fullres::path_step_portable(&prev[..plen], pband, &cost, band, p2, &mut want[..olen]);
        if got != want {
            let g: [i64; SLOTS + 4] = core::array::from_fn(|k| got[k] as i64);
            let p: [i64; SLOTS + 4] = core::array::from_fn(|k| want[k] as i64);
            println!("MUIR-KERNELS FAILED path step case {case}: {pband:?} -> {band:?} p2={p2} plen={plen} olen={olen}");
            fail("path step", case as usize, &g, &p);
        }
        cases += 1;
    }
    cases
}

/// Largest patch of the convolution-row check (`k * k * sum(parts)`).
const CONV_KL: usize = 9 * 72;
/// Largest input part (`h x w x ch`) and output (`h x w x cout`) of the convolution-row check.
const CONV_IN: usize = 5 * 13 * 24;
const CONV_OUT: usize = 5 * 13 * 13;

/// The tables and buffers of the convolution-row check, aligned as the engine's are.
#[repr(C, align(8))]
struct ConvBufs {
    weights: [i8; 13 * CONV_KL],
    mult: [u8; 8 * 13 * 3],
    bias: [u8; 8 * 13],
    x8: [[u8; CONV_IN]; 3],
    x16: [[i16; CONV_IN]; 3],
    want: [i16; CONV_OUT],
    got: [i16; CONV_OUT],
    scratch: [u8; 24 * CONV_KL],
}

static mut CONV: ConvBufs = ConvBufs {
    weights: [0; 13 * CONV_KL],
    mult: [0; 8 * 13 * 3],
    bias: [0; 8 * 13],
    x8: [[0; CONV_IN]; 3],
    x16: [[0; CONV_IN]; 3],
    want: [0; CONV_OUT],
    got: [0; CONV_OUT],
    scratch: [0; 24 * CONV_KL],
};

/// The DSP build's requantisation of the convolution's short epilogue (`dsp::requantize_i32`,
/// `SMLAL` and a 64-bit shift split at 32) against the specification (`arith::requantize` of
/// the same `i32` sum): every shift the short path takes (8 to 62), extreme and random sums and
/// multipliers (both signs, zero, the i32 limits).
#[cfg(not(feature = "mve"))]
fn check_requant_dsp(r: &mut Rng) -> usize {
    use muir::arith::{Multiplier, requantize};
    use muir::kernels::dsp;
    let edges = [i32::MIN, i32::MIN + 1, -65536, -1, 0, 1, 65535, i32::MAX - 1, i32::MAX];
    let mut cases = 0;
    for shift in 8..=62u8 {
        for i in 0..120usize {
            let pick = |r: &mut Rng, j: usize| match j % 3 {
                0 => edges[(r.next() % edges.len() as u64) as usize],
                1 => ((r.next() >> 32) as i32) >> (r.next() % 31),
                _ => (r.next() >> 32) as i32,
            };
            let (acc, m) = (pick(r, i), pick(r, i / 3));
            let mult = Multiplier { m, shift };
            let (got, want) = (dsp::requantize_i32(acc, mult), requantize(acc as i64, mult));
            if got != want {
                println!("MUIR-KERNELS FAILED dsp::requantize_i32({acc}, m={m}, shift={shift}): {got}, requantize {want}");
                process::exit(1);
            }
            cases += 1;
            // The one-part epilogue folded into one multiply-add (`dsp::Folded`): the short
            // path's `(requantize + bias + 2^7) >> 8`, where it is made (shifts 24 to 62, the
            // folded constant within 2^62), for biases of either sign up to 2^40.
            let bias = match i % 4 {
                0 => 0,
                1 => ((r.next() >> 40) as i64) - (1 << 23),
                2 => ((r.next() >> 24) as i64) - (1 << 39),
                _ => [-(1i64 << 40) + 1, -129, -128, 127, (1 << 40) - 1][(r.next() % 5) as usize],
            };
            if let Some(f) = dsp::Folded::new(mult, bias) {
                let (got, want) = (f.apply(acc) as i64, (want + bias + 128) >> 8);
                if got != want {
                    println!("MUIR-KERNELS FAILED dsp::Folded({acc}, m={m}, shift={shift}, bias={bias}): {got}, short path {want}");
                    process::exit(1);
                }
                cases += 1;
                // Shifts of 33 and more: the one-`SMMLA` form (`Folded::apply_high`).
                if f.high_only() != (shift >= 33) || (f.high_only() && f.apply_high(acc) as i64 != want) {
                    println!("MUIR-KERNELS FAILED dsp::Folded::apply_high({acc}, m={m}, shift={shift}, bias={bias}): short path {want}");
                    process::exit(1);
                }
            } else if (24..=40).contains(&shift) && bias.abs() < 1 << 20 {
                println!("MUIR-KERNELS FAILED dsp::Folded not made for shift={shift}, bias={bias}");
                process::exit(1);
            }
        }
    }
    cases
}

/// `dsp::Folded::apply_high` (one `SMMLA`) against `Folded::apply` (`SMLAL` onto the folded
/// constant) for shifts 33 to 46 (the blobs' largest), random sums, multipliers and biases:
/// 40,000 cases, so that the few where the product's low word carries into the kept bits
/// (about one in 2^(s - 24)) come up.
#[cfg(not(feature = "mve"))]
fn check_folded_high(r: &mut Rng) -> usize {
    use muir::arith::Multiplier;
    use muir::kernels::dsp;
    let mut cases = 0;
    for i in 0..40_000u32 {
        let shift = 33 + (i % 14) as u8;
        let (acc, m) = ((r.next() >> 32) as i32, (r.next() >> 32) as i32);
        let bias = ((r.next() >> 40) as i64) - (1 << 23);
        if let Some(f) = dsp::Folded::new(Multiplier { m, shift }, bias) {
            if !f.high_only() || f.apply_high(acc) != f.apply(acc) {
                println!("MUIR-KERNELS FAILED dsp::Folded::apply_high({acc}, m={m}, shift={shift}, bias={bias}): {}, apply {}", f.apply_high(acc), f.apply(acc));
                process::exit(1);
            }
            cases += 1;
        }
    }
    cases
}

/// The short epilogue's sum over the parts of a block (`dsp::requant_parts`, the assembly loop
/// of `conv_row_i16_nat`) against the specification: per value, the sum over parts of
/// `arith::requantize` of the part's sum with its channel's multiplier, and false exactly where
/// some part's sum is not an i32. 1 to 6 parts, shifts 8 to 62 (the short path's), extreme and
/// random multipliers and sums, sums just outside i32 in a random part. Also one part's
/// contributions added for 1 to 20 pairs (`dsp::requant_add`, `w16_parts`).
#[cfg(not(feature = "mve"))]
fn check_requant_parts(r: &mut Rng) -> usize {
    use muir::arith::{Multiplier, requantize};
    use muir::kernels::dsp;
    let edges = [i32::MIN, i32::MIN + 1, -65536, -1, 0, 1, 65535, i32::MAX - 1, i32::MAX];
    let mut cases = 0;
    for i in 0..3000usize {
        let np = 1 + i % 6;
        let pick = |r: &mut Rng, j: usize| match j % 3 {
            0 => edges[(r.next() % edges.len() as u64) as usize],
            1 => ((r.next() >> 32) as i32) >> (r.next() % 31),
            _ => (r.next() >> 32) as i32,
        };
        let mut sums = [[0i64; 4]; 6];
        let mut mults = [[Multiplier { m: 0, shift: 8 }; 2]; 6];
        let mut reqs = [[dsp::NatReq::ZERO; 2]; 6];
        for p in 0..np {
            for c in 0..4 {
                sums[p][c] = pick(r, i / 7 + c) as i64;
            }
            for c in 0..2 {
                let shift = if i % 5 == 0 { [8u8, 31, 32, 33, 62][(r.next() % 5) as usize] } else { 8 + (r.next() % 55) as u8 };
                mults[p][c] = Multiplier { m: pick(r, i / 3 + c), shift };
                reqs[p][c] = dsp::NatReq::new(mults[p][c]);
            }
        }
        let outside = i % 11 == 3;
        if outside {
            let (p, c) = ((r.next() % np as u64) as usize, (r.next() % 4) as usize);
            sums[p][c] = [i32::MAX as i64 + 1, i32::MIN as i64 - 1, 1 << 40, -(1 << 33)][(r.next() % 4) as usize];
        }
        let mut want = [0i64; 4];
        for p in 0..np {
            for c in 0..4 {
                want[c] += requantize(sums[p][c], mults[p][c & 1]);
            }
        }
        let mut got = [0i64; 4];
        let fits = dsp::requant_parts(&sums[..np], &reqs[..np], &mut got);
        if fits == outside || (fits && got != want) {
            println!("MUIR-KERNELS FAILED dsp::requant_parts case {i} ({np} parts): {got:?} fits={fits}, requantize {want:?}");
            process::exit(1);
        }
        cases += 1;
        // One part for 1 to 20 pairs (`dsp::requant_add`, `w16_parts`): added to random i64
        // sums; the entry after the last pair untouched.
        let n = 1 + i % 20;
        let mut pairs = [[0i32; 4]; 21];
        let mut acc = [[0i64; 4]; 21];
        for (d, a) in pairs.iter_mut().zip(acc.iter_mut()) {
            for c in 0..4 {
                d[c] = pick(r, i / 7 + c);
                a[c] = (r.next() as i64) >> (8 + r.next() % 40);
            }
        }
        let mut want = acc;
        for (d, a) in pairs.iter().zip(want.iter_mut()).take(n) {
            for c in 0..4 {
                a[c] += requantize(d[c] as i64, mults[0][c & 1]);
            }
        }
        dsp::requant_add(&pairs[..n], &reqs[0], &mut acc[..n]);
        let mut after = acc;
        dsp::requant_add(&pairs[..0], &reqs[0], &mut after[..n]);
        if acc != want || after != acc {
            println!("MUIR-KERNELS FAILED dsp::requant_add case {i} ({n} pairs, shifts {}, {})", mults[0][0].shift, mults[0][1].shift);
            process::exit(1);
        }
        cases += 1;
    }
    cases
}

/// The DSP build's group copies of the gathers (`dsp::put_groups_i16`, the i16 pair layout's
/// swap; `dsp::widen_u8_groups`, u8 pairs widened to it): 1 to 9 groups, word-aligned buffers
/// (the assembly loops) and not (the compiled ones), both patches of a pair, against the
/// layouts written out value by value; nothing outside the groups written.
#[cfg(not(feature = "mve"))]
fn check_groups(r: &mut Rng) -> usize {
    use muir::kernels::dsp;
    #[repr(C, align(8))]
    struct A<T>([T; 96]);
    let mut s16 = A([0i16; 96]);
    let mut s8 = A([0u8; 96]);
    for v in s16.0.iter_mut() {
        *v = (r.next() >> 48) as i16;
    }
    for v in s8.0.iter_mut() {
        *v = (r.next() >> 56) as u8;
    }
    let mut cases = 0;
    for q in 1..=9usize {
        for (so, dof) in [(0, 0), (1, 0), (0, 1), (2, 2)] {
            for second in [false, true] {
                let mut d = A([0x5A5Ai16; 96]);
                dsp::put_groups_i16(&mut d.0[dof..dof + 8 * q], &s16.0[so..so + 4 * q], second);
                let off = if second { 4 } else { 0 };
                for (i, &got) in d.0.iter().enumerate() {
                    let j = i.wrapping_sub(dof);
                    let want = if i >= dof && j < 8 * q && (j % 8) / 4 == off / 4 { s16.0[so + 4 * (j / 8) + [0, 2, 1, 3][j % 4]] } else { 0x5A5A };
                    if got != want {
                        println!("MUIR-KERNELS FAILED dsp::put_groups_i16 q={q} offsets {so}/{dof} second={second} at {i}: {got}, want {want}");
                        process::exit(1);
                    }
                }
                cases += 1;
            }
            let mut d = A([0x5A5Ai16; 96]);
            dsp::widen_u8_groups(&mut d.0[dof..dof + 4 * q], &s8.0[so..so + 4 * q]);
            for (i, &got) in d.0.iter().enumerate() {
                let j = i.wrapping_sub(dof);
                let want = if i >= dof && j < 4 * q { s8.0[so + 4 * (j / 4) + [0, 2, 1, 3][j % 4]] as i16 } else { 0x5A5A };
                if got != want {
                    println!("MUIR-KERNELS FAILED dsp::widen_u8_groups q={q} offsets {so}/{dof} at {i}: {got}, want {want}");
                    process::exit(1);
                }
            }
            cases += 1;
        }
    }
    cases
}

/// Whole convolutions row by row through the engine's entry (`engine::encoder::run_conv`: with
/// Helium the vector epilogue of `conv`, on the DSP build the u8 rows widened once to the i16
/// loop) against the plain twin `conv_plain`: random layers of 1 to 3 parts (channel counts with
/// and without whole groups of four), kernels 1, 3 and 7, strides 1 and 2, odd and even widths
/// and channel counts, u8 and i16 inputs, every output type and activation, shifts inside and
/// outside the vector path's range, large biases, and extreme operands that saturate the vector
/// lanes (the recomputed blocks).
fn check_conv(r: &mut Rng) -> usize {
    use muir::engine::encoder::run_conv;
    use muir::kernels::OutRow;
    use muir::kernels::conv::{BiasRef, ConvParams, MultRef, PartRows, conv_plain};
    use muir::model::graph::PostOp;
    // SAFETY: called once, the only user of `CONV`.
    let b = unsafe { &mut *core::ptr::addr_of_mut!(CONV) };
    let mut cases = 0;
    for case in 0..600u32 {
        let wide = case % 2 == 1;
        let np = 1 + (r.next() % 3) as usize;
        let mut parts = [0usize; 3];
        for ch in parts.iter_mut().take(np) {
            *ch = match r.next() % 4 {
                0 => 4 * (1 + (r.next() % 6) as usize),
                _ => 1 + (r.next() % 24) as usize,
            };
        }
        let cin: usize = parts.iter().sum();
        let k = match r.next() % 3 {
            0 => 1,
            1 if cin <= 8 => 7,
            _ => 3,
        };
        let stride = 1 + (r.next() % 2) as usize;
        let (h, w) = (1 + (r.next() % 5) as usize, 1 + (r.next() % 13) as usize);
        let cout = 1 + (r.next() % 13) as usize;
        let kl = k * k * cin;
        let extreme = case % 5 == 4;
        for v in b.weights.iter_mut().take(cout * kl) {
            *v = if extreme { if r.next() % 2 == 0 { i8::MIN } else { i8::MAX } } else { (r.next() >> 56) as i8 };
        }
        // Shifts: mostly the vector path's 8..=62; some layers one outside it (the portable path).
        let odd_shift = match case % 7 {
            3 => Some(5u8),
            5 => Some(63u8),
            _ => None,
        };
        for (i, e) in b.mult.chunks_exact_mut(8).take(cout * np).enumerate() {
            let shift = match odd_shift {
                Some(s) if i == cout * np / 2 => s,
                _ if extreme => 8 + (r.next() % 6) as u8,
                _ => 20 + (r.next() % 20) as u8,
            };
            let m = if extreme { i32::MAX - (r.next() % 2) as i32 } else { (r.next() >> 33) as i32 + (1 << 29) };
            e[..4].copy_from_slice(&m.to_le_bytes());
            e[4] = shift;
            e[5..].fill(0);
        }
        let big_bias = case % 11 == 6;
        for (c, e) in b.bias.chunks_exact_mut(8).take(cout).enumerate() {
            let v = if big_bias && c == 0 { 1i64 << 35 } else { ((r.next() >> 40) as i64) - (1 << 23) };
            e.copy_from_slice(&v.to_le_bytes());
        }
        let post = [PostOp::None, PostOp::Relu, PostOp::Sigmoid, PostOp::Tanh][(r.next() % 4) as usize];
        let p = ConvParams {
            k,
            stride,
            parts: &parts[..np],
            cout,
            weights: &b.weights[..cout * kl],
            bias: BiasRef(&b.bias[..8 * cout]),
            mult: MultRef(&b.mult[..8 * cout * np]),
            post,
        };
        let (h_out, w_out) = ((h + 2 * (k / 2) - k) / stride + 1, p.out_width(w));
        let n_out = h_out * w_out * cout;
        let out_kind = r.next() % 3;
        let fill = |r: &mut Rng| if extreme { Fill::Max } else if r.next() % 8 == 0 { Fill::Min } else { Fill::Random };
        if wide {
            for (t, &ch) in b.x16.iter_mut().zip(&parts[..np]) {
                let f = fill(r);
                for v in t.iter_mut().take(h * w * ch) {
                    *v = i16::sample(r, f);
                }
            }
        } else {
            for (t, &ch) in b.x8.iter_mut().zip(&parts[..np]) {
                let f = fill(r);
                for v in t.iter_mut().take(h * w * ch) {
                    *v = u8::sample(r, f);
                }
            }
        }
        b.want[..n_out].fill(0);
        b.got[..n_out].fill(0);
        let (want, got) = (&mut b.want[..n_out], &mut b.got[..n_out]);
        // Both outputs as i16 storage, or as bytes of the same memory (i8 / u8 rows).
        fn row<'a>(kind: u64, v: &'a mut [i16]) -> OutRow<'a> {
            match kind {
                0 => OutRow::I16(v),
                1 => OutRow::U8(bytemuck::cast_slice_mut(v)),
                _ => OutRow::I8(bytemuck::cast_slice_mut(v)),
            }
        }
        let row_len = w_out * cout;
        macro_rules! run {
            ($x:expr) => {{
                let ts: [&[_]; 3] = [&$x[0][..h * w * parts[0]], &$x[1][..h * w * parts[1]], &$x[2][..h * w * parts[2]]];
                conv_plain(&p, &ts[..np], h, w, &mut row(out_kind, want));
                for y in 0..h_out {
                    let rows: [PartRows<'_, _>; 3] = core::array::from_fn(|i| PartRows::of_tensor(ts[i], h, w * parts[i], y, k, stride));
                    let mut all = row(out_kind, got);
                    let dst = match &mut all {
                        OutRow::I16(o) => OutRow::I16(&mut o[y * row_len..(y + 1) * row_len]),
                        OutRow::U8(o) => OutRow::U8(&mut o[y * row_len..(y + 1) * row_len]),
                        OutRow::I8(o) => OutRow::I8(&mut o[y * row_len..(y + 1) * row_len]),
                    };
                    let mut dst = dst;
                    run_conv(&p, &rows[..np], w, &mut dst, &mut b.scratch);
                }
            }};
        }
        if wide {
            run!(b.x16);
        } else {
            run!(b.x8);
        }
        if b.want[..n_out] != b.got[..n_out] {
            let at = b.want[..n_out].iter().zip(&b.got[..n_out]).position(|(a, g)| a != g).unwrap_or(0);
            println!(
                "MUIR-KERNELS FAILED conv row case {case}: k={k} stride={stride} parts={:?} cout={cout} {h}x{w} wide={wide} out={out_kind} post={} at {at}: engine {}, plain {}",
                &parts[..np], post as u8, b.got[at], b.want[at]
            );
            process::exit(1);
        }
        cases += 1;
        // The DSP build's rows with the gathered pixel pairs in a second buffer
        // (`conv::conv_row_i16_w16_spare`, the 1/16 ConvGRU gates' path): the single patch and
        // the widened weights in the head of the scratch, `j` pairs of patches (3 to 8) in a
        // buffer after it, against the same plain results.
        #[cfg(not(feature = "mve"))]
        if wide && w_out >= 6 {
            let j = 3 + (r.next() as usize) % 6;
            let words: usize = parts[..np].iter().map(|&ch| ch * k * k / 4 * 4).sum();
            let head = 4 + 2 * kl + 4 * words + 4;
            let len = 4 + 4 * kl * j;
            if head + len <= b.scratch.len() {
                b.got[..n_out].fill(0);
                let x = &b.x16;
                let ts: [&[i16]; 3] = [&x[0][..h * w * parts[0]], &x[1][..h * w * parts[1]], &x[2][..h * w * parts[2]]];
                let (scratch, spare) = b.scratch.split_at_mut(head);
                let mut used = true;
                for y in 0..h_out {
                    let rows: [PartRows<'_, i16>; 3] = core::array::from_fn(|i| PartRows::of_tensor(ts[i], h, w * parts[i], y, k, stride));
                    let mut all = row(out_kind, &mut b.got[..n_out]);
                    let mut dst = match &mut all {
                        OutRow::I16(o) => OutRow::I16(&mut o[y * row_len..(y + 1) * row_len]),
                        OutRow::U8(o) => OutRow::U8(&mut o[y * row_len..(y + 1) * row_len]),
                        OutRow::I8(o) => OutRow::I8(&mut o[y * row_len..(y + 1) * row_len]),
                    };
                    used &= muir::kernels::conv::conv_row_i16_w16_spare(&p, &rows[..np], w, &mut dst, scratch, &mut spare[..len]);
                }
                if !used || b.want[..n_out] != b.got[..n_out] {
                    let at = b.want[..n_out].iter().zip(&b.got[..n_out]).position(|(a, g)| a != g).unwrap_or(0);
                    println!(
                        "MUIR-KERNELS FAILED conv_row_i16_w16_spare case {case}: k={k} stride={stride} parts={:?} cout={cout} {h}x{w} pairs={j} out={out_kind} used={used} at {at}: got {}, plain {}",
                        &parts[..np], b.got[at], b.want[at]
                    );
                    process::exit(1);
                }
                cases += 1;
            }
        }
    }
    cases
}

/// The DSP build's in-place i16 kernel (`dsp::widen_weights_nat`, `dsp::nat_block`, the 1/8
/// ConvGRU gates' `conv::conv_row_i16_nat`) on the vectors `check` just filled, against the plain
/// products: one table of three entries over the first `min(n / 4, 127)` groups (one i32 chunk)
/// and the next up to 7 values: a two-pixel groups entry (pixels a and b in one buffer at value
/// offsets 0 or 1 each: the LDRD loop and the unaligned one), a one-pixel groups entry (pixel b
/// alone, bstep 0) and a plain entry (two pixels, w1's weights `kl` bytes after w0's), each into
/// its own part's sums from random starting values.
#[cfg(not(feature = "mve"))]
fn check_nat(buf: &mut Buffers<i16>, ww: &mut [u32; MAX_N], n: usize, r: &mut Rng) -> usize {
    use muir::kernels::dsp::{self, NatEntry};
    let q = (n / 4).min(127);
    if q == 0 {
        return 0;
    }
    let m = 1 + n % 7;
    ww.fill(0x5A5A_5A5A);
    dsp::widen_weights_nat(&buf.w0[..4 * q], &buf.w1[..4 * q], q, ww);
    untouched("dsp::widen_weights_nat", &ww[..], 4 * q);
    // The plain entry's weights: w0's `m` then, `kl = 8` bytes later, w1's.
    let mut wp = [0i8; 16];
    wp[..m].copy_from_slice(&buf.w0[..m]);
    wp[8..8 + m].copy_from_slice(&buf.w1[..m]);
    let mut cases = 0;
    for (oa, gap) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
        // Pixel a at `oa`, pixel b at `ob`, each `4 q + m` values, in the pair buffer.
        let len = 4 * q + m;
        let ob = oa + len + gap;
        buf.pair[oa..oa + len].copy_from_slice(&buf.a[..len]);
        buf.pair[ob..ob + len].copy_from_slice(&buf.b[..len]);
        let (a, b) = (&buf.a[..4 * q], &buf.b[..4 * q]);
        let (w0, w1) = (&buf.w0[..4 * q], &buf.w1[..4 * q]);
        let bstep = 2 * (ob - oa);
        let table = [
            NatEntry::new(buf.pair[oa..].as_ptr(), 0, 0, q, bstep, 0),
            NatEntry::new(buf.pair[ob..].as_ptr(), 0, 0, q, 0, 1),
            NatEntry::new(buf.pair[oa + 4 * q..].as_ptr(), 0, 0, m | NatEntry::PLAIN, bstep, 2),
        ];
        let start: [[i64; 4]; 3] = core::array::from_fn(|_| core::array::from_fn(|_| ((r.next() >> 20) as i64) - (1 << 43)));
        let (ta, tb) = (&buf.a[4 * q..len], &buf.b[4 * q..len]);
        let plain = [
            [dot_plain(w0, a), dot_plain(w1, a), dot_plain(w0, b), dot_plain(w1, b)],
            [dot_plain(w0, b), dot_plain(w1, b), dot_plain(w0, b), dot_plain(w1, b)],
            [dot_plain(&wp[..m], ta), dot_plain(&wp[8..8 + m], ta), dot_plain(&wp[..m], tb), dot_plain(&wp[8..8 + m], tb)],
        ];
        let mut sums = start;
        // SAFETY: every entry's values lie inside `buf.pair` (`4 q` or `m` from its row, pixel b
        // `bstep` later), the groups entries read `4 q` words of `ww` from offset 0, the plain
        // entry `m` bytes of `wp` at 0 and at `kl = 8`, and every part index is below 3.
        unsafe { dsp::nat_block(&table, 0, &mut sums, 8, &wp, &ww[..]) };
        for (p, ((got, s), pl)) in sums.iter().zip(&start).zip(&plain).enumerate() {
            let want: [i64; 4] = core::array::from_fn(|i| s[i] + pl[i]);
            if *got != want {
                let what = ["dsp::nat_block two pixels", "dsp::nat_block one pixel", "dsp::nat_block plain entry"][p];
                println!("MUIR-KERNELS FAILED {what}: offsets {oa}/{ob}");
                fail(what, 4 * q, got, &want);
            }
        }
        cases += 1;
    }
    cases
}

/// `conv::conv_row_i16_nat` (the activations read in place from the input rows, the end pixels
/// one at a time, the runs' heads and tails by the plain products) against `conv_plain`: rows of
/// 8 to 26 pixels (its narrowest is 8), 1 to 4 rows (padding rows above and below), kernels 1
/// to 7, 1 to 3 parts of 1 to 24 channels (whole groups of four and not), even channel counts,
/// random and extreme values and weights; the path must take every case.
#[cfg(not(feature = "mve"))]
fn check_conv_nat(r: &mut Rng) -> usize {
    use muir::kernels::OutRow;
    use muir::kernels::conv::{BiasRef, ConvParams, MultRef, PartRows, conv_plain, conv_row_i16_nat};
    use muir::model::graph::PostOp;
    // SAFETY: called once, after `check_conv`: the only user of `CONV` now.
    let b = unsafe { &mut *core::ptr::addr_of_mut!(CONV) };
    let mut cases = 0;
    for case in 0..300u32 {
        let k = [1, 3, 3, 3, 5, 7][(r.next() % 6) as usize];
        let np = if k == 7 { 1 + (r.next() % 2) as usize } else { 1 + (r.next() % 3) as usize };
        let (h, w) = (1 + (r.next() % 4) as usize, 8 + (r.next() % 19) as usize);
        let mut parts = [0usize; 3];
        let most = (CONV_IN / (h * w)).min(24).min(CONV_KL / (k * k * np));
        for ch in parts.iter_mut().take(np) {
            *ch = match r.next() % 4 {
                0 => (4 * (1 + (r.next() % 6) as usize)).min(most / 4 * 4).max(1),
                1 => 1,
                _ => 1 + (r.next() as usize) % most.max(1),
            };
        }
        let cin: usize = parts.iter().sum();
        let kl = k * k * cin;
        let cout = 2 * (1 + (r.next() as usize) % (CONV_OUT / (h * w) / 2).clamp(1, 6));
        let extreme = case % 5 == 4;
        for v in b.weights.iter_mut().take(cout * kl) {
            *v = if extreme { if r.next() % 2 == 0 { i8::MIN } else { i8::MAX } } else { (r.next() >> 56) as i8 };
        }
        for e in b.mult.chunks_exact_mut(8).take(cout * np) {
            let m = if extreme { i32::MAX - (r.next() % 2) as i32 } else { (r.next() >> 33) as i32 + (1 << 29) };
            e[..4].copy_from_slice(&m.to_le_bytes());
            e[4] = if extreme { 8 + (r.next() % 6) as u8 } else { 20 + (r.next() % 20) as u8 };
            e[5..].fill(0);
        }
        for e in b.bias.chunks_exact_mut(8).take(cout) {
            e.copy_from_slice(&(((r.next() >> 40) as i64) - (1 << 23)).to_le_bytes());
        }
        let post = [PostOp::None, PostOp::Relu, PostOp::Sigmoid, PostOp::Tanh][(r.next() % 4) as usize];
        let p = ConvParams {
            k,
            stride: 1,
            parts: &parts[..np],
            cout,
            weights: &b.weights[..cout * kl],
            bias: BiasRef(&b.bias[..8 * cout]),
            mult: MultRef(&b.mult[..8 * cout * np]),
            post,
        };
        for (t, &ch) in b.x16.iter_mut().zip(&parts[..np]) {
            let f = if extreme { Fill::Max } else if r.next() % 8 == 0 { Fill::Min } else { Fill::Random };
            for v in t.iter_mut().take(h * w * ch) {
                *v = i16::sample(r, f);
            }
        }
        let n_out = h * w * cout;
        let ts: [&[i16]; 3] = [&b.x16[0][..h * w * parts[0]], &b.x16[1][..h * w * parts[1]], &b.x16[2][..h * w * parts[2]]];
        b.want[..n_out].fill(0);
        b.got[..n_out].fill(0);
        conv_plain(&p, &ts[..np], h, w, &mut OutRow::I16(&mut b.want[..n_out]));
        let mut used = true;
        for y in 0..h {
            let rows: [PartRows<'_, i16>; 3] = core::array::from_fn(|i| PartRows::of_tensor(ts[i], h, w * parts[i], y, k, 1));
            let row_len = w * cout;
            let mut dst = OutRow::I16(&mut b.got[y * row_len..(y + 1) * row_len]);
            used &= conv_row_i16_nat(&p, &rows[..np], w, &mut dst, &mut b.scratch);
        }
        if !used || b.want[..n_out] != b.got[..n_out] {
            let at = b.want[..n_out].iter().zip(&b.got[..n_out]).position(|(a, g)| a != g).unwrap_or(0);
            println!(
                "MUIR-KERNELS FAILED conv_row_i16_nat case {case}: k={k} parts={:?} cout={cout} {h}x{w} used={used} at {at}: got {}, plain {}",
                &parts[..np], b.got[at], b.want[at]
            );
            process::exit(1);
        }
        cases += 1;
    }
    cases
}

/// `mve::lookup_samples` (the post-pooled lookup's i32 samples of one level, four a vector)
/// against the scalar i32 formula of `corr::lookup_with`: random prefix sums (small, and any
/// i64, so that the numerator wraps), phases 0-255, strides 1-16, 1-13 samples, shifts 1-62
/// (also the zero multiplier), a sentinel after the samples; short prefixes, stride 0 and shifts
/// 0 and 63 refused with nothing written.
#[cfg(feature = "mve")]
fn check_lookup(r: &mut Rng) -> usize {
    use muir::arith::{Multiplier, requantize_i32, sat_i16};
    use muir::kernels::mve;
    let mut pre = [0i64; 16 * 14 + 2];
    let mut cases = 0;
    for case in 0..3000usize {
        let sl = [1usize, 2, 4, 8, 16, 3][case % 6];
        let k = 1 + (r.next() % 13) as usize;
        let a = match case % 7 {
            0 => 0,
            1 => 255,
            _ => (r.next() >> 56) as i32,
        };
        let shift = match case % 11 {
            0 => 1,
            1 => 62,
            2 => 32,
            3 => 33,
            _ => 1 + (r.next() % 62) as u8,
        };
        let m = match case % 13 {
            0 => 0,
            1 => i32::MAX,
            2 => 1 << 30,
            _ => ((1u64 << 30) + (r.next() >> 34)) as i32,
        };
        let mult = Multiplier { m, shift };
        let need = (k - 1) * sl + sl + 2;
        let kind = case % 5;
        for v in pre.iter_mut().take(need) {
            let x = r.next() as i64;
            *v = match kind {
                0 => x,
                1 => x >> 40,
                2 => x >> 20,
                3 => if x & 1 == 0 { i64::MAX } else { i64::MIN },
                _ => x >> 50,
            };
        }
        let mut out = [0x5a5ai16; 14];
        if !mve::lookup_samples(&pre[..need], sl, a, mult, &mut out[..k]) {
            println!("MUIR-KERNELS FAILED lookup_samples: refused sl={sl} k={k} shift={shift}");
            process::exit(1);
        }
        for t in 0..k {
            let (x0, x1, y0, y1) = (pre[t * sl] as i32, pre[t * sl + sl] as i32, pre[t * sl + 1] as i32, pre[t * sl + 1 + sl] as i32);
            let (b0, b1) = (x1.wrapping_sub(x0), y1.wrapping_sub(y0));
            let want = sat_i16(requantize_i32((256 - a).wrapping_mul(b0).wrapping_add(a.wrapping_mul(b1)), mult));
            if out[t] != want {
                println!("MUIR-KERNELS FAILED lookup_samples: case {case} sl={sl} k={k} a={a} m={m} shift={shift} t={t}: {} != {want}", out[t]);
                process::exit(1);
            }
        }
        if out[k] != 0x5a5a {
            println!("MUIR-KERNELS FAILED lookup_samples: case {case} wrote past {k} samples");
            process::exit(1);
        }
        cases += 1;
        if case % 50 == 0 {
            let mut o = [0x5a5ai16; 14];
            let bad = [
                mve::lookup_samples(&pre[..need - 1], sl, a, mult, &mut o[..k]),
                mve::lookup_samples(&pre[..need], 0, a, mult, &mut o[..k]),
                mve::lookup_samples(&pre[..need], sl, a, Multiplier { m, shift: 0 }, &mut o[..k]),
                mve::lookup_samples(&pre[..need], sl, a, Multiplier { m, shift: 63 }, &mut o[..k]),
            ];
            if bad.iter().any(|&b| b) || o.iter().any(|&v| v != 0x5a5a) {
                println!("MUIR-KERNELS FAILED lookup_samples: case {case}: invalid arguments accepted");
                process::exit(1);
            }
            cases += 4;
        }
    }
    cases
}

/// `corr::window` (Helium: `mve::corr_window` over the in-row columns, zeros around them)
/// against the plain correlations: feature lengths 1-40 and around the 16-lane vectors and 256,
/// random and extreme i8 features, windows starting left of, inside and right of the row, a row
/// one column short of its width (the plain path then), a sentinel after the window; and
/// `corr_window` refusing an empty feature vector and a short row.
#[cfg(feature = "mve")]
fn check_corr_window(f1: &mut [i8; MAX_N], f2: &mut [i8; MAX_N], r: &mut Rng) -> usize {
    use muir::kernels::{corr, mve};
    let mut cases = 0;
    let cs = (1..=40usize).chain([47, 48, 49, 63, 64, 65, 128, 255, 256, 257]);
    for (ci, c) in cs.enumerate() {
        for rep in 0..6usize {
            let w = 1 + (r.next() % (MAX_N as u64 / c as u64).min(40)) as usize;
            let fill = (ci + rep) % 4;
            for v in f1.iter_mut().take(c) {
                *v = match fill {
                    1 => i8::MIN,
                    2 => i8::MAX,
                    _ => (r.next() >> 56) as i8,
                };
            }
            for v in f2.iter_mut().take(w * c) {
                *v = match fill {
                    1 | 2 => i8::MIN,
                    _ => (r.next() >> 56) as i8,
                };
            }
            let n = 1 + (r.next() % 24) as usize;
            let lo = (r.next() % (w as u64 + n as u64 + 4)) as i64 - n as i64 - 2;
            // The row one column short of `w` in every sixth case (its last column then reads 0).
            let len = if rep == 5 { (w - 1) * c } else { w * c };
            let mut win = [0x5a5a_5a5ai32; 25];
            corr::window(&f1[..c], &f2[..len], w, lo, &mut win[..n]);
            for (i, &got) in win[..n].iter().enumerate() {
                let col = lo + i as i64;
                let want = if col < 0 || col as usize >= w || (col as usize + 1) * c > len {
                    0
                } else {
                    let f = &f2[col as usize * c..(col as usize + 1) * c];
                    f1[..c].iter().zip(f).map(|(a, b)| *a as i32 * *b as i32).sum::<i32>()
                };
                if got != want {
                    println!("MUIR-KERNELS FAILED corr_window: c={c} w={w} lo={lo} n={n} column {i}: {got} != {want}");
                    process::exit(1);
                }
            }
            if win[n] != 0x5a5a_5a5a {
                println!("MUIR-KERNELS FAILED corr_window: c={c} wrote past {n} columns");
                process::exit(1);
            }
            cases += 1;
        }
    }
    let mut win = [7i32; 4];
    if mve::corr_window(&f1[..0], &f2[..64], &mut win) || mve::corr_window(&f1[..16], &f2[..63], &mut win) || win != [7; 4] {
        println!("MUIR-KERNELS FAILED corr_window: invalid arguments accepted");
        process::exit(1);
    }
    cases + 2
}

/// `mve::blend_q15` and `mve::mul_q15` (the GRU blend and gate products) against the plain
/// i64 formulas of `eltwise`: lengths 0-40 and around the vectors, random, extreme (both signs,
/// so that the blend saturates) and small values, operands of unequal lengths (the shortest
/// counts), a sentinel after the written values.
#[cfg(feature = "mve")]
fn check_q15(x: &mut [i16; MAX_N], y: &mut [i16; MAX_N], r: &mut Rng) -> usize {
    use muir::arith::{rshift_round, sat_i16};
    use muir::kernels::mve;
    let mut cases = 0;
    let ns = (0..=40usize).chain([63, 64, 65, 127, 128, 129, 1000]);
    for (ni, n) in ns.enumerate() {
        for kind in 0..5usize {
            let pick = |r: &mut Rng, k: usize| -> i16 {
                let v = (r.next() >> 48) as i16;
                match k {
                    1 => if v & 1 == 0 { i16::MIN } else { i16::MAX },
                    2 => v >> 12,
                    3 => if v & 1 == 0 { i16::MIN } else { v },
                    _ => v,
                }
            };
            for v in x.iter_mut().take(n + 1) {
                *v = pick(r, kind);
            }
            for v in y.iter_mut().take(2 * n + 2) {
                *v = pick(r, (kind + ni) % 5);
            }
            let (z, q) = y.split_at(n + 1);
            // The blend: `h` one longer than `z` in odd cases (the last `h` then stays).
            let extra = (ni + kind) % 2;
            let mut h = [0i16; 1001];
            h[..n + 1].copy_from_slice(&x[..n + 1]);
            mve::blend_q15(&mut h[..n + extra], &z[..n], &q[..n]);
            for i in 0..=n {
                let want = if i < n {
                    let d = q[i] as i64 - x[i] as i64;
                    sat_i16(x[i] as i64 + rshift_round(z[i] as i64 * d, 15))
                } else {
                    x[i]
                };
                if h[i] != want {
                    println!("MUIR-KERNELS FAILED blend_q15: n={n} kind={kind} i={i}: {} != {want}", h[i]);
                    process::exit(1);
                }
            }
            let mut o = [0x5a5ai16; 1001];
            mve::mul_q15(&x[..n + extra], &z[..n], &mut o[..n + 1 - extra]);
            let m = n.min(n + 1 - extra);
            for i in 0..=n {
                let want = if i < m { sat_i16(rshift_round(x[i] as i64 * z[i] as i64, 15)) } else { 0x5a5a };
                if o[i] != want {
                    println!("MUIR-KERNELS FAILED mul_q15: n={n} kind={kind} i={i}: {} != {want}", o[i]);
                    process::exit(1);
                }
            }
            let mut o = [0x5a5ai16; 1001];
            let k = z[0];
            mve::mul_q15_by(&x[..n + extra], k, &mut o[..n + 1 - extra]);
            for i in 0..=n {
                let want = if i < m { sat_i16(rshift_round(x[i] as i64 * k as i64, 15)) } else { 0x5a5a };
                if o[i] != want {
                    println!("MUIR-KERNELS FAILED mul_q15_by: n={n} kind={kind} i={i}: {} != {want}", o[i]);
                    process::exit(1);
                }
            }
            cases += 3;
        }
    }
    cases
}

/// `mve::residual_relu` (four type pairs) against the i64 reference of `eltwise::residual_relu`:
/// `O::from_i64_sat((y + shift_round(x, shift)).max(0))`; lengths around the vector width,
/// shifts from -255 to 24 (the dispatch's range; beyond, the i64 reference itself can overflow), random and extreme values, a sentinel after the last output.
#[cfg(feature = "mve")]
fn check_residual(r: &mut Rng) -> usize {
    use muir::arith::shift_round;
    use muir::kernels::mve;
    let mut cases = 0;
    let ns = (0..=40usize).chain([63, 64, 65, 127, 128, 129, 1000]);
    let shifts = [-255i32, -100, -40, -33, -32, -31, -17, -16, -15, -8, -3, -2, -1, 0, 1, 2, 3, 7, 8, 15, 16, 17, 23, 24];
    let mut y = [0i16; 1001];
    let mut x16 = [0i16; 1001];
    let mut x8 = [0u8; 1001];
    for (ni, n) in ns.enumerate() {
        for (si, &shift) in shifts.iter().enumerate() {
            let kind = (ni + si) % 4;
            for i in 0..=n {
                let v = r.next();
                let (a, b) = ((v >> 48) as i16, (v >> 32) as i16);
                (y[i], x16[i]) = match kind {
                    1 => (if a & 1 == 0 { i16::MIN } else { i16::MAX }, if b & 1 == 0 { i16::MIN } else { i16::MAX }),
                    2 => (a >> 6, b >> 9),
                    3 => (if a & 1 == 0 { i16::MIN } else { a }, b & 0x7fff),
                    _ => (a, b),
                };
                x8[i] = if kind == 1 { if v & 4 == 0 { 0 } else { 255 } } else { v as u8 };
            }
            let extra = (ni + si) % 2;
            let m = n.min(n + 1 - extra);
            let want = |i: usize, x: i64, lim: i64| (y[i] as i64 + shift_round(x, shift)).max(0).min(lim);
            let mut o8 = [0x5au8; 1001];
            let mut o16 = [0x5a5ai16; 1001];
            mve::residual_relu_u8_u8(&y[..n + extra], &x8[..n], shift, &mut o8[..n + 1 - extra]);
            for i in 0..=n {
                let w = if i < m { want(i, x8[i] as i64, 255) } else { 0x5a };
                if o8[i] as i64 != w {
                    println!("MUIR-KERNELS FAILED residual_relu_u8_u8: n={n} shift={shift} kind={kind} i={i}: {} != {w}", o8[i]);
                    process::exit(1);
                }
            }
            mve::residual_relu_i16_u8(&y[..n + extra], &x16[..n], shift, &mut o8[..n + 1 - extra]);
            for i in 0..=n {
                let w = if i < m { want(i, x16[i] as i64, 255) } else { 0x5a };
                if o8[i] as i64 != w {
                    println!("MUIR-KERNELS FAILED residual_relu_i16_u8: n={n} shift={shift} kind={kind} i={i}: {} != {w}", o8[i]);
                    process::exit(1);
                }
            }
            mve::residual_relu_u8_i16(&y[..n + extra], &x8[..n], shift, &mut o16[..n + 1 - extra]);
            for i in 0..=n {
                let w = if i < m { want(i, x8[i] as i64, 32767) } else { 0x5a5a };
                if o16[i] as i64 != w {
                    println!("MUIR-KERNELS FAILED residual_relu_u8_i16: n={n} shift={shift} kind={kind} i={i}: {} != {w}", o16[i]);
                    process::exit(1);
                }
            }
            mve::residual_relu_i16_i16(&y[..n + extra], &x16[..n], shift, &mut o16[..n + 1 - extra]);
            for i in 0..=n {
                let w = if i < m { want(i, x16[i] as i64, 32767) } else { 0x5a5a };
                if o16[i] as i64 != w {
                    println!("MUIR-KERNELS FAILED residual_relu_i16_i16: n={n} shift={shift} kind={kind} i={i}: {} != {w}", o16[i]);
                    process::exit(1);
                }
            }
            cases += 4;
        }
    }
    cases
}

/// `mve::zero` (the patches' padding columns) and `mve::fill_ones` (the path steps' windows) on u8
/// and i16 slices of 0 to 40 and 63-65, 127-129
/// values at every start offset 0-3 in a buffer of random bytes: every value of the slice 0, the
/// values before and after it untouched.
#[cfg(feature = "mve")]
fn check_zero(r: &mut Rng) -> usize {
    let mut cases = 0;
    let mut b8 = [0u8; 140];
    let mut b16 = [0i16; 140];
    for n in (0..=40usize).chain([63, 64, 65, 127, 128, 129]) {
        for at in 0..4usize {
            for (x, y) in b8.iter_mut().zip(b16.iter_mut()) {
                (*x, *y) = ((r.next() >> 56) as u8 | 1, (r.next() >> 48) as i16 | 1);
            }
            let (k8, k16) = (b8, b16);
            muir::kernels::mve::zero(&mut b8[at..at + n]);
            muir::kernels::mve::zero(&mut b16[at..at + n]);
            // `fill_ones` over the same span of a copy: u16::MAX inside, the rest untouched.
            let mut ones = k16.map(|v| core::mem::MaybeUninit::new(v as u16));
            muir::kernels::mve::fill_ones(&mut ones[at..at + n]);
            for (i, v) in ones.iter().enumerate() {
                // SAFETY: every value was initialised (`MaybeUninit::new`, then `fill_ones`).
                let v = unsafe { v.assume_init() };
                if v != if (at..at + n).contains(&i) { u16::MAX } else { k16[i] as u16 } {
                    fail("mve fill_ones", n * 10 + at, &[i as i64, v as i64], &[]);
                }
            }
            for i in 0..140 {
                let inside = (at..at + n).contains(&i);
                if b8[i] != if inside { 0 } else { k8[i] } || b16[i] != if inside { 0 } else { k16[i] } {
                    fail("mve zero", n * 10 + at, &[i as i64, b8[i] as i64, b16[i] as i64], &[]);
                }
            }
            cases += 1;
        }
    }
    cases
}

/// `mve::max_abs_i32` against the scalar maximum of `unsigned_abs`: lengths around the vector
/// width, random, small, `i32::MIN`/`MAX` values, the largest value at each position, a
/// sentinel `i32::MIN` after the last element (which must not be read).
#[cfg(feature = "mve")]
fn check_max_abs(r: &mut Rng) -> usize {
    use muir::kernels::mve;
    let mut cases = 0;
    let mut v = [0i32; 1001];
    for n in (0..=40usize).chain([63, 64, 65, 127, 128, 129, 1000]) {
        for kind in 0..5usize {
            for x in v.iter_mut().take(n) {
                let t = r.next();
                *x = match kind {
                    0 => t as i32,
                    1 => if t & 1 == 0 { i32::MIN } else { i32::MAX },
                    2 => (t as i32) >> 20,
                    3 => ((t as i32) >> 24).min(0),
                    _ => 0,
                };
            }
            if kind == 4 && n > 0 {
                let at = (r.next() % n as u64) as usize;
                v[at] = if n % 2 == 0 { -(1 << 21) } else { (1 << 21) - 1 };
            }
            v[n] = i32::MIN;
            let want = v[..n].iter().map(|x| x.unsigned_abs()).max().unwrap_or(0);
            let got = mve::max_abs_i32(&v[..n]);
            if got != want {
                println!("MUIR-KERNELS FAILED max_abs_i32: n={n} kind={kind}: {got} != {want}");
                process::exit(1);
            }
            cases += 1;
        }
    }
    cases
}

/// The one-part u8 pair of every channel in one call (`mve::dots_flipped`: activations flipped in
/// place to `x - 128`, `VMLADAVA.S8` in groups of three channels, the last group overlapping
/// when `cout` is not a multiple of 3, `128 sum(w)` added) with the weight sums of `mve::sum_i8`,
/// against the plain dot products: `cout` 3..=72 (every value in turn), patch lengths 1..=40,
/// 15..=17, 63..=65 and random up to the weight buffer, random fills, all-extreme fills of every
/// sign pair (weights -128 or 127, activations 0 or 255), one extreme channel and patch; the
/// pair must come back flipped (every byte `^ 0x80`, none past `2 kl`), the table untouched
/// outside the channels written (sentinels). Refused with nothing flipped or written: `cout` 0,
/// 1, 2, 73, `kl` 0 and `2^16`, short weights, pair or sums. `sum_i8` also against the plain sum
/// at lengths 0..=40, 63..=65, 1000, 18432.
#[cfg(feature = "mve")]
fn check_dots_flipped(pair: &mut [u8; 2 * MAX_N], r: &mut Rng) -> usize {
    use muir::kernels::mve::{FLIP_MAX, dots_flipped, sum_i8};
    use muir::model::graph::MAX_PARTS;
    // SAFETY: the only user of `W12` at this time, in the single thread of this program.
    let w12 = unsafe { &mut *core::ptr::addr_of_mut!(W12) };
    // SAFETY: the only user of `ORIG8`.
    let orig = unsafe { &mut *core::ptr::addr_of_mut!(ORIG8) };
    let mut cases = 0;
    const SENTINEL: i32 = 0x5a5a_1234;
    for n in (0..=40usize).chain([63, 64, 65, 1000, 12 * W12_KL]) {
        for v in &mut w12[..n] {
            *v = i8::sample(r, if n % 3 == 0 { Fill::Random } else if n % 3 == 1 { Fill::Min } else { Fill::Max });
        }
        let want: i32 = w12[..n].iter().map(|&w| w as i32).sum();
        if sum_i8(&w12[..n]) != want {
            fail("sum_i8", n, &[sum_i8(&w12[..n]) as i64], &[want as i64]);
        }
        cases += 1;
    }
    for case in 0..420u32 {
        let cout = 3 + (case as usize % (FLIP_MAX - 2));
        let most = (12 * W12_KL / cout).min(MAX_N);
        let kl = match r.next() % 5 {
            0 => 1 + (r.next() % 40) as usize,
            1 => 15 + (r.next() % 3) as usize,
            2 => 63 + (r.next() % 3) as usize,
            _ => 1 + (r.next() % most as u64) as usize,
        }
        .min(most);
        let mode = (case / 70) % 4; // 0, 1 random; 2 all extreme; 3 one extreme channel and patch
        let (hc, hb) = ((r.next() % cout as u64) as usize, r.next() % 2 == 0);
        let (wf, xf) = match r.next() % 4 {
            0 => (Fill::Min, Fill::Max),
            1 => (Fill::Max, Fill::Max),
            2 => (Fill::Min, Fill::Min),
            _ => (Fill::Max, Fill::Min),
        };
        let ext = |one: bool, f: Fill| if mode == 2 || (mode == 3 && one) { f } else { Fill::Random };
        for c in 0..cout {
            let f = ext(c == hc, wf);
            for v in &mut w12[c * kl..(c + 1) * kl] {
                *v = i8::sample(r, f);
            }
        }
        for (i, v) in pair[..2 * kl].iter_mut().enumerate() {
            *v = u8::sample(r, ext((i >= kl) == hb, xf));
        }
        pair[2 * kl] = 0x3c;
        orig[..2 * kl + 1].copy_from_slice(&pair[..2 * kl + 1]);
        let mut ws = [0i32; FLIP_MAX];
        for (s, w) in ws.iter_mut().zip(w12.chunks_exact(kl)).take(cout) {
            *s = sum_i8(w).wrapping_mul(128);
        }
        let mut d = [SENTINEL; 24 * MAX_PARTS];
        if !dots_flipped(&ws[..cout], &w12[..cout * kl], kl, cout, &mut pair[..], &mut d) {
            println!("MUIR-KERNELS FAILED dots_flipped case {case}: refused cout={cout} kl={kl}");
            process::exit(1);
        }
        if pair[..2 * kl].iter().zip(orig.iter()).any(|(p, o)| *p != *o ^ 0x80) || pair[2 * kl] != 0x3c {
            println!("MUIR-KERNELS FAILED dots_flipped case {case}: the pair is not flipped exactly (cout={cout} kl={kl})");
            process::exit(1);
        }
        let (a, b) = (&orig[..kl], &orig[kl..2 * kl]);
        for (c, w) in w12.chunks_exact(kl).take(cout).enumerate() {
            for (x, at) in [(a, c), (b, FLIP_MAX + c)] {
                let want = dot_plain(w, x);
                if d[at] as i64 != want {
                    println!("MUIR-KERNELS FAILED dots_flipped case {case}: cout={cout} kl={kl} channel {c} at {at}");
                    fail("dots_flipped", kl, &[d[at] as i64], &[want]);
                }
            }
        }
        if d[cout..FLIP_MAX].iter().chain(&d[FLIP_MAX + cout..]).any(|&v| v != SENTINEL) {
            println!("MUIR-KERNELS FAILED dots_flipped case {case}: written past channel {cout} (kl={kl})");
            process::exit(1);
        }
        cases += 1;
    }
    // Refused, with nothing flipped or written.
    let ws = [0i32; FLIP_MAX + 1];
    for v in pair.iter_mut().take(64) {
        *v = 7;
    }
    let mut d = [SENTINEL; 24 * MAX_PARTS];
    let refused = [
        dots_flipped(&ws, &w12[..], 8, 0, &mut pair[..], &mut d),
        dots_flipped(&ws, &w12[..], 8, 1, &mut pair[..], &mut d),
        dots_flipped(&ws, &w12[..], 8, 2, &mut pair[..], &mut d),
        dots_flipped(&ws, &w12[..], 8, FLIP_MAX + 1, &mut pair[..], &mut d),
        dots_flipped(&ws, &w12[..], 0, 4, &mut pair[..], &mut d),
        dots_flipped(&ws, &w12[..], 1 << 16, 4, &mut pair[..], &mut d),
        dots_flipped(&ws, &w12[..31], 8, 4, &mut pair[..], &mut d),
        dots_flipped(&ws, &w12[..32], 8, 4, &mut pair[..15], &mut d),
        dots_flipped(&ws[..3], &w12[..32], 8, 4, &mut pair[..], &mut d),
    ];
    if refused.iter().any(|&x| x) || pair[..64].iter().any(|&v| v != 7) || d.iter().any(|&v| v != SENTINEL) {
        println!("MUIR-KERNELS FAILED dots_flipped: a bad shape accepted ({refused:?}) or something written");
        process::exit(1);
    }
    cases + refused.len()
}

/// One case of `check_requant_pair` for output type `O`: the pair kernel against two calls of the
/// one-pixel kernel (same outputs, `FPSCR.QC` set exactly when one of them saturates) and, where
/// nothing saturated, the portable formula `want`; the outputs at 1 and 9 of a sentinel-filled
/// row (nothing else written).
#[cfg(feature = "mve")]
#[allow(clippy::too_many_arguments)]
fn requant_pair_case<O: muir::kernels::mve::Narrow + Default + PartialEq + Into<i64>>(
    sentinel: O,
    case: u32,
    d: &[i32; 288],
    wide: bool,
    t: &Tables,
    k: &muir::kernels::mve::Requant4,
    np: usize,
    table: Option<&[i16; 1025]>,
    want: &[[i64; 4]; 2],
) -> bool {
    use muir::kernels::mve;
    let (off_b, stride) = if wide { (12, 24) } else { (4, 8) };
    let mut one = [[sentinel; 4]; 2];
    let mut qc_one = false;
    for (i, o) in one.iter_mut().enumerate() {
        let dp = d.as_ptr().wrapping_add(i * off_b);
        // SAFETY: `d` holds `stride (np - 1) + off_b + 4 <= 288` values, the tables 4 channels of
        // `np` parts, `o` four.
        unsafe {
            match (table, wide) {
                (None, false) => mve::requant4(dp, t.mult.as_ptr(), k, np, t.bias.as_ptr(), o.as_mut_ptr()),
                (None, true) => mve::requant4_wide(dp, t.mult.as_ptr(), k, np, t.bias.as_ptr(), o.as_mut_ptr()),
                (Some(tb), false) => mve::requant4_lut(dp, t.mult.as_ptr(), k, np, t.bias.as_ptr(), tb, o.as_mut_ptr()),
                (Some(tb), true) => mve::requant4_lut_wide(dp, t.mult.as_ptr(), k, np, t.bias.as_ptr(), tb, o.as_mut_ptr()),
            }
        }
        qc_one |= mve::take_qc();
    }
    let mut row = [sentinel; 16];
    let o = row.as_mut_ptr();
    let _ = stride;
    // SAFETY: as above for both pixels; outputs at 1..5 and 9..13 of the 16-value row.
    unsafe { mve::requant4_pair([d.as_ptr(), d.as_ptr().wrapping_add(off_b)], t.mult.as_ptr(), k, np, t.bias.as_ptr(), table, wide, [o.wrapping_add(1), o.wrapping_add(9)]) };
    let qc = mve::take_qc();
    let got = [[row[1], row[2], row[3], row[4]], [row[9], row[10], row[11], row[12]]];
    if qc != qc_one || got != one || [0, 5, 6, 7, 8, 13, 14, 15].iter().any(|&i| row[i] != sentinel) {
        println!("MUIR-KERNELS FAILED requant4_pair case {case}: np={np} wide={wide} table={}: QC {qc} vs {qc_one}, or outputs differ from one-pixel calls, or written outside", table.is_some());
        process::exit(1);
    }
    // One part: the portable values even where a lane saturated (`conv_helium`'s `qc`).
    if !qc || np == 1 {
        for (g, w) in got.iter().zip(want) {
            let g = g.map(Into::into);
            if g != *w {
                fail("requant4_pair", case as usize, &g, w);
            }
        }
    }
    !qc
}

/// `mve::requant4_pair` (two pixels' epilogues, each part's multipliers gathered once, with and
/// without a sigmoid or tanh table, parts 32 or 96 bytes apart) against two one-pixel calls and
/// the portable formula, as `check_requant`: 1-6 parts, extreme multipliers and sums (saturating
/// cases), random and small operands, every output type.
#[cfg(feature = "mve")]
fn check_requant_pair(r: &mut Rng) -> usize {
    use muir::arith::{Multiplier, requantize_i32, rshift_round};
    use muir::arith::lut;
    use muir::kernels::mve::Requant4;
    let mut t = Tables { mult: [0; 8 * 4 * 6], bias: [0; 32] };
    let (mut exact, mut cases) = (0usize, 0usize);
    let _ = muir::kernels::mve::take_qc();
    for case in 0..3000u32 {
        let np = 1 + (case % 6) as usize;
        let kind = (case / 6) % 5;
        let wide = (case / 30) % 2 == 1;
        let (off_b, stride) = if wide { (12, 24) } else { (4, 8) };
        let mut d = [0i32; 288];
        let mut ms = [Multiplier { m: 0, shift: 8 }; 24];
        for ch in 0..4 {
            for p in 0..np {
                let shift = 8 + (r.next() % 55) as u8;
                let m = match kind {
                    0 => i32::MIN,
                    1 => i32::MAX,
                    3 => ((r.next() >> 32) as i32) >> 12,
                    _ => (r.next() >> 32) as i32,
                };
                ms[ch * np + p] = Multiplier { m, shift };
                let e = &mut t.mult[8 * (ch * np + p)..8 * (ch * np + p + 1)];
                e[..4].copy_from_slice(&m.to_le_bytes());
                e[4] = shift;
                e[5..].fill(0);
                for px in 0..2 {
                    d[stride * p + px * off_b + ch] = match kind {
                        0 | 1 => if r.next() % 2 == 0 { i32::MIN } else { i32::MAX },
                        2 => ((r.next() >> 32) as i32) >> 12,
                        3 => (r.next() % 2001) as i32 - 1000,
                        _ => (r.next() >> 32) as i32,
                    };
                }
            }
            let b = ((r.next() >> 33) as i64) - (1 << 30) + 1;
            let b = if kind == 3 { b >> 12 } else { b };
            t.bias[8 * ch..8 * ch + 8].copy_from_slice(&b.to_le_bytes());
        }
        let lut_case = case % 3 == 2;
        let (lo, hi) = if lut_case { (-32768, 32767) } else { [(0, 255), (-128, 127), (-32768, 32767), (0, 32767)][(case % 4) as usize] };
        let (f, table): (fn(i16) -> i16, _) = if case % 2 == 0 { (lut::sigmoid_q12, lut::sigmoid_table()) } else { (lut::tanh_q12, lut::tanh_table()) };
        let (olo, ohi) = if lut_case { [(0i64, 255i64), (-128, 127), (-32768, 32767)][(case / 3 % 3) as usize] } else { (lo as i64, hi as i64) };
        let mut want = [[0i64; 4]; 2];
        for (px, w) in want.iter_mut().enumerate() {
            for (ch, w) in w.iter_mut().enumerate() {
                let s: i64 = (0..np).map(|p| requantize_i32(d[stride * p + px * off_b + ch], ms[ch * np + p])).sum();
                let b = i64::from_le_bytes(t.bias[8 * ch..8 * ch + 8].try_into().unwrap_or_default());
                let v = rshift_round(s + b, 8).clamp(lo as i64, hi as i64);
                *w = if lut_case { (f(v as i16) as i64).clamp(olo, ohi) } else { v };
            }
        }
        let k = Requant4::new(np, lo, hi).with_out(olo as i32, ohi as i32);
        let table = lut_case.then_some(table);
        let ok = match (olo, ohi) {
            (-128, _) => requant_pair_case::<i8>(0x55, case, &d, wide, &t, &k, np, table, &want),
            (0, 255) => requant_pair_case::<u8>(0x55, case, &d, wide, &t, &k, np, table, &want),
            _ => requant_pair_case::<i16>(0x5555, case, &d, wide, &t, &k, np, table, &want),
        };
        if kind == 3 && !ok {
            println!("MUIR-KERNELS FAILED requant4_pair case {case}: saturation reported for small operands");
            process::exit(1);
        }
        exact += usize::from(ok);
        cases += 1;
    }
    if exact < 500 || cases - exact < 100 {
        println!("MUIR-KERNELS FAILED requant4_pair: {exact} exact of {cases} cases (saturated ones must occur too)");
        process::exit(1);
    }
    cases
}

/// `mve::logits32` (the MGA logits of a 32-value query against a block of keys, less the maximum,
/// the query kept in registers) against the plain i64 dot products: blocks of 1..=130 keys, a key
/// block with a partial key at its end, `e` shorter than the block, random, extreme
/// (`i16::MIN`/`MAX`) and small values, the maximum the block's largest logit (every difference
/// fits) or far off (`None` must come back exactly when some difference leaves i32); a sentinel
/// after the last key's value; queries of 31 or 33 values and empty blocks refused.
#[cfg(feature = "mve")]
fn check_logits32(keys: &mut [i16; MAX_N], r: &mut Rng) -> usize {
    use muir::kernels::mve::logits32;
    let mut cases = 0;
    let mut q = [0i16; 33];
    let mut e = [0i32; 131];
    for case in 0..400u32 {
        let nk = 1 + (case as usize % 130);
        let kind = (case / 130) % 4;
        let sample = |r: &mut Rng| -> i16 {
            match kind {
                0 => (r.next() >> 48) as i16,
                1 => if r.next() % 2 == 0 { i16::MIN } else { i16::MAX },
                2 => ((r.next() >> 48) as i16) >> 8,
                _ => if r.next() % 3 == 0 { i16::MIN } else { (r.next() >> 48) as i16 },
            }
        };
        for v in q.iter_mut() {
            *v = sample(r);
        }
        let extra = (r.next() % 3) as usize * 7; // a partial key after the last whole one
        for v in keys[..32 * nk + extra].iter_mut() {
            *v = sample(r);
        }
        let ne = if case % 5 == 0 { (nk / 2).max(1) } else { nk };
        let plain: [i64; 130] = core::array::from_fn(|j| if j < nk { keys[32 * j..32 * j + 32].iter().zip(&q[..32]).map(|(a, b)| *a as i64 * *b as i64).sum() } else { 0 });
        let top = plain[..nk].iter().copied().max().unwrap_or(0);
        let max = match case % 4 {
            0 | 1 => top,
            2 => top + (r.next() % (1 << 33)) as i64,
            _ => top - (1 << 31) + (r.next() % 4) as i64,
        };
        e.fill(0x5a5a_5a5a);
        let got = logits32(&q[..32], &keys[..32 * nk + extra], max, &mut e[..ne]);
        let n = nk.min(ne);
        let fits = plain[..n].iter().all(|&l| i32::try_from(l - max).is_ok());
        if got != fits.then_some(n) {
            println!("MUIR-KERNELS FAILED logits32 case {case}: {got:?}, want {:?} (keys {nk}, e {ne})", fits.then_some(n));
            process::exit(1);
        }
        if fits {
            for j in 0..n {
                if e[j] as i64 != plain[j] - max {
                    fail("logits32", j, &[e[j] as i64], &[plain[j] - max]);
                }
            }
        }
        if e[n..].iter().any(|&v| v != 0x5a5a_5a5a) {
            println!("MUIR-KERNELS FAILED logits32 case {case}: written past key {n}");
            process::exit(1);
        }
        cases += 1;
    }
    let refused = [logits32(&q[..31], &keys[..64], 0, &mut e), logits32(&q[..33], &keys[..64], 0, &mut e), logits32(&q[..32], &keys[..31], 0, &mut e), logits32(&q[..32], &keys[..64], 0, &mut e[..0])];
    if refused.iter().any(Option::is_some) {
        println!("MUIR-KERNELS FAILED logits32: a bad shape accepted");
        process::exit(1);
    }
    cases + refused.len()
}

/// Multiplier and bias tables of up to 32 groups of four channels of 6 parts (`check_requant_groups`).
#[cfg(feature = "mve")]
#[repr(C, align(8))]
struct BigTables {
    mult: [u8; 32 * 6 * 32],
    bias: [u8; 32 * 32],
}

#[cfg(feature = "mve")]
static mut BIG: BigTables = BigTables { mult: [0; 32 * 6 * 32], bias: [0; 32 * 32] };

/// One case of `check_requant_groups` for output type `O`: `requant4_groups` against a loop of
/// `requant4_pair` calls (same outputs, saturation bit `g` exactly when group `g`'s call set
/// `FPSCR.QC`), outputs in a sentinel-filled row (pixel `a`'s groups at 1, `b`'s after a gap).
#[cfg(feature = "mve")]
#[allow(clippy::too_many_arguments)]
fn requant_groups_case<O: muir::kernels::mve::Narrow + Default + PartialEq + Copy + Into<i64>>(
    sentinel: O,
    case: u32,
    d: &[i32; 512],
    wide: bool,
    t: &BigTables,
    k: &muir::kernels::mve::Requant4,
    np: usize,
    table: Option<&[i16; 1025]>,
    groups: usize,
) -> u32 {
    use muir::kernels::mve;
    let off_b = 4 * groups;
    let mut one = [sentinel; 2 * 4 * 32 + 8];
    let mut mask_one = 0u32;
    let bo = 4 * groups + 3; // pixel b's outputs
    for g in 0..groups {
        let o = one.as_mut_ptr();
        // SAFETY: group `g` reads `d[4 g + {0, off_b}] + stride (np - 1) + 4 <= 512` values,
        // `32 np` multiplier and 32 bias bytes at `32 np g` and `32 g` (inside the tables), and
        // writes four values at `1 + 4 g` and `bo + 4 g` of the row (inside it, apart).
        unsafe {
            mve::requant4_pair(
                [d.as_ptr().wrapping_add(4 * g), d.as_ptr().wrapping_add(off_b + 4 * g)],
                t.mult.as_ptr().wrapping_add(32 * np * g),
                k,
                np,
                t.bias.as_ptr().wrapping_add(32 * g),
                table,
                wide,
                [o.wrapping_add(1 + 4 * g), o.wrapping_add(bo + 4 * g)],
            )
        };
        mask_one |= u32::from(mve::take_qc()) << g;
    }
    let mut row = [sentinel; 2 * 4 * 32 + 8];
    let o = row.as_mut_ptr();
    // SAFETY: as above for every group; `1 <= groups <= 32`; the two pixels' outputs apart.
    let mask = unsafe { mve::requant4_groups([d.as_ptr(), d.as_ptr().wrapping_add(off_b)], t.mult.as_ptr(), k, np, t.bias.as_ptr(), table, wide, [o.wrapping_add(1), o.wrapping_add(bo)], groups) };
    // One part without a table: no saturation test (mask 0, `FPSCR.QC` may be left set).
    let one_part = np == 1 && table.is_none();
    let qc_left = mve::take_qc() && !one_part;
    let mask_one = if one_part { 0 } else { mask_one };
    if qc_left || mask != mask_one || row != one {
        let at = row.iter().zip(&one).position(|(a, b)| a != b);
        println!("MUIR-KERNELS FAILED requant4_groups case {case}: np={np} wide={wide} table={} groups={groups}: mask {mask:#x} vs {mask_one:#x}, first differing output {at:?}", table.is_some());
        process::exit(1);
    }
    mask
}

/// `mve::requant4_groups` (the epilogues of 1..=32 groups of four channels of two pixels in one
/// call, each group's saturation reported) against group-by-group `mve::requant4_pair` calls:
/// 1-6 parts, parts 32 or 96 bytes apart, with and without a sigmoid or tanh table, every output
/// type, random, extreme (saturating) and small operands; a sentinel-filled output row (nothing
/// written between or after the two pixels' outputs). Saturated and unsaturated groups must both
/// occur.
#[cfg(feature = "mve")]
fn check_requant_groups(r: &mut Rng) -> usize {
    use muir::arith::lut;
    use muir::kernels::mve::Requant4;
    // SAFETY: the only user of `BIG`.
    let t = unsafe { &mut *core::ptr::addr_of_mut!(BIG) };
    let (mut cases, mut sat, mut clean) = (0usize, 0u32, 0u32);
    let _ = muir::kernels::mve::take_qc();
    for case in 0..600u32 {
        let np = 1 + (case % 6) as usize;
        let kind = (case / 6) % 5;
        let wide = (case / 30) % 2 == 1;
        let groups = match case % 7 {
            0 => 32,
            1 => 3,
            _ => 1 + (r.next() % 18) as usize,
        };
        let mut d = [0i32; 512];
        for v in d.iter_mut() {
            *v = match kind {
                0 | 1 => if r.next() % 2 == 0 { i32::MIN } else { i32::MAX },
                2 => ((r.next() >> 32) as i32) >> 12,
                3 => (r.next() % 2001) as i32 - 1000,
                _ => if r.next() % 8 == 0 { (r.next() >> 32) as i32 } else { ((r.next() >> 32) as i32) >> 14 },
            };
        }
        for e in t.mult[..32 * np * groups].chunks_exact_mut(8) {
            let m = match kind {
                0 => i32::MIN,
                1 => i32::MAX,
                3 => ((r.next() >> 32) as i32) >> 12,
                _ => (r.next() >> 32) as i32,
            };
            e[..4].copy_from_slice(&m.to_le_bytes());
            e[4] = 8 + (r.next() % 55) as u8;
            e[5..].fill(0);
        }
        for e in t.bias[..32 * groups].chunks_exact_mut(8) {
            let b = ((r.next() >> 33) as i64) - (1 << 30) + 1;
            let b = if kind == 3 { b >> 12 } else { b };
            e.copy_from_slice(&b.to_le_bytes());
        }
        let lut_case = case % 3 == 2;
        let (lo, hi) = if lut_case { (-32768, 32767) } else { [(0, 255), (-128, 127), (-32768, 32767), (0, 32767)][(case % 4) as usize] };
        let table = if case % 2 == 0 { lut::sigmoid_table() } else { lut::tanh_table() };
        let (olo, ohi) = if lut_case { [(0, 255), (-128, 127), (-32768, 32767)][(case / 3 % 3) as usize] } else { (lo, hi) };
        let k = Requant4::new(np, lo, hi).with_out(olo, ohi);
        let table = lut_case.then_some(table);
        let mask = match (olo, ohi) {
            (-128, _) => requant_groups_case::<i8>(0x55, case, &d, wide, t, &k, np, table, groups),
            (0, 255) => requant_groups_case::<u8>(0x55, case, &d, wide, t, &k, np, table, groups),
            _ => requant_groups_case::<i16>(0x5555, case, &d, wide, t, &k, np, table, groups),
        };
        sat += mask.count_ones();
        clean += groups as u32 - mask.count_ones();
        cases += 1;
    }
    if sat < 100 || clean < 100 {
        println!("MUIR-KERNELS FAILED requant4_groups: {sat} saturated and {clean} clean groups (both must occur)");
        process::exit(1);
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
    // SAFETY: as above, the only user of `WW`.
    #[cfg(not(feature = "mve"))]
    let ww = unsafe { &mut *core::ptr::addr_of_mut!(WW) };
    for n in lengths() {
        for &(wf, xf) in &fills {
            cases += check("i16", &mut i16s, &mut r, n, wf, xf);
            #[cfg(not(feature = "mve"))]
            {
                cases += check_w16(&i16s, ww, n);
                cases += check_nat(&mut i16s, ww, n, &mut r);
            }
        }
    }
    #[cfg(feature = "mve")]
    {
        cases += check_dots4(&mut i16s, &mut r);
        cases += check_dots12(&mut *i16s.pair, &mut r);
        cases += check_dots12_u8(&mut *u8s.pair, &mut r);
        cases += check_attention(i16s.a, i16s.b, &mut r);
        cases += check_requant(&mut r);
        cases += check_popcount(&mut r);
        cases += check_weights(&mut r, i16s.a, i16s.b);
        cases += check_lookup(&mut r);
        cases += check_corr_window(&mut *i16s.w0, &mut *i16s.w1, &mut r);
        cases += check_q15(&mut *i16s.a, &mut *i16s.b, &mut r);
        cases += check_residual(&mut r);
        cases += check_max_abs(&mut r);
        cases += check_zero(&mut r);
        cases += check_dots_flipped(&mut *u8s.pair, &mut r);
        cases += check_requant_pair(&mut r);
        cases += check_requant_groups(&mut r);
        cases += check_logits32(&mut *i16s.a, &mut r);
    }
    cases += check_refine(&mut r);
    #[cfg(not(feature = "mve"))]
    {
        cases += check_requant_dsp(&mut r);
        cases += check_requant_parts(&mut r);
        cases += check_folded_high(&mut r);
        cases += check_groups(&mut r);
        cases += check_aggregate_dsp(i16s.a, &mut r);
        cases += check_corr4(&mut r);
        cases += check_corr4w(&mut r);
        cases += check_lookup_dsp(&mut *i8s.a, &mut *i8s.b, &mut r);
        cases += check_decide(&mut r);
        cases += check_logit_dsp(i16s.a, i16s.b, &mut r);
        cases += check_aggregate_cm(i16s.a, &mut r);
        cases += check_min_dsp(&mut r);
        cases += check_weights(&mut r, i16s.a, i16s.b);
    }
    cases += check_conv(&mut r);
    #[cfg(not(feature = "mve"))]
    {
        cases += check_conv_nat(&mut r);
    }
    println!("MUIR-KERNELS ok cases={cases}");
    process::exit(0)
}
