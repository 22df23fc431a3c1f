//! Open-vocabulary semantic segmentation: how well text queries find labelled classes, in 3D
//! (a map against labelled ground-truth points) and in 2D (an encoder's pixel embeddings against
//! label images).
//!
//! - [`classes`]: the NYU40 and ScanNet20 class lists (the `other*` classes are not evaluated).
//! - [`ground_truth`]: labelled 3D points from labelled RGB-D frames (back-projection and a
//!   majority vote per voxel), for any dataset with label images.
//! - [`sweep`]: the paper's IoU averaged over the full range of similarity thresholds.
//! - [`vlem`]: the paper's 3D protocol (nearest map point within 5 cm, threshold sweep).
//! - [`rayfronts`]: the RayFronts protocol (softmax over the class prompts, prompt denoising,
//!   5 cm voxels, k-nearest-neighbour votes, IoU, f-mIoU and accuracy).
//! - [`image`]: the paper's 2D protocol (threshold sweep over pixels of every n-th frame).
//! - [`scores`]: what they report.

pub mod classes;
pub mod ground_truth;
pub mod image;
pub mod rayfronts;
pub mod scores;
pub mod sweep;
pub mod vlem;

pub use classes::{Class, ClassIndex, ClassList};
pub use ground_truth::{GroundTruth, GroundTruthBuilder};
pub use scores::{ClassScore, SemsegScores};
pub use sweep::ThresholdSweep;
