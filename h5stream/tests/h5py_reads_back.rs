//! A property test of the writer against h5py: random group trees holding random datasets (every
//! number type, ranks 0-3, empty ones, fixed-length ASCII strings; some written in one call,
//! some a random slice at a time) and random attributes on groups and datasets (every number
//! type, scalar or 1-D; fixed- and variable-length strings, ASCII or UTF-8, scalar or 1-D;
//! UTF-8 names), read back with h5py and compared exactly (`h5py_check.py`: dtypes, shapes, the
//! values' bytes, string kinds and widths). Seeds 0-49, fixed: a failure names its seed and
//! reproduces.
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "tests: a failed unwrap is a failed test, and a scenario reads top to bottom"
)]

use std::path::{Path, PathBuf};

use evalstats::splitmix::SplitMix64;
use h5stream::{Attr, Element, Group, StrKind, Writer};
use serde_json::{json, Map, Value};

const CASES: u64 = 50;

/// The seeded generator of every case (evalstats' SplitMix64), with the draws the trees need.
struct Rng(SplitMix64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0.next_u64()
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
    fn chance(&mut self, percent: u64) -> bool {
        self.below(100) < percent
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// `n` values of `T` from random bits (every bit pattern: NaNs and infinities among the floats).
fn values<T: Element>(rng: &mut Rng, n: usize, from_bits: fn(u64) -> T) -> Vec<T> {
    (0..n).map(|_| from_bits(rng.next())).collect()
}

/// The numpy dtype string h5py reads for a number type of `size` bytes.
fn np_dtype(kind: char, size: usize) -> String {
    format!("{}{kind}{size}", if size == 1 { '|' } else { '<' })
}

/// A random name: ASCII mostly, sometimes UTF-8; unique among `taken`.
fn name(rng: &mut Rng, taken: &mut Vec<String>) -> String {
    const PARTS: [&str; 12] = ["a", "b", "obs", "qpos", "_", "7", "cam", "é", "日本", "x-y", " ", "Z"];
    loop {
        let n = 1 + rng.below(4);
        let s: String = (0..n).map(|_| PARTS[rng.below(PARTS.len() as u64) as usize]).collect();
        if !taken.contains(&s) {
            taken.push(s.clone());
            return s;
        }
    }
}

/// A random string; sometimes, when it goes to the global heap (`heap`: a variable-length one),
/// one longer than a heap collection (a fixed-length one that long would pass the 64 KiB an
/// object header message holds, which the writer refuses).
fn string(rng: &mut Rng, ascii: bool, heap: bool) -> String {
    const ASCII: [&str; 6] = ["a", "B", "0", " ", "{\"k\": 1}", "long string "];
    const UTF8: [&str; 3] = ["é", "日本語", "ü"];
    if heap && rng.chance(3) {
        // Past one 64 KiB heap collection.
        return "y".repeat(70_000 + rng.below(100) as usize);
    }
    let n = rng.below(6);
    (0..n)
        .map(|_| {
            if !ascii && rng.chance(30) {
                UTF8[rng.below(3) as usize]
            } else {
                ASCII[rng.below(6) as usize]
            }
        })
        .collect()
}

/// A random attribute and what h5py should read for it.
fn attribute(rng: &mut Rng) -> (Attr, Value) {
    let array = rng.chance(50);
    let len = if array { rng.below(6) as usize } else { 1 };
    let shape = if array { json!([len]) } else { json!([]) };
    macro_rules! num {
        ($t:ty, $kind:expr, $from:expr) => {{
            let v: Vec<$t> = values(rng, len, $from);
            let mut bytes = Vec::new();
            <$t as Element>::put(&v, &mut bytes);
            let a = if array { Attr::numbers(&v) } else { Attr::number(v[0]) };
            let d = json!({"type": "num", "dtype": np_dtype($kind, std::mem::size_of::<$t>()),
                           "shape": shape, "hex": hex(&bytes)});
            (a, d)
        }};
    }
    match rng.below(16) {
        0 => num!(i8, 'i', |b| b as i8),
        1 => num!(i16, 'i', |b| b as i16),
        2 => num!(i32, 'i', |b| b as i32),
        3 => num!(i64, 'i', |b| b as i64),
        4 => num!(u8, 'u', |b| b as u8),
        5 => num!(u16, 'u', |b| b as u16),
        6 => num!(u32, 'u', |b| b as u32),
        7 => num!(u64, 'u', |b| b),
        8 => num!(f32, 'f', |b| f32::from_bits(b as u32)),
        9 => num!(f64, 'f', f64::from_bits),
        10 => {
            let v = rng.next() as i64;
            (Attr::I64(v), json!({"type": "num", "dtype": "<i8", "shape": [], "hex": hex(&v.to_le_bytes())}))
        }
        11 => {
            let v = f64::from_bits(rng.next());
            (Attr::F64(v), json!({"type": "num", "dtype": "<f8", "shape": [], "hex": hex(&v.to_le_bytes())}))
        }
        12 => {
            let s = string(rng, false, true);
            let d = json!({"type": "str", "kind": "var_utf8", "width": null, "shape": [], "values": [s]});
            (Attr::Str(s), d)
        }
        _ => {
            let (kind, label, ascii) = match rng.below(4) {
                0 => (StrKind::FixedUtf8, "fixed_utf8", false),
                1 => (StrKind::FixedAscii, "fixed_ascii", true),
                2 => (StrKind::VarUtf8, "var_utf8", false),
                _ => (StrKind::VarAscii, "var_ascii", true),
            };
            let heap = matches!(kind, StrKind::VarUtf8 | StrKind::VarAscii);
            let v: Vec<String> = (0..len).map(|_| string(rng, ascii, heap)).collect();
            let width = match kind {
                StrKind::FixedUtf8 | StrKind::FixedAscii => {
                    json!(v.iter().map(String::len).max().unwrap_or(0).max(1))
                }
                _ => Value::Null,
            };
            let d = json!({"type": "str", "kind": label, "width": width, "shape": shape, "values": v});
            let a = if array { Attr::strings(v, kind) } else { Attr::string(&v[0], kind) };
            (a, d)
        }
    }
}

/// Random attributes (unique names) set with `set`, and their descriptions.
fn attributes(rng: &mut Rng, mut set: impl FnMut(&str, Attr)) -> Map<String, Value> {
    let mut out = Map::new();
    let mut taken = Vec::new();
    for _ in 0..rng.below(5) {
        let n = name(rng, &mut taken);
        let (a, d) = attribute(rng);
        set(&n, a);
        out.insert(n, d);
    }
    out
}

/// Writes a random numeric dataset (whole, or a random slice at a time) and returns its address
/// and description.
fn dataset(rng: &mut Rng, w: &mut Writer) -> (u64, Value) {
    let shape: Vec<u64> = if rng.chance(5) {
        // Past the writer's conversion chunk (64 Ki values).
        vec![1000 + rng.below(500), 70 + rng.below(30)]
    } else {
        (0..rng.below(4)).map(|_| rng.below(5)).collect()
    };
    let n = shape.iter().product::<u64>() as usize;
    macro_rules! go {
        ($t:ty, $kind:expr, $from:expr) => {{
            let v: Vec<$t> = values(rng, n, $from);
            let mut bytes = Vec::new();
            <$t as Element>::put(&v, &mut bytes);
            let (at, attrs) = if rng.chance(50) && rng.chance(50) {
                (w.dataset(&shape, &v).unwrap(), Map::new())
            } else {
                let mut d = w.stream::<$t>(&shape).unwrap();
                let mut rest = &v[..];
                while !rest.is_empty() {
                    let k = 1 + rng.below(rest.len() as u64) as usize;
                    d.write(&rest[..k]).unwrap();
                    rest = &rest[k..];
                    if rng.chance(20) {
                        d.write(&[]).unwrap();
                    }
                }
                let attrs = attributes(rng, |k, a| d.attr(k, a));
                (d.finish().unwrap(), attrs)
            };
            let desc = json!({"kind": "dataset", "dtype": np_dtype($kind, std::mem::size_of::<$t>()),
                              "shape": shape, "hex": hex(&bytes), "attrs": attrs});
            (at, desc)
        }};
    }
    match rng.below(11) {
        0 => go!(i8, 'i', |b| b as i8),
        1 => go!(i16, 'i', |b| b as i16),
        2 => go!(i32, 'i', |b| b as i32),
        3 => go!(i64, 'i', |b| b as i64),
        4 => go!(u8, 'u', |b| b as u8),
        5 => go!(u16, 'u', |b| b as u16),
        6 => go!(u32, 'u', |b| b as u32),
        7 => go!(u64, 'u', |b| b),
        8 => go!(f32, 'f', |b| f32::from_bits(b as u32)),
        9 => go!(f64, 'f', f64::from_bits),
        _ => {
            let mut taken = Vec::new();
            let strs: Vec<String> = (0..rng.below(4)).map(|_| name(rng, &mut taken)).collect();
            let strs: Vec<String> = strs.into_iter().map(|s| s.replace(['é', '日', '本'], "e")).collect();
            let refs: Vec<&str> = strs.iter().map(String::as_str).collect();
            let width = strs.iter().map(String::len).max().unwrap_or(0).max(1);
            let mut bytes = vec![0u8; width * strs.len()];
            for (slot, s) in bytes.chunks_mut(width).zip(&strs) {
                slot[..s.len()].copy_from_slice(s.as_bytes());
            }
            let at = w.ascii_strings(&refs).unwrap();
            let desc = json!({"kind": "dataset", "dtype": format!("|S{width}"), "shape": [strs.len()],
                              "hex": hex(&bytes), "attrs": {}});
            (at, desc)
        }
    }
}

/// Writes a random group at `path` (its children first) into `g`; records every object.
fn fill_group(
    rng: &mut Rng,
    w: &mut Writer,
    g: &mut Group,
    path: &str,
    depth: u32,
    objects: &mut Map<String, Value>,
) {
    let children = if rng.chance(10) { 9 + rng.below(4) } else { rng.below(5) };
    let mut taken = Vec::new();
    for _ in 0..children {
        let n = name(rng, &mut taken);
        let child = if path == "/" { format!("/{n}") } else { format!("{path}/{n}") };
        if depth < 3 && rng.chance(35) {
            let mut sub = Group::default();
            fill_group(rng, w, &mut sub, &child, depth + 1, objects);
            g.link(&n, w.group(sub).unwrap());
        } else {
            let (at, desc) = dataset(rng, w);
            g.link(&n, at);
            objects.insert(child, desc);
        }
    }
    let attrs = attributes(rng, |k, a| g.attr(k, a));
    objects.insert(path.to_string(), json!({"kind": "group", "attrs": attrs}));
}

/// Writes the file of `seed` and returns what h5py should read in it.
fn write_case(dir: &Path, seed: u64) -> Value {
    let mut rng = Rng(SplitMix64(seed));
    let file = dir.join(format!("case-{seed}.h5"));
    let mut w = Writer::create(&file).unwrap();
    let mut root = Group::default();
    let mut objects = Map::new();
    fill_group(&mut rng, &mut w, &mut root, "/", 0, &mut objects);
    w.finish(root).unwrap();
    json!({"file": file, "seed": seed, "objects": objects})
}

#[test]
fn h5py_reads_back_random_files_exactly() {
    if !store::test_support::require_python(&["h5py", "numpy"]) {
        return;
    }
    let started = std::time::Instant::now();
    let dir = tempfile::tempdir().unwrap();
    let cases: Vec<Value> = (0..CASES).map(|seed| write_case(dir.path(), seed)).collect();
    let expected = dir.path().join("expected.json");
    std::fs::write(&expected, serde_json::to_vec(&cases).unwrap()).unwrap();
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/h5py_check.py");
    let out = std::process::Command::new("python3").arg(script).arg(&expected).output().unwrap();
    assert!(
        out.status.success(),
        "h5py read back something else:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!("{} in {:.1} s", String::from_utf8_lossy(&out.stdout).trim(), started.elapsed().as_secs_f64());
}
