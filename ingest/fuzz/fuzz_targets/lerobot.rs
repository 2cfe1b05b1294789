#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    // The parquet crate still panics on some corrupt pages; the reader catches those (they become
    // errors naming the file). libfuzzer-sys aborts on *any* panic, caught or not, so let panics
    // raised inside the parquet/arrow crates unwind to the reader's catch_unwind; any other panic
    // (ours) still aborts and is reported.
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| {
        let abort_hook = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            let upstream = info
                .location()
                .map(|l| l.file().contains("/parquet-") || l.file().contains("/arrow-"))
                .unwrap_or(false);
            if !upstream {
                abort_hook(info);
            }
        }));
    });
    ingest::fuzzing::lerobot_bytes(data);
});
