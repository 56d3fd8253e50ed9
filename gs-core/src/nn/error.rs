//! The error type of the `nn` module: shape mismatches and non-finite values.
//!
//! Every public entry point of `nn` validates sizes and finiteness up front and returns one
//! of these instead of panicking, so a NaN never reaches a network's parameters silently.

/// Error from a network, an encoding or an input-assembly helper.
#[derive(Debug, Clone, PartialEq)]
pub enum NnError {
    /// A slice had the wrong length for the declared shape.
    Shape {
        what: &'static str,
        expected: usize,
        got: usize,
    },
    /// A configuration value was out of range (zero width, too many frequencies, empty box).
    Config(String),
    /// A NaN or infinity was found in an input, a parameter or an output.
    NonFinite { what: &'static str, index: usize },
    /// A Gaussian index pointed past the end of the parameter arrays.
    Index { index: usize, len: usize },
    /// A geometric quantity had no defined value (a Gaussian at the camera centre, a zero
    /// Sun vector); `index` is the Gaussian's index where there is one.
    Degenerate { what: &'static str, index: usize },
}

impl std::fmt::Display for NnError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            NnError::Shape {
                what,
                expected,
                got,
            } => write!(f, "{what}: expected {expected} values, got {got}"),
            NnError::Config(msg) => write!(f, "invalid network configuration: {msg}"),
            NnError::NonFinite { what, index } => {
                write!(f, "{what}: non-finite value at index {index}")
            }
            NnError::Index { index, len } => {
                write!(f, "Gaussian index {index} out of range (model has {len})")
            }
            NnError::Degenerate { what, index } => {
                write!(f, "{what} is undefined (index {index})")
            }
        }
    }
}

impl std::error::Error for NnError {}

/// `Ok` when `values.len() == expected`.
pub(crate) fn check_len(what: &'static str, values: usize, expected: usize) -> Result<(), NnError> {
    if values == expected {
        Ok(())
    } else {
        Err(NnError::Shape {
            what,
            expected,
            got: values,
        })
    }
}

/// `Ok` when every value is finite; otherwise the first offending flat index.
pub(crate) fn check_finite(what: &'static str, values: &[f32]) -> Result<(), NnError> {
    // Branch-free sweep first (vectorises); the index search runs only on failure.
    let all_finite = values
        .chunks(64)
        .all(|chunk| chunk.iter().fold(true, |ok, v| ok & v.is_finite()));
    if all_finite {
        return Ok(());
    }
    let index = values.iter().position(|v| !v.is_finite()).unwrap_or(0);
    Err(NnError::NonFinite { what, index })
}
