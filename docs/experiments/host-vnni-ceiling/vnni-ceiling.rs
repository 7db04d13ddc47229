//! The 512-bit `vpdpwssd` loop of `conv_avx512::block` without the engine around it: how many
//! i16 multiply-accumulates a second the loop pattern reaches on this CPU, against the same
//! instruction with register operands only. See README.md in this folder.
//!
//!     rustc -C opt-level=3 vnni-ceiling.rs && ./vnni-ceiling
use std::arch::x86_64::*;
use std::time::Instant;

/// `vpdpwssd` on registers only: 16 independent accumulators.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
unsafe fn registers(n: usize) -> i32 {
    let mut a = [_mm512_set1_epi32(1); 16];
    let (x, y) = (_mm512_set1_epi32(3), _mm512_set1_epi32(5));
    for _ in 0..n {
        for a in a.iter_mut() {
            *a = _mm512_dpwssd_epi32(*a, x, y);
        }
    }
    a.iter().fold(_mm512_setzero_si512(), |s, v| _mm512_add_epi32(s, *v)).as_i32()
}

trait Sum {
    fn as_i32(self) -> i32;
}
impl Sum for __m512i {
    fn as_i32(self) -> i32 {
        // SAFETY: AVX-512 F is checked in `main` before any of this runs.
        unsafe { _mm512_reduce_add_epi32(self) }
    }
}

/// The engine's loop shape: `R` output channels x `P` vectors of 16 pixels in registers; a 3x3
/// layer's 9 taps, each `groups` groups of two i16 channels; activations `[ky][group][column]`
/// (`gs` columns a group, tap `kx` one column further), each channel's weights a row of its own,
/// one group broadcast per channel and step.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
unsafe fn layer<const R: usize, const P: usize>(xt: &[i32], gs: usize, groups: usize, w: &[Vec<i32>], npx: usize, reps: usize) -> i32 {
    let mut tot = _mm512_setzero_si512();
    for _ in 0..reps {
        for c0 in (0..w.len() + 1 - R).step_by(R) {
            let wp: [*const i32; R] = core::array::from_fn(|i| w[c0 + i].as_ptr());
            let mut x = 0;
            while x + 16 * P <= npx {
                let mut acc = [[_mm512_setzero_si512(); P]; R];
                for tap in 0..9 {
                    let xb = xt.as_ptr().add((tap / 3) * groups * gs + tap % 3 + x);
                    for g in 0..groups {
                        let xs: [__m512i; P] = core::array::from_fn(|v| _mm512_loadu_si512(xb.add(g * gs + 16 * v).cast()));
                        for i in 0..R {
                            let b = _mm512_set1_epi32(*wp[i].add(tap * groups + g));
                            for v in 0..P {
                                acc[i][v] = _mm512_dpwssd_epi32(acc[i][v], xs[v], b);
                            }
                        }
                    }
                }
                for a in acc.iter() {
                    for v in a {
                        tot = _mm512_add_epi32(tot, *v);
                    }
                }
                x += 16 * P;
            }
        }
    }
    tot.as_i32()
}

fn run<const R: usize, const P: usize>(groups: usize, cout: usize, npx: usize) {
    let gs = npx + 3;
    let xt: Vec<i32> = (0..3 * groups * gs + 64).map(|i| i as i32 & 0x7fff).collect();
    let w: Vec<Vec<i32>> = (0..cout).map(|c| (0..9 * groups).map(|g| (g + c) as i32).collect()).collect();
    let macs = (cout / R * R) * (npx / (16 * P) * 16 * P) * 9 * groups * 2;
    let reps = (20_000_000_000 / macs).max(1);
    let t = Instant::now();
    // SAFETY: AVX-512 F/BW/VNNI checked in `main`; every load lies inside `xt` and `w`.
    let r = unsafe { layer::<R, P>(&xt, gs, groups, &w, npx, reps) };
    let dt = t.elapsed().as_secs_f64();
    println!("| {groups} groups a tap, {cout} channels, {npx} pixels | {R} x {P} | {:.1} |  ({})", (reps * macs) as f64 / dt / 1e9, r & 1);
}

/// The MGA value sums of kept weights (`attention_avx512::Prepared::values_kept::<4>`): per key
/// pair, the 64 channels' value pairs (4 vectors) times two queries' weight pairs, each weight
/// split into bytes `e >> 8` and `e & 255` (two `vpdpwssd` per product pair), 128 pairs per
/// flush. `presplit`: the split bytes read from memory instead (no ALU operations in the loop).
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
unsafe fn values(vt: &[u32], rows: &[Vec<u32>; 2], split: &[Vec<u32>; 2], npairs: usize, presplit: bool) -> i32 {
    let bytes = _mm512_set1_epi32(0x00FF_00FF);
    let z = _mm512_setzero_si512();
    let mut tot = z;
    let mut j0 = 0;
    while j0 < npairs {
        let (mut h, mut l) = ([[z; 4]; 2], [[z; 4]; 2]);
        for pk in j0..(j0 + 128).min(npairs) {
            let vrow = vt.as_ptr().add(pk * 64);
            let v: [__m512i; 4] = core::array::from_fn(|b| _mm512_loadu_si512(vrow.add(16 * b).cast()));
            for t in 0..2 {
                let (bh, bl) = if presplit {
                    (_mm512_set1_epi32(*split[t].as_ptr().add(2 * pk) as i32), _mm512_set1_epi32(*split[t].as_ptr().add(2 * pk + 1) as i32))
                } else {
                    let e = _mm512_set1_epi32(*rows[t].as_ptr().add(pk) as i32);
                    (_mm512_and_si512(_mm512_srli_epi32::<8>(e), bytes), _mm512_and_si512(e, bytes))
                };
                for b in 0..4 {
                    h[t][b] = _mm512_dpwssd_epi32(h[t][b], v[b], bh);
                    l[t][b] = _mm512_dpwssd_epi32(l[t][b], v[b], bl);
                }
            }
        }
        for t in 0..2 {
            for b in 0..4 {
                tot = _mm512_add_epi32(tot, _mm512_add_epi32(h[t][b], l[t][b]));
            }
        }
        j0 += 128;
    }
    tot.as_i32()
}

fn run_values(keys: usize, presplit: bool) {
    let npairs = keys / 2;
    let rnd = |i: usize| (i as u32).wrapping_mul(2_654_435_761) & 0x7fff_7fff;
    let vt: Vec<u32> = (0..npairs * 64).map(rnd).collect();
    let rows: Vec<[Vec<u32>; 2]> = (0..8).map(|q| core::array::from_fn(|t| (0..npairs).map(|k| rnd(7 * k + t + q) & 0x7fff_7fff).collect())).collect();
    let split: Vec<[Vec<u32>; 2]> = rows.iter().map(|r| core::array::from_fn(|t| r[t].iter().flat_map(|&e| [(e >> 8) & 0x00ff_00ff, e & 0x00ff_00ff]).collect())).collect();
    // `vpdpwssd` lane products: 64 channels x 2 keys x 2 queries x 2 (bytes) per key pair.
    let per = npairs * 64 * 2 * 2 * 2;
    let reps = 4_000_000_000 / per;
    let t = Instant::now();
    let mut s = 0;
    for i in 0..reps {
        // SAFETY: AVX-512 F/BW/VNNI checked in `main`; every load lies inside the buffers.
        s ^= unsafe { values(&vt, &rows[i % 8], &split[i % 8], npairs, presplit) };
    }
    let dt = t.elapsed().as_secs_f64();
    println!("| {keys} keys ({} KB of values) | {} | {:.1} |  ({})", npairs * 256 / 1024, if presplit { "read from memory" } else { "split in the loop" }, (reps * per) as f64 / dt / 1e9, s & 1);
}

fn main() {
    if !(is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("avx512bw") && is_x86_feature_detected!("avx512vnni")) {
        eprintln!("needs AVX-512 F, BW and VNNI");
        std::process::exit(1);
    }
    let n = 50_000_000;
    let t = Instant::now();
    // SAFETY: checked above.
    let r = unsafe { registers(n) };
    println!("registers only: {:.1} GMAC/s ({})", (n * 16 * 32) as f64 / t.elapsed().as_secs_f64() / 1e9, r & 1);
    println!("\n| layer | channels x pixel vectors | GMAC/s |\n|---|---|---:|");
    for _ in 0..2 {
        run::<8, 2>(32, 128, 64);
        run::<6, 4>(32, 126, 64);
        run::<12, 2>(32, 132, 64);
        run::<8, 2>(320, 128, 64);
        run::<6, 4>(320, 126, 64);
        run::<12, 2>(320, 132, 64);
    }
    println!("\n| MGA value sums | weight bytes | G lane products/s |\n|---|---|---:|");
    for _ in 0..2 {
        for keys in [512, 4800] {
            run_values(keys, false);
            run_values(keys, true);
        }
    }
}
