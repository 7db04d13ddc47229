//! Mutated model blobs end in `Ok` or a typed error, never a panic or a hang (issue #22 item 3):
//! a short run of the seeded mutation harness (`support/mutate.rs`); the long, documented run is
//! `cargo run --release --example fuzz_blob -- 1000000`.

#[path = "support/mutate.rs"]
mod mutate;

#[test]
fn mutated_blobs_are_typed_errors_or_run() {
    let rep = mutate::run(3_000, 1, |_| {});
    println!("{rep:?}");
    assert_eq!(rep.panics, 0, "{:#?}", rep.failures);
    assert_eq!(rep.hangs, 0, "{:#?}", rep.failures);
    // The harness reaches the engine: a good share of the mutants parse and run.
    assert!(rep.parsed > rep.executions / 10, "{rep:?}");
    assert!(rep.ran_ok > 0, "{rep:?}");
}
