//! Label load test: 64 concurrent labelers updating overlapping episodes over loopback HTTP with
//! If-Match (retrying on 409) for 20 s on SQLite (and Postgres with `--postgres`), then a replay
//! of the audit log that must reproduce every episode's final label and revision. The server runs
//! in its own process (this benchmark started again with `--serve-child`), so the clients' work
//! is not counted against it; `--in-process` runs both in one process as the test does.
//!
//! `cargo bench -p api --bench label_load [-- --seconds 20 --labelers 64 --episodes 256 --runs 1 --postgres --no-sqlite --in-process --no-feed-follower]`
//!
//! Every run also checks the change feed: a follower long-polls `GET /v1/events` while the
//! labelers write (`--no-feed-follower`: it reads the feed once at the end), and every
//! acknowledged write must be in it exactly once, in commit order.
//!
//! Each run prints its figures with the machine's load average (the box is shared: other
//! processes' CPU use moves the figures); with `--runs N` the medians are printed at the end.
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "benchmarks: a failed unwrap is a failed run, and a measurement reads top to bottom"
)]

#[path = "../tests/common/mod.rs"]
mod common;

use common::load::{run_label_load_at, LoadReport, ServerAt};
use common::Db;
use std::time::Duration;

fn loadavg() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "n/a".into())
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

/// The server half: `--serve-child DATA_DIR [DATABASE_URL]` serves that store on a free loopback
/// port, prints `listening on URL` and runs until killed.
fn serve_child(args: &[String]) {
    let dir = std::path::PathBuf::from(&args[0]);
    let cfg = store::StoreConfig {
        data_dir: dir.clone(),
        database_url: args.get(1).cloned(),
        object_store_url: None,
    };
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build().unwrap();
    rt.block_on(async move {
        let store = store::Store::open(&cfg).await.unwrap();
        let mut sc = api::ServeConfig::new(&dir);
        sc.addr = "127.0.0.1:0".parse().unwrap();
        sc.run_worker_in_process = false;
        api::serve(store, sc, common::TestRunner::new(50), std::future::pending()).await.unwrap();
    });
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if let Some(i) = args.iter().position(|a| a == "--serve-child") {
        return serve_child(&args[i + 1..]);
    }
    let at = if args.iter().any(|a| a == "--in-process") {
        ServerAt::InProcess
    } else {
        ServerAt::Child(std::env::current_exe().expect("this benchmark's path"))
    };
    let arg = |name: &str, default: u64| -> u64 {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1))
            .and_then(|v| v.parse().ok())
            .unwrap_or(default)
    };
    let seconds = arg("--seconds", 20);
    let labelers = arg("--labelers", 64) as usize;
    let episodes = arg("--episodes", 256) as usize;
    let runs = arg("--runs", 1).max(1) as usize;
    // By default a follower long-polls the change feed during the load (as a webhook deliverer
    // or `ufops events --follow` would); with this flag the feed is only read at the end.
    let follow = !args.iter().any(|a| a == "--no-feed-follower");
    let mut dbs = Vec::new();
    if !args.iter().any(|a| a == "--no-sqlite") {
        dbs.push(Db::Sqlite);
    }
    if args.iter().any(|a| a == "--postgres") {
        dbs.push(Db::Postgres);
    }
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build().unwrap();
    for db in dbs {
        let mut reports: Vec<LoadReport> = Vec::new();
        for run in 1..=runs {
            let before = loadavg();
            let r = rt.block_on(run_label_load_at(
                db,
                &at,
                labelers,
                episodes,
                Duration::from_secs(seconds),
                follow,
            ));
            print!("run {run}/{runs} (load average before: {before}, after: {}): ", loadavg());
            r.print();
            reports.push(r);
        }
        let w = median(reports.iter().map(|r| r.writes_per_s()).collect());
        let p50 = median(reports.iter().map(|r| r.p50_ms).collect());
        let p99 = median(reports.iter().map(|r| r.p99_ms).collect());
        println!("{db:?}: median of {runs} run(s): {w:.0} writes/s, p50 {p50:.2} ms, p99 {p99:.2} ms");
        if db == Db::Sqlite {
            let goal = w >= 2000.0 && p99 <= 20.0;
            println!(
                "goal (>= 2000 writes/s, p99 <= 20 ms on SQLite): {}",
                if goal { "met" } else { "NOT met on this machine" }
            );
        }
    }
}
