//! vlem-eval: how good a run was.
//!
//! - [`trajectory`]: absolute trajectory error (after a least-squares rigid alignment) and
//!   relative pose error of an estimated camera trajectory against a reference.
//! - [`semseg`]: open-vocabulary semantic segmentation in 3D and 2D, under the paper's protocol
//!   (IoU averaged over similarity thresholds) and RayFronts' (argmax over class prompts).
//! - [`error`]: the crate's one error type, [`EvalError`].

mod error;
pub mod semseg;
pub mod trajectory;

pub use error::{EvalError, Result};
