#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    ingest::fuzzing::lerobot_eval_bytes(data);
});
