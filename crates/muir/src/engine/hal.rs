//! `embedded-hal` helpers (feature `hal`).
//!
//! [`run_with_busy_pin`] raises a GPIO for the duration of a frame, the usual way to time
//! inference on a board with a logic analyser or an oscilloscope (the pulse width is the frame
//! time, with no timer or logging in the loop).
//!
//! ```ignore
//! let mut engine = Engine::new(&model, &mut ARENA.0)?;
//! run_with_busy_pin(&mut engine, &left, &right, &mut out, &mut busy_pin)?;
//! ```

use embedded_hal::digital::OutputPin;

use super::{Engine, EngineError, Output};
use crate::input::ImageView;

/// [`Engine::run`] with `pin` driven high while the frame is computed and low afterwards.
///
/// The pin goes low again even when the engine refuses the pair, so a failed frame shows as a
/// short pulse.
///
/// # Errors
/// The engine's error if it refused the run (it takes precedence over a pin error when both
/// fail), else [`EngineError::Pin`] if the pin could not be driven. When the pin cannot be driven
/// high the frame is not computed.
pub fn run_with_busy_pin<P: OutputPin>(
    engine: &mut Engine<'_, '_, '_>,
    left: &ImageView<'_>,
    right: &ImageView<'_>,
    out: &mut Output<'_>,
    pin: &mut P,
) -> Result<(), EngineError> {
    pin.set_high().map_err(|_| EngineError::Pin)?;
    let result = engine.run(left, right, out);
    let low = pin.set_low().map_err(|_| EngineError::Pin);
    result.and(low)
}
