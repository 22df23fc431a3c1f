//! The shared encoder conformance suite of `vlem-testkit`, run on the colour-names encoder.
#![cfg(feature = "colour-names")]

use vlem_plugin_colour_names::ColourNamesEncoder;

// The encoder embeds only colour words, so the suite gets one it understands.
vlem_testkit::encoder_conformance!(|| Box::new(ColourNamesEncoder::default()), text = "red");
