//! The vlem-testkit segmenter conformance suite for every segmenter of this crate.

use vlem_core::Segmenter;
use vlem_query::segmenters::{ArgmaxSegmenter, ClusterSegmenter, ThresholdSegmenter};

mod threshold {
    use super::*;

    fn build() -> Box<dyn Segmenter> {
        Box::new(ThresholdSegmenter::default())
    }

    vlem_testkit::segmenter_conformance!(build);
}

mod argmax {
    use super::*;

    fn build() -> Box<dyn Segmenter> {
        Box::new(ArgmaxSegmenter::default())
    }

    vlem_testkit::segmenter_conformance!(build);
}

mod cluster {
    use super::*;

    fn build() -> Box<dyn Segmenter> {
        Box::new(ClusterSegmenter::default())
    }

    vlem_testkit::segmenter_conformance!(build);
}
