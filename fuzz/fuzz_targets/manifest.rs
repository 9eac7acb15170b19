#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| crestscan_fuzz::manifest(data));
