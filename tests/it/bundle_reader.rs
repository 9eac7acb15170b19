use crate::common::Scratch;
#[test]
fn placeholder_compiles() { let _ = Scratch::new(); }
