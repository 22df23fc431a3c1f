//! What an evaluation reports: per-class IoU and the means over classes.

use serde::Serialize;

use super::classes::Class;
use super::sweep::ThresholdSweep;

/// The IoU of one class.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ClassScore {
    /// NYU40 id.
    pub id: u16,
    /// Name.
    pub name: String,
    /// IoU in `[0, 1]`; `None` when the class is absent from the ground truth.
    pub iou: Option<f64>,
    /// Ground-truth elements (points, voxels or pixels) of the class.
    pub support: u64,
}

/// Per-class IoUs and their summaries.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SemsegScores {
    /// One entry per evaluated class, in class-list order.
    pub classes: Vec<ClassScore>,
    /// Mean IoU over the classes present in the ground truth; `None` when none is.
    pub miou: Option<f64>,
    /// Frequency-weighted mean IoU (RayFronts protocol only).
    pub fmiou: Option<f64>,
    /// Fraction of ground-truth elements given their class (RayFronts protocol only).
    pub accuracy: Option<f64>,
}

impl SemsegScores {
    /// The scores of a threshold sweep over `classes` (the sweep's class `i` is `classes[i]`).
    pub fn from_sweep(sweep: &ThresholdSweep, classes: &[Class]) -> Self {
        let classes: Vec<ClassScore> = classes
            .iter()
            .enumerate()
            .map(|(i, c)| ClassScore {
                id: c.id,
                name: c.name.clone(),
                iou: sweep.class_iou(i),
                support: sweep.support(i),
            })
            .collect();
        Self {
            miou: mean_present(&classes),
            classes,
            fmiou: None,
            accuracy: None,
        }
    }

    /// Number of classes with an IoU (present in the ground truth).
    pub fn evaluated_classes(&self) -> usize {
        self.classes.iter().filter(|c| c.iou.is_some()).count()
    }
}

/// The mean of the IoUs that exist (a NaN-mean); `None` when there are none.
pub fn mean_present(classes: &[ClassScore]) -> Option<f64> {
    let present: Vec<f64> = classes.iter().filter_map(|c| c.iou).collect();
    (!present.is_empty()).then(|| present.iter().sum::<f64>() / present.len() as f64)
}
