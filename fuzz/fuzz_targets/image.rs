#![no_main]
libfuzzer_sys::fuzz_target!(|data: &[u8]| furnace_proto::fuzz::image(data));
