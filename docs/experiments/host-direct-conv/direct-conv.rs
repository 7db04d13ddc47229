//! A 3x3, stride-1 convolution row of u8 activations and i8 weights with the output channels
//! along the vector (one input group of 4 channels broadcast per pixel, weights re-laid
//! `[ky][kx][group][cout]`), reading the rows in their `[x][c]` order: no transposition of the
//! inputs or the outputs. Checked exact against a plain loop (sums, then requantised u8 outputs),
//! then timed. See README.md in this folder.
//!
//!     rustc --edition 2021 -C opt-level=3 direct-conv.rs && ./direct-conv
use std::arch::x86_64::*;
use std::time::Instant;

struct Rng(u64);
impl Rng { fn next(&mut self) -> u64 { self.0 ^= self.0 << 13; self.0 ^= self.0 >> 7; self.0 ^= self.0 << 17; self.0 } }

/// exact sums, reference: out[x][c] = sum_{ky,kx,ci} in[ky][x+kx-1][ci] * w[c][ky][kx][ci]
fn reference(rows: &[Vec<u8>; 3], w: &[i8], cin: usize, cout: usize, width: usize) -> Vec<i32> {
    let mut out = vec![0i32; width * cout];
    for x in 0..width { for c in 0..cout {
        let mut s = 0i32;
        for ky in 0..3 { for kx in 0..3 {
            let xx = x as isize + kx as isize - 1;
            if xx < 0 || xx >= width as isize { continue; }
            for ci in 0..cin { s += rows[ky][xx as usize * cin + ci] as i32 * w[((c * 3 + ky) * 3 + kx) * cin + ci] as i32; }
        }}
        out[x * cout + c] = s;
    }}
    out
}

/// weights re-laid [ky][kx][g][cout] as i32 (4 i8 of group g for channel c)
fn relay(w: &[i8], cin: usize, cout: usize) -> Vec<i32> {
    let g_n = cin / 4;
    let mut r = vec![0i32; 9 * g_n * cout];
    for c in 0..cout { for t in 0..9 { for g in 0..g_n {
        let b = &w[(c * 9 + t) * cin + 4 * g..][..4];
        r[(t * g_n + g) * cout + c] = i32::from_le_bytes([b[0] as u8, b[1] as u8, b[2] as u8, b[3] as u8]);
    }}}
    r
}

/// padded rows: one zero column each side, [x+1][ci]
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
unsafe fn direct<const PX: usize>(pad: &[Vec<u8>; 3], wr: &[i32], cin: usize, cout: usize, width: usize, out: &mut [i32], epi: Option<(&[i64], &[i64], &[i64], &mut [u8])>) {
    let epi = epi.map(|(m, s, b, o)| (m.as_ptr(), s.as_ptr(), b.as_ptr(), o.as_mut_ptr()));
    let mut cb = 0;
    while cb < cout {
        if cb + 32 <= cout { block::<PX, 2>(pad, wr, cin, cout, width, out, cb, epi); cb += 32; } else { block::<PX, 1>(pad, wr, cin, cout, width, out, cb, epi); cb += 16; }
    }
}

#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[inline]
unsafe fn block<const PX: usize, const NV: usize>(pad: &[Vec<u8>; 3], wr: &[i32], cin: usize, cout: usize, width: usize, out: &mut [i32], cb: usize, epi: Option<(*const i64, *const i64, *const i64, *mut u8)>) {
    let g_n = cin / 4;
    let mut x0 = 0;
    while x0 < width {
        let np = (width - x0).min(PX);
        {
            let mut acc = [[_mm512_setzero_si512(); NV]; PX];
            for ky in 0..3 {
                let row = pad[ky].as_ptr();
                for kx in 0..3 {
                    let wt = wr.as_ptr().add((ky * 3 + kx) * g_n * cout + cb);
                    let xp = row.add((x0 + kx) * cin);
                    for g in 0..g_n {
                        let wv: [__m512i; NV] = core::array::from_fn(|v| _mm512_loadu_si512(wt.add(g * cout + 16 * v).cast()));
                        for p in 0..PX {
                            let a = _mm512_set1_epi32((xp.add(p * cin + 4 * g) as *const i32).read_unaligned());
                            for v in 0..NV { acc[p][v] = _mm512_dpbusd_epi32(acc[p][v], a, wv[v]); }
                        }
                    }
                }
            }
            match epi {
                None => for p in 0..np { for v in 0..NV {
                    _mm512_storeu_si512(out.as_mut_ptr().add((x0 + p) * cout + cb + 16 * v).cast(), acc[p][v]);
                }},
                Some((m, sh, b, o)) => {
                    // per channel (8 lanes of i64 each half): r = clamp(((sum m + 2^(s-1)) >> s) + b, 0, 255)
                    for v in 0..NV {
                        let c = cb + 16 * v;
                        let (m0, m1) = (_mm512_loadu_si512(m.add(c).cast()), _mm512_loadu_si512(m.add(c + 8).cast()));
                        let (s0, s1) = (_mm512_loadu_si512(sh.add(c).cast()), _mm512_loadu_si512(sh.add(c + 8).cast()));
                        let (b0, b1) = (_mm512_loadu_si512(b.add(c).cast()), _mm512_loadu_si512(b.add(c + 8).cast()));
                        let one = _mm512_set1_epi64(1);
                        let (h0, h1) = (_mm512_sllv_epi64(one, _mm512_sub_epi64(s0, one)), _mm512_sllv_epi64(one, _mm512_sub_epi64(s1, one)));
                        let (lo, hi) = (_mm512_setzero_si512(), _mm512_set1_epi64(255));
                        for p in 0..np {
                            let a = acc[p][v];
                            let (a0, a1) = (_mm512_cvtepi32_epi64(_mm512_castsi512_si256(a)), _mm512_cvtepi32_epi64(_mm512_extracti64x4_epi64::<1>(a)));
                            let r0 = _mm512_add_epi64(_mm512_srav_epi64(_mm512_add_epi64(_mm512_mul_epi32(a0, m0), h0), s0), b0);
                            let r1 = _mm512_add_epi64(_mm512_srav_epi64(_mm512_add_epi64(_mm512_mul_epi32(a1, m1), h1), s1), b1);
                            let (r0, r1) = (_mm512_min_epi64(_mm512_max_epi64(r0, lo), hi), _mm512_min_epi64(_mm512_max_epi64(r1, lo), hi));
                            let d = o.add((x0 + p) * cout + c);
                            _mm_storel_epi64(d.cast(), _mm512_cvtepi64_epi8(r0));
                            _mm_storel_epi64(d.add(8).cast(), _mm512_cvtepi64_epi8(r1));
                        }
                    }
                }
            }
        }
        x0 += PX;
    }
}

fn run(cin: usize, cout: usize, width: usize, rows_n: usize) {
    let mut r = Rng(0x9e3779b97f4a7c15);
    let rows: [Vec<u8>; 3] = core::array::from_fn(|_| (0..width * cin).map(|_| r.next() as u8).collect());
    let w: Vec<i8> = (0..cout * 9 * cin).map(|_| r.next() as i8).collect();
    let want = reference(&rows, &w, cin, cout, width);
    let wr = relay(&w, cin, cout);
    // padded copies (+1 column each side, +16 columns slack for the last pixel block)
    let pad: [Vec<u8>; 3] = core::array::from_fn(|k| { let mut v = vec![0u8; (width + 2 + 16) * cin]; v[cin..cin + width * cin].copy_from_slice(&rows[k]); v });
    let mut got = vec![0i32; (width + 16) * cout];
    unsafe { direct::<8>(&pad, &wr, cin, cout, width, &mut got, None) };
    if let Some(i) = (0..width * cout).find(|&i| want[i] != got[i]) { panic!("mismatch at x {} c {}: want {} got {}", i / cout, i % cout, want[i], got[i]); }
    let reps = 2000;
    let t = Instant::now();
    for _ in 0..reps { for _ in 0..rows_n { unsafe { direct::<8>(&pad, &wr, cin, cout, width, &mut got, None) }; } }
    let dt = t.elapsed().as_secs_f64() / reps as f64;
    let macs = (rows_n * width * cout * cin * 9) as f64;
    println!("| {cin} -> {cout}, {rows_n} rows of {width} | exact sums | {:.1} us | {:.0} |", dt * 1e6, macs / dt / 1e9);
    // with the epilogue: per channel multiplier m in [2^30, 2^31), shift 36..44, bias
    let m: Vec<i64> = (0..cout).map(|_| (1i64 << 30) + (r.next() % (1 << 30)) as i64).collect();
    let sh: Vec<i64> = (0..cout).map(|_| 36 + (r.next() % 8) as i64).collect();
    let b: Vec<i64> = (0..cout).map(|_| (r.next() % 64) as i64 - 32).collect();
    let mut o = vec![0u8; (width + 16) * cout];
    unsafe { direct::<8>(&pad, &wr, cin, cout, width, &mut got, Some((&m, &sh, &b, &mut o))) };
    for x in 0..width { for c in 0..cout {
        let v = want[x * cout + c] as i64;
        let e = (((v * m[c] + (1i64 << (sh[c] - 1))) >> sh[c]) + b[c]).clamp(0, 255) as u8;
        assert_eq!(e, o[x * cout + c], "epilogue x {x} c {c}");
    }}
    let t = Instant::now();
    for _ in 0..reps { for _ in 0..rows_n { unsafe { direct::<8>(&pad, &wr, cin, cout, width, &mut got, Some((&m, &sh, &b, &mut o))) }; } }
    let dt = t.elapsed().as_secs_f64() / reps as f64;
    println!("| {cin} -> {cout}, {rows_n} rows of {width} | u8 outputs (requantised) | {:.1} us | {:.0} |", dt * 1e6, macs / dt / 1e9);
}

fn main() {
    if !(is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("avx512bw") && is_x86_feature_detected!("avx512vnni")) {
        eprintln!("needs AVX-512 F, BW and VNNI");
        std::process::exit(1);
    }
    println!("| layer | output | time | G multiply-accumulates/s |\n|---|---|---:|---:|");
    for _ in 0..2 {
        run(64, 64, 160, 4);
        run(32, 32, 225, 4);
        run(48, 48, 113, 4);
    }
}
