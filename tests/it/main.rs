//! The integration-test binary: real files, real archives, real rendered focal stacks.

mod budget;
mod bundle_reader;
mod common;
mod depth;
mod fuzz_corpus;
#[path = "../../fuzz/src/lib.rs"]
mod fuzz_targets;
mod layers;
mod learned;
mod numeric_props;
mod pipeline;
mod qualify_cli;
mod reader_props;
mod readme;
mod service;
mod simulator;
