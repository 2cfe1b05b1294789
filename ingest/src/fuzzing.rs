//! Fuzz target bodies, as plain functions so that `cargo test` can run them over deterministic
//! mutations and `cargo fuzz` (ingest/fuzz/) over random ones. Each must never panic: any input
//! gives `Ok` or an error.

use std::path::Path;

use crate::options::ReadOptions;
use crate::sink::CountSink;

/// A robomimic HDF5 file's bytes.
pub fn robomimic_bytes(data: &[u8]) {
    let mut sink = CountSink::default();
    let _ = crate::robomimic::read_bytes(
        Path::new("fuzz.hdf5"),
        data.to_vec(),
        &ReadOptions::default(),
        &mut sink,
    );
}

/// A LeRobot `info.json` and a data Parquet file: the input is split at the first NUL byte
/// (before: info.json; after: parquet). Without a NUL, all bytes are tried as both.
pub fn lerobot_bytes(data: &[u8]) {
    let (info, pq) = match data.iter().position(|&b| b == 0) {
        Some(i) => (&data[..i], &data[i + 1..]),
        None => (data, data),
    };
    let _ = crate::lerobot::parse_info(Path::new("fuzz/meta/info.json"), info);
    let _ = crate::lerobot::fuzz_entry(info, pq);
}

/// A lerobot-eval `eval_info.json` and one of its MP4 videos, split at the first NUL byte (before:
/// the JSON; after: the MP4). Without a NUL, all bytes are tried as both.
pub fn lerobot_eval_bytes(data: &[u8]) {
    let (info, mp4) = match data.iter().position(|&b| b == 0) {
        Some(i) => (&data[..i], &data[i + 1..]),
        None => (data, data),
    };
    let _ = crate::lerobot_eval::fuzz_entry(info, mp4);
}

/// An MCAP file's bytes (read with the default mapping, and scanned).
pub fn mcap_bytes(data: &[u8]) {
    let mut sink = CountSink::default();
    let p = Path::new("fuzz.mcap");
    let _ = crate::mcapfmt::read(p, &mut &data[..], data.len() as u64, &ReadOptions::default(), &mut sink);
    let opts = ReadOptions { recover: true, ..Default::default() };
    let _ = crate::mcapfmt::read(p, &mut &data[..], data.len() as u64, &opts, &mut sink);
    let _ = crate::mcapfmt::scan(p, &mut &data[..], data.len() as u64);
}

/// A ros2msg schema text + CDR payload, split at the first NUL.
pub fn cdr_bytes(data: &[u8]) {
    let (schema, msg) = match data.iter().position(|&b| b == 0) {
        Some(i) => (&data[..i], &data[i + 1..]),
        None => (data, &[][..]),
    };
    if let Ok(text) = std::str::from_utf8(schema) {
        if let Ok(s) = crate::ros2msg::parse_schema("fuzz/msg/Top", text) {
            let _ = crate::ros2msg::decode_cdr(&s, msg);
        }
    }
}

/// A tiny deterministic PRNG (xorshift64*) for mutation tests.
pub struct Rng(pub u64);

impl Rng {
    pub fn next_u64(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        self.0 = x;
        x.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    pub fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            0
        } else {
            (self.next_u64() % n as u64) as usize
        }
    }
}

/// One deterministic mutation of `base`: bit flips, byte overwrites, truncation, duplication of
/// a slice, or an "interesting" integer written somewhere.
pub fn mutate(base: &[u8], rng: &mut Rng) -> Vec<u8> {
    let mut v = base.to_vec();
    if v.is_empty() {
        return v;
    }
    let ops = 1 + rng.below(4);
    for _ in 0..ops {
        match rng.below(6) {
            0 => {
                let i = rng.below(v.len());
                v[i] ^= 1 << rng.below(8);
            }
            1 => {
                let i = rng.below(v.len());
                v[i] = rng.next_u64() as u8;
            }
            2 => {
                let n = rng.below(v.len());
                v.truncate(n.max(1));
            }
            3 => {
                let i = rng.below(v.len());
                let vals: [u64; 6] = [0, 1, 0xff, 0xffff_ffff, u64::MAX, 0x7fff_ffff_ffff_ffff];
                let x = vals[rng.below(vals.len())].to_le_bytes();
                let w = [1usize, 2, 4, 8][rng.below(4)];
                for (k, b) in x.iter().take(w).enumerate() {
                    if i + k < v.len() {
                        v[i + k] = *b;
                    }
                }
            }
            4 => {
                let i = rng.below(v.len());
                let n = rng.below(64.min(v.len() - i) + 1);
                let s = v[i..i + n].to_vec();
                let j = rng.below(v.len());
                v.splice(j..j, s);
            }
            _ => {
                let i = rng.below(v.len());
                let n = rng.below(64.min(v.len() - i) + 1);
                v.drain(i..i + n);
                if v.is_empty() {
                    v.push(0);
                }
            }
        }
    }
    v
}
