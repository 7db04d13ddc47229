//! Wall time of each phase of the last frame (host builds, feature `std`): where a frame's time
//! goes, and how each phase scales with threads (`muir run --timings`). A firmware build has
//! none of this (no clock in the core): there the QEMU instruction profile answers the question.

use core::time::Duration;
use std::time::Instant;

/// The phases of a frame, in the order they run (the per-iteration ones summed over the
/// iterations). With two or more threads some run beside each other (`engine::side`), and the
/// timer, on the calling thread, books them as follows: UFI and the MGA setup under [`Phase::Ufi`]
/// until UFI ends and under [`Phase::MgaSetup`] for the wait for the other thread after it; MUD,
/// the MGA values and the 1/16 steps under [`Phase::Gru16`] until the 1/16 steps end and under
/// [`Phase::Mud`] for the wait after them ([`Phase::MgaValues`] stays 0); the MGA aggregation
/// within [`Phase::Gru08`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// Both image encoders (side by side with threads).
    Encoders,
    /// UFI: proposals, initializer and decoder.
    Ufi,
    /// MGA keys, queries and softmax statistics.
    MgaSetup,
    /// MUD passes of the iterations.
    Mud,
    /// MGA values of the iterations.
    MgaValues,
    /// The 1/16 ConvGRU steps (two an iteration).
    Gru16,
    /// Motion encoder, MGA aggregation and the 1/8 ConvGRU.
    Gru08,
    /// Disparity head.
    FlowHead,
    /// The last MUD pass and the convex upsampling to full resolution.
    Output,
    /// The full-resolution refinement (semi-global matching in a band).
    FullRes,
}

impl Phase {
    /// Every phase, in order.
    pub const ALL: [Phase; 10] =
        [Phase::Encoders, Phase::Ufi, Phase::MgaSetup, Phase::Mud, Phase::MgaValues, Phase::Gru16, Phase::Gru08, Phase::FlowHead, Phase::Output, Phase::FullRes];

    /// A short name (`encoders`, `ufi`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Phase::Encoders => "encoders",
            Phase::Ufi => "ufi",
            Phase::MgaSetup => "mga setup",
            Phase::Mud => "mud",
            Phase::MgaValues => "mga values",
            Phase::Gru16 => "gru16",
            Phase::Gru08 => "motion + mga + gru08",
            Phase::FlowHead => "flow head",
            Phase::Output => "final mud + upsample",
            Phase::FullRes => "full-res refinement",
        }
    }
}

/// Wall time per [`Phase`] of a frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PhaseTimes {
    times: [Duration; Phase::ALL.len()],
}

impl PhaseTimes {
    /// The time of phase `p`.
    pub fn get(&self, p: Phase) -> Duration {
        self.times.get(p as usize).copied().unwrap_or_default()
    }

    /// Every phase with its time, in order.
    pub fn iter(&self) -> impl Iterator<Item = (Phase, Duration)> + '_ {
        Phase::ALL.iter().map(|&p| (p, self.get(p)))
    }

    /// The frame: the sum of the phases.
    pub fn total(&self) -> Duration {
        self.times.iter().sum()
    }
}

/// Adds the time since the previous lap to a phase.
pub(super) struct Stopwatch {
    last: Instant,
    pub(super) times: PhaseTimes,
}

impl Stopwatch {
    pub(super) fn new() -> Self {
        Stopwatch { last: Instant::now(), times: PhaseTimes::default() }
    }

    /// Ends phase `p` (its time since the last lap is added to it).
    pub(super) fn lap(&mut self, p: Phase) {
        let now = Instant::now();
        if let Some(t) = self.times.times.get_mut(p as usize) {
            *t += now - self.last;
        }
        self.last = now;
    }
}
