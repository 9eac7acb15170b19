//! The integration-test binary: real files, real archives, real rendered focal stacks.

mod bundle_reader;
mod common;
mod reader_props;
mod simulator;
