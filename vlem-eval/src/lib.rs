//! vlem-eval: how good a run was.
//!
//! - [`trajectory`]: absolute trajectory error (after a least-squares rigid alignment) and
//!   relative pose error of an estimated camera trajectory against a reference.
//! - [`error`]: the crate's one error type, [`EvalError`].

pub mod error;
pub mod trajectory;

pub use error::{EvalError, Result};
