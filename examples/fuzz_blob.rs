//! The long run of the blob mutation harness (issue #22 item 3): `cargo run --release --example
//! fuzz_blob -- [EXECUTIONS [SEED [FIRST]]]` (default 1,000,000 from seed 1; `FIRST` replays from
//! that execution on). Prints progress every 10,000 executions and a summary; exits with status 1
//! if any execution panicked or hung.

#[path = "../host-tests/support/mutate.rs"]
mod mutate;

fn main() {
    let mut args = std::env::args().skip(1);
    let n: u64 = args.next().and_then(|a| a.parse().ok()).unwrap_or(1_000_000);
    let seed: u64 = args.next().and_then(|a| a.parse().ok()).unwrap_or(1);
    let first: u64 = args.next().and_then(|a| a.parse().ok()).unwrap_or(0);
    let t0 = std::time::Instant::now();
    let rep = mutate::run_from(first, n, seed, |r| {
        let s = t0.elapsed().as_secs_f64();
        eprintln!(
            "{} / {n} ({:.0} %, {:.0} s, ETA {:.0} s): parsed {}, ran {}, engine errors {}, panics {}, hangs {}",
            r.executions,
            100.0 * r.executions as f64 / n as f64,
            s,
            s / r.executions as f64 * (n - r.executions) as f64,
            r.parsed,
            r.ran_ok,
            r.engine_errors,
            r.panics,
            r.hangs
        );
    });
    println!(
        "fuzz_blob: {} executions from seed {seed} in {:.0} s: {} parsed, {} ran to the end, {} engine errors, {} panics, {} hangs (slowest {:?})",
        rep.executions,
        t0.elapsed().as_secs_f64(),
        rep.parsed,
        rep.ran_ok,
        rep.engine_errors,
        rep.panics,
        rep.hangs,
        rep.slowest
    );
    println!("parse errors by kind: {:?}", rep.parse_errors);
    for (e, what) in &rep.failures {
        println!("  execution {e}: {what}");
    }
    if rep.panics + rep.hangs > 0 {
        std::process::exit(1);
    }
}
