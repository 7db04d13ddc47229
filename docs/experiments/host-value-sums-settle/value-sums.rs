//! The MGA value sums' inner loop two ways, on data in cache, without the engine around it: the
//! engine's (each softmax weight split in two bytes, two `vpdpwssd` a key pair and channel
//! vector) against the "settled" form (one `vpdpwssd` of `e - 16384` a key pair, wrapping in
//! i32, and one `vpdpbusd` of the weights' and values' high bytes a key quad, from which the
//! wrapped sums are settled every 128 keys). See README.md in this folder.
//!
//!     rustc -C opt-level=3 --edition 2021 value-sums.rs && ./value-sums
use std::arch::x86_64::*;
use std::time::Instant;

/// Value channels.
const CV: usize = 64;

/// The engine's loop (`Prepared::values_kept` at 2026-12-06): 2 queries, 4 channel vectors.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
unsafe fn split(vt: &[i32], rows: &[u32], npad: usize, reps: usize) -> i32 {
    let z = _mm512_setzero_si512();
    let bytes = _mm512_set1_epi32(0x00FF_00FF);
    let mut tot = z;
    for rep in 0..reps {
        let rp = [rows.as_ptr().add((rep % 8) * npad / 2), rows.as_ptr().add(((rep + 1) % 8) * npad / 2)];
        for j0 in (0..npad).step_by(256) {
            let (mut h, mut l) = ([[z; 4]; 2], [[z; 4]; 2]);
            for pk in j0 / 2..(j0 + 256) / 2 {
                let vrow = vt.as_ptr().add(pk * CV);
                let mut v = [z; 4];
                for (b, v) in v.iter_mut().enumerate() {
                    *v = _mm512_loadu_si512(vrow.add(16 * b).cast());
                }
                for t in 0..2 {
                    let e = _mm512_set1_epi32(*rp[t].add(pk) as i32);
                    let (bh, bl) = (_mm512_and_si512(_mm512_srli_epi32::<8>(e), bytes), _mm512_and_si512(e, bytes));
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
        }
    }
    _mm512_reduce_add_epi32(tot)
}

/// The settled form: `RK` queries, `NB` channel vectors; `SETTLE`: the i64 settling of every 128
/// keys' sums into memory, as the engine would need it (else the sums are only added up).
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[allow(clippy::too_many_arguments)]
unsafe fn settled<const RK: usize, const NB: usize, const SETTLE: bool>(vt: &[i32], vq: &[i32], vs: &[i32], acc: &mut [i64], ew: &[[i32; 128]; 4], eq: &[[i32; 64]; 4], npad: usize, reps: usize) -> i32 {
    let z = _mm512_setzero_si512();
    let mut tot = z;
    for _ in 0..reps {
        for j0 in (0..npad).step_by(256) {
            for cb in (0..CV / 16).step_by(NB) {
                for sb in 0..2 {
                    // The two pairs of a quad in accumulators of their own: one chain through
                    // both is split by LLVM into `vpmaddwd` + `vpaddd`.
                    let (mut w, mut w1, mut h) = ([[z; NB]; RK], [[z; NB]; RK], [[z; NB]; RK]);
                    for qd in 0..32 {
                        let quad = sb * 32 + qd;
                        for half in 0..2 {
                            let vrow = vt.as_ptr().add((j0 / 2 + 2 * quad + half) * CV + 16 * cb);
                            let mut v = [z; NB];
                            for (b, v) in v.iter_mut().enumerate() {
                                *v = _mm512_loadu_si512(vrow.add(16 * b).cast());
                            }
                            let w = if half == 0 { &mut w } else { &mut w1 };
                            for t in 0..RK {
                                let e = _mm512_set1_epi32(ew[t][2 * quad + half]);
                                for b in 0..NB {
                                    w[t][b] = _mm512_dpwssd_epi32(w[t][b], v[b], e);
                                }
                            }
                        }
                        let qrow = vq.as_ptr().add((j0 / 4 + quad) * CV + 16 * cb);
                        let mut v = [z; NB];
                        for (b, v) in v.iter_mut().enumerate() {
                            *v = _mm512_loadu_si512(qrow.add(16 * b).cast());
                        }
                        for t in 0..RK {
                            let e = _mm512_set1_epi32(eq[t][quad]);
                            for b in 0..NB {
                                h[t][b] = _mm512_dpbusd_epi32(h[t][b], e, v[b]);
                            }
                        }
                    }
                    for t in 0..RK {
                        for b in 0..NB {
                            let wv = _mm512_add_epi32(w[t][b], w1[t][b]);
                            if SETTLE {
                                let s = _mm512_loadu_si512(vs.as_ptr().add((j0 / 128 + sb) * CV + 16 * (cb + b)).cast());
                                settle(wv, h[t][b], s, &mut acc[t * CV + 16 * (cb + b)..t * CV + 16 * (cb + b + 1)]);
                            } else {
                                tot = _mm512_add_epi32(tot, _mm512_add_epi32(wv, h[t][b]));
                            }
                        }
                    }
                }
            }
        }
    }
    _mm512_reduce_add_epi32(tot) + acc[5] as i32
}

/// 16 exact sums into `a` from the wrapped `w`, the high bytes' `h` and the values' sums `s`.
#[target_feature(enable = "avx512f")]
unsafe fn settle(w: __m512i, h: __m512i, s: __m512i, a: &mut [i64]) {
    let round = _mm512_set1_epi64(1 << 31);
    let halves = [
        (_mm512_castsi512_si256(w), _mm512_castsi512_si256(h), _mm512_castsi512_si256(s)),
        (_mm512_extracti64x4_epi64::<1>(w), _mm512_extracti64x4_epi64::<1>(h), _mm512_extracti64x4_epi64::<1>(s)),
    ];
    for (k, (w, h, s)) in halves.into_iter().enumerate() {
        let (w, h, s) = (_mm512_cvtepi32_epi64(w), _mm512_cvtepi32_epi64(h), _mm512_cvtepi32_epi64(s));
        let s14 = _mm512_slli_epi64::<14>(s);
        let wraps = _mm512_srai_epi64::<32>(_mm512_add_epi64(_mm512_sub_epi64(_mm512_sub_epi64(_mm512_slli_epi64::<16>(h), s14), w), round));
        let exact = _mm512_add_epi64(_mm512_add_epi64(w, _mm512_slli_epi64::<32>(wraps)), s14);
        let a = &mut a[8 * k..8 * k + 8];
        _mm512_storeu_si512(a.as_mut_ptr().cast(), _mm512_add_epi64(_mm512_loadu_si512(a.as_ptr().cast()), exact));
    }
}

fn main() {
    if !(is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("avx512bw") && is_x86_feature_detected!("avx512vnni")) {
        println!("no AVX-512 VNNI on this CPU");
        return;
    }
    println!("| keys (values: split, settled) | split, 2 queries | settled, 4 queries, no settling | settled, 4 queries | settled / split |");
    println!("|---|---:|---:|---:|---:|");
    for npad in [512usize, 2816, 7680] {
        let vt: Vec<i32> = (0..npad / 2 * CV).map(|i| (i as i32).wrapping_mul(2654435761u32 as i32)).collect();
        let vq: Vec<i32> = (0..npad / 4 * CV).map(|i| (i as i32).wrapping_mul(40503)).collect();
        let vs: Vec<i32> = (0..npad / 128 * CV).map(|i| i as i32).collect();
        let rows: Vec<u32> = (0..8 * npad / 2).map(|i| (i as u32).wrapping_mul(2246822519) & 0x7FFF_7FFF).collect();
        let (ew, eq) = ([[3i32; 128]; 4], [[5i32; 64]; 4]);
        let mut acc = vec![0i64; 4 * CV];
        // Query-key-channel products a second.
        let rate = |queries: usize, reps: usize, secs: f64| (queries * reps * npad * CV) as f64 / secs / 1e9;
        let reps = 2_000_000_000 / (npad * CV);
        let t = Instant::now();
        // SAFETY: AVX-512 F/BW/VNNI checked above; every load lies inside the buffers.
        let r0 = unsafe { split(&vt, &rows, npad, reps) };
        let a = rate(2, reps, t.elapsed().as_secs_f64());
        let t = Instant::now();
        // SAFETY: as above.
        let r1 = unsafe { settled::<4, 2, false>(&vt, &vq, &vs, &mut acc, &ew, &eq, npad, reps / 2) };
        let b = rate(4, reps / 2, t.elapsed().as_secs_f64());
        let t = Instant::now();
        // SAFETY: as above.
        let r2 = unsafe { settled::<4, 2, true>(&vt, &vq, &vs, &mut acc, &ew, &eq, npad, reps / 2) };
        let c = rate(4, reps / 2, t.elapsed().as_secs_f64());
        println!("| {npad} ({} KB, {} KB) | {a:.1} G | {b:.1} G | {c:.1} G | {:.2} |  ({})", npad / 2 * CV * 4 / 1024, (npad / 2 + npad / 4) * CV * 4 / 1024, c / a, (r0 ^ r1 ^ r2) & 1);
    }
}
