//! The integration-test binary: real files, real archives, real rendered focal stacks.

mod bundle_reader;
mod common;
mod depth;
mod layers;
mod numeric_props;
mod pipeline;
mod reader_props;
mod service;
mod simulator;
