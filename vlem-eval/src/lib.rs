//! vlem-eval: how good a run was.
//!
//! - [`trajectory`]: absolute trajectory error (after a least-squares rigid alignment) and
//!   relative pose error of an estimated camera trajectory against a reference.
//! - [`semseg`]: open-vocabulary semantic segmentation in 3D and 2D, under the paper's protocol
//!   (IoU averaged over similarity thresholds) and RayFronts' (argmax over class prompts).
//! - [`report`]: whole evaluations from files and configs to one serialisable report, as the
//!   `vlem eval` command, the study runner and the Python package run them.
//! - [`run_folder`]: a run's outputs written into its folder as one set (trajectory, map, stats),
//!   as `vlem run`, the study's cells and Python write them.
//! - [`study`]: comparison studies (maps × encoders × trackers × sequences), one child process
//!   per cell, results as a table.
//! - [`error`]: the crate's one error type, [`EvalError`].

mod error;
pub mod report;
pub mod run_folder;
pub mod semseg;
pub mod study;
pub mod trajectory;

pub use error::{EvalError, Result};
