//! The fuzz target bodies (`ingest::fuzzing`) over a few thousand deterministic mutations of the
//! fixtures: none may panic. Bounded in time (each format stops after its budget).

use crate::common;

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::time::{Duration, Instant};

use common::fixtures;
use ingest::fuzzing::{self, mutate, Rng};

fn run(name: &str, bases: &[Vec<u8>], target: fn(&[u8]), n: usize, budget: Duration) -> usize {
    let t0 = Instant::now();
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15 ^ name.len() as u64);
    let mut done = 0;
    // the unmodified bases and fixed truncation points first
    for b in bases {
        for cut in [0, 1, 7, 8, 16, 64, 512, b.len() / 3, b.len() / 2, b.len().saturating_sub(1), b.len()] {
            let d = &b[..cut.min(b.len())];
            if catch_unwind(AssertUnwindSafe(|| target(d))).is_err() {
                panic!("{name}: panic on a truncation at {cut} bytes");
            }
            done += 1;
        }
    }
    for i in 0..n {
        if t0.elapsed() > budget {
            break;
        }
        let base = &bases[i % bases.len()];
        let m = mutate(base, &mut rng);
        if catch_unwind(AssertUnwindSafe(|| target(&m))).is_err() {
            let p = std::env::temp_dir().join(format!("ingest-fuzz-{name}-{i}.bin"));
            let _ = std::fs::write(&p, &m);
            panic!("{name}: panic on mutation {i} (input saved to {})", p.display());
        }
        done += 1;
    }
    eprintln!("{name}: {done} inputs in {:.1} s, no panic", t0.elapsed().as_secs_f64());
    done
}

fn quiet_panics() {
    // keep the output readable: a panic fails the test anyway
    let _ = std::panic::take_hook();
    std::panic::set_hook(Box::new(|info| eprintln!("panic: {info}")));
}

#[test]
fn robomimic_mutations_never_panic() {
    quiet_panics();
    let f = fixtures();
    let bases = vec![std::fs::read(f.join("robomimic/lift_rollouts_lowdim.hdf5")).unwrap()];
    let n = run("robomimic", &bases, fuzzing::robomimic_bytes, 4000, Duration::from_secs(8));
    assert!(n > 100);
}

#[test]
fn mcap_mutations_never_panic() {
    quiet_panics();
    let f = fixtures();
    let mut bases = Vec::new();
    for n in ["json_eval.mcap", "ros2_jointstate_eval.mcap", "protobuf_eval.mcap", "truncated.mcap"] {
        bases.push(std::fs::read(f.join("mcap").join(n)).unwrap());
    }
    for e in std::fs::read_dir(f.join("mcap/conformance")).unwrap() {
        let p = e.unwrap().path();
        if p.extension().and_then(|x| x.to_str()) == Some("mcap") {
            bases.push(std::fs::read(p).unwrap());
        }
    }
    let n = run("mcap", &bases, fuzzing::mcap_bytes, 8000, Duration::from_secs(8));
    assert!(n > 100);
}

#[test]
fn lerobot_mutations_never_panic() {
    quiet_panics();
    let f = fixtures();
    let mut bases = Vec::new();
    for ds in ["v30_eval_video", "v30_unlabeled"] {
        let info = std::fs::read(f.join("lerobot").join(ds).join("meta/info.json")).unwrap();
        let pq = std::fs::read(f.join("lerobot").join(ds).join("data/chunk-000/file-000.parquet")).unwrap();
        let mut b = info;
        b.push(0);
        b.extend(pq);
        bases.push(b);
    }
    let info = std::fs::read(f.join("lerobot/v21_eval_video/meta/info.json")).unwrap();
    let pq = std::fs::read(f.join("lerobot/v21_eval_video/data/chunk-000/episode_000000.parquet")).unwrap();
    let mut b = info;
    b.push(0);
    b.extend(pq);
    bases.push(b);
    // the good inputs are read fully
    let (i, p) = bases[0].split_at(bases[0].iter().position(|&x| x == 0).unwrap());
    assert_eq!(ingest::lerobot::fuzz_entry(i, &p[1..]).unwrap(), 519);
    let n = run("lerobot", &bases, fuzzing::lerobot_bytes, 5000, Duration::from_secs(8));
    assert!(n > 100);
}

#[test]
fn lerobot_eval_mutations_never_panic() {
    quiet_panics();
    let f = fixtures().join("lerobot_eval");
    let mut bases = Vec::new();
    for (run, video) in
        [("v04/ckpt-a", "videos/pusht_0/eval_episode_2.mp4"), ("v03/ckpt-b", "videos/eval_episode_0.mp4")]
    {
        let mut b = std::fs::read(f.join(run).join("eval_info.json")).unwrap();
        b.push(0);
        b.extend(std::fs::read(f.join(run).join(video)).unwrap());
        bases.push(b);
    }
    // the good inputs are read fully
    let (i, p) = bases[0].split_at(bases[0].iter().position(|&x| x == 0).unwrap());
    let (episodes, frames) = ingest::lerobot_eval::fuzz_entry(i, &p[1..]);
    assert_eq!((episodes.unwrap(), frames.unwrap()), (8, 7));
    let n = run("lerobot_eval", &bases, fuzzing::lerobot_eval_bytes, 5000, Duration::from_secs(6));
    assert!(n > 100);
}

#[test]
fn cdr_mutations_never_panic() {
    quiet_panics();
    let schema = b"std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[3] fixed\nint8[<=4] bounded\nbuiltin_interfaces/Time t\n================================================================================\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n================================================================================\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n".to_vec();
    let mut msg = vec![0u8, 1, 0, 0];
    msg.extend([1, 0, 0, 0, 2, 0, 0, 0, 3, 0, 0, 0, b'a', b'b', 0, 0]);
    msg.extend([1, 0, 0, 0, 2, 0, 0, 0, b'x', 0, 0, 0]);
    msg.extend([1, 0, 0, 0]);
    msg.extend(1.5f64.to_le_bytes());
    for _ in 0..3 {
        msg.extend(2.5f64.to_le_bytes());
    }
    msg.extend([2, 0, 0, 0, 7, 8, 0, 0, 5, 0, 0, 0, 6, 0, 0, 0]);
    let mut b = schema;
    b.push(0);
    b.extend(msg);
    let n = run("cdr", &[b], fuzzing::cdr_bytes, 3000, Duration::from_secs(4));
    assert!(n > 100);
}
