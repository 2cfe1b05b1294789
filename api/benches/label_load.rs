//! Label load test: 64 concurrent labelers updating overlapping episodes over loopback HTTP with
//! If-Match (retrying on 409) for 20 s on SQLite (and Postgres with `--postgres`), then a replay
//! of the audit log that must reproduce every episode's final label and revision.
//!
//! `cargo bench -p api --bench label_load [-- --seconds 20 --labelers 64 --episodes 256 --postgres]`

#[path = "../tests/common/mod.rs"]
mod common;

use common::load::run_label_load;
use common::Db;
use std::time::Duration;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let arg = |name: &str, default: u64| -> u64 {
        args.iter().position(|a| a == name).and_then(|i| args.get(i + 1)).and_then(|v| v.parse().ok()).unwrap_or(default)
    };
    let seconds = arg("--seconds", 20);
    let labelers = arg("--labelers", 64) as usize;
    let episodes = arg("--episodes", 256) as usize;
    let mut dbs = vec![Db::Sqlite];
    if args.iter().any(|a| a == "--postgres") {
        dbs.push(Db::Postgres);
    }
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build().unwrap();
    for db in dbs {
        let r = rt.block_on(run_label_load(db, labelers, episodes, Duration::from_secs(seconds)));
        r.print();
        if db == Db::Sqlite {
            let goal = r.writes_per_s() >= 2000.0 && r.p99_ms <= 20.0;
            println!(
                "goal (>= 2000 writes/s, p99 <= 20 ms on SQLite): {}",
                if goal { "met" } else { "NOT met on this machine" }
            );
        }
    }
}
