//! Test support for every crate's tests (hidden from the docs): tests that need an external tool
//! (Python packages, SeaweedFS, Postgres, a browser) ask [`require`] first. A missing tool is a
//! failure when its switch (`UFOPS_REQUIRE_PYTHON`, `_S3`, `_POSTGRES`, `_BROWSER`) is set, as
//! `scripts/test.sh` does; otherwise the test is skipped with a notice nobody can miss.

use std::io::Write;
use std::net::{TcpStream, ToSocketAddrs};
use std::process::Command;
use std::time::Duration;

/// An external tool some tests need.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Tool {
    /// python3 with the interop packages (numpy, pyarrow, duckdb, safetensors, ...).
    Python,
    /// The SeaweedFS `weed` binary (the S3 server of the scale-out tests).
    S3,
    /// The Postgres server of the tests ([`crate::test_postgres_base`]).
    Postgres,
    /// Chromium, node and playwright-core (the labeling page's browser test).
    Browser,
}

impl Tool {
    /// The env switch that turns a missing tool into a failure.
    pub fn switch(self) -> &'static str {
        match self {
            Tool::Python => "UFOPS_REQUIRE_PYTHON",
            Tool::S3 => "UFOPS_REQUIRE_S3",
            Tool::Postgres => "UFOPS_REQUIRE_POSTGRES",
            Tool::Browser => "UFOPS_REQUIRE_BROWSER",
        }
    }

    fn how_to_get(self) -> &'static str {
        match self {
            Tool::Python | Tool::S3 => {
                "`python3 -m pip install -r tests/python/requirements.txt` (scripts/test.sh does it)"
            }
            Tool::Postgres => {
                "a Postgres server at 127.0.0.1:5432 with database `test` and trust auth, or \
                 UFOPS_TEST_POSTGRES=postgres://USER@HOST:PORT/DB (`source scripts/env.sh && ensure_postgres` starts a local one)"
            }
            Tool::Browser => "`source scripts/env.sh && ensure_browser` installs them",
        }
    }

    /// Whether the switch is set (to anything but empty or `0`).
    pub fn required(self) -> bool {
        std::env::var(self.switch()).is_ok_and(|v| !v.is_empty() && v != "0")
    }
}

/// `true`: the tool is there, run the test. When `probe` says what is missing: panics if the
/// tool's switch is set, else prints a skip notice (straight to stderr, which the test harness
/// does not capture) and returns `false` — the caller then returns.
pub fn require(tool: Tool, probe: Result<(), String>) -> bool {
    match verdict(tool, tool.required(), probe) {
        Verdict::Run => true,
        Verdict::Fail(msg) => panic!("{msg}"),
        Verdict::Skip(msg) => {
            let bar = "!".repeat(78);
            let _ = writeln!(std::io::stderr(), "\n{bar}\n!! SKIPPED {msg}\n{bar}\n");
            false
        }
    }
}

#[derive(Debug, PartialEq)]
enum Verdict {
    Run,
    Skip(String),
    Fail(String),
}

fn verdict(tool: Tool, required: bool, probe: Result<(), String>) -> Verdict {
    let Err(missing) = probe else { return Verdict::Run };
    let test = std::thread::current().name().filter(|n| *n != "main").unwrap_or("this test").to_string();
    let msg = format!("{test} needs {missing}; to get it: {}", tool.how_to_get());
    if required {
        Verdict::Fail(format!("{msg} ({}=1: a missing tool is a failure)", tool.switch()))
    } else {
        Verdict::Skip(format!(
            "{msg}\n!! (scripts/test.sh sets {}=1, which makes this a failure)",
            tool.switch()
        ))
    }
}

/// [`require`] for python3 able to import every module in `modules`.
pub fn require_python(modules: &[&str]) -> bool {
    require(Tool::Python, python_modules(modules))
}

/// [`require`] for the tests' Postgres server.
pub fn require_postgres() -> bool {
    require(Tool::Postgres, postgres_reachable())
}

/// A store in `dir` on `db`: its SQLite catalog there, or a fresh Postgres schema named after
/// `schema_prefix` (the test Postgres must answer: callers that may skip ask [`require_postgres`]
/// first).
pub async fn open_test_store(db: crate::Backend, dir: &std::path::Path, schema_prefix: &str) -> crate::Store {
    let database_url = match db {
        crate::Backend::Sqlite => None,
        crate::Backend::Postgres => {
            Some(crate::create_test_schema(schema_prefix).await.expect("the Postgres tests need a server"))
        }
    };
    let cfg = crate::StoreConfig { data_dir: dir.into(), database_url, object_store_url: None };
    crate::Store::open(&cfg).await.expect("open the test store")
}

/// Ok when `python3` imports every module in `modules`.
pub fn python_modules(modules: &[&str]) -> Result<(), String> {
    let what = format!("python3 with {}", modules.join(", "));
    let code = modules.iter().map(|m| format!("import {m}")).collect::<Vec<_>>().join("; ");
    match Command::new("python3").args(["-c", &code]).output() {
        Err(e) => Err(format!("{what} (cannot run python3: {e})")),
        Ok(o) if !o.status.success() => {
            let err = String::from_utf8_lossy(&o.stderr);
            Err(format!("{what} ({})", err.lines().last().unwrap_or("import failed").trim()))
        }
        Ok(_) => Ok(()),
    }
}

/// Ok when something accepts TCP connections at the test Postgres URL's host and port (a wrong
/// database or role still fails the test itself, with the server's message).
pub fn postgres_reachable() -> Result<(), String> {
    let url = crate::test_postgres_base();
    let addr = host_port(&url);
    let what = format!("the Postgres server at {addr}");
    let addrs =
        addr.to_socket_addrs().map_err(|e| format!("{what} (cannot resolve: {e})"))?.collect::<Vec<_>>();
    let mut last = String::from("no address");
    for a in addrs {
        match TcpStream::connect_timeout(&a, Duration::from_secs(2)) {
            Ok(_) => return Ok(()),
            Err(e) => last = e.to_string(),
        }
    }
    Err(format!("{what} ({last})"))
}

/// `host:port` of a `postgres://user:pw@host:port/db?opts` URL (port 5432 when absent).
fn host_port(url: &str) -> String {
    let rest = url.split_once("://").map_or(url, |(_, r)| r);
    let authority = rest.split(['/', '?']).next().unwrap_or("");
    let host = authority.rsplit_once('@').map_or(authority, |(_, h)| h);
    let host = if host.is_empty() { "localhost" } else { host };
    // `[::1]:5433`, `[::1]`, `db:5433`, `db`
    let has_port = host.rsplit_once(':').is_some_and(|(h, p)| {
        !p.is_empty() && p.bytes().all(|b| b.is_ascii_digit()) && (!h.contains(':') || h.ends_with(']'))
    });
    if has_port {
        host.to_string()
    } else {
        format!("{host}:5432")
    }
}

/// Observation keys and widths of the synthetic Square-sized rollouts (robomimic's low-dim Square).
pub const SQUARE_OBS: [(&str, usize); 4] =
    [("object", 14), ("robot0_eef_pos", 3), ("robot0_eef_quat", 4), ("robot0_gripper_qpos", 2)];
/// Action width of the synthetic Square-sized rollouts.
pub const SQUARE_ACTION: usize = 7;

/// A synthetic Square-sized rollout for benchmarks: 150–400 steps of smooth signals with a
/// little seeded noise, one in three a failure. The same `i` gives the same episode.
pub fn square_rollout(i: u32) -> crate::EpisodeInput {
    let mut rng = (i as u64).wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
    let mut noise = move || {
        rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((rng >> 33) as f32 / (1u64 << 31) as f32 - 0.5) * 0.01
    };
    let steps = 150 + (i as usize * 7919) % 251;
    let phase = i as f32 * 0.37;
    let mut observations = Vec::new();
    for (k, (name, dim)) in SQUARE_OBS.iter().enumerate() {
        let mut values = Vec::with_capacity(steps * dim);
        for t in 0..steps {
            for d in 0..*dim {
                let x = t as f32 / steps as f32;
                values.push((x * (1.0 + d as f32) + phase + k as f32).sin() * 0.5 + noise());
            }
        }
        observations.push(crate::VectorColumn { name: name.to_string(), dim: *dim, values });
    }
    let action = crate::VectorColumn {
        name: "action".into(),
        dim: SQUARE_ACTION,
        values: (0..steps * SQUARE_ACTION)
            .map(|k| {
                ((k % SQUARE_ACTION) as f32 * 0.1 + (k / SQUARE_ACTION) as f32 * 0.02 + phase).cos() + noise()
            })
            .collect(),
    };
    let success = !i.is_multiple_of(3);
    let label = if success { crate::Label::Success } else { crate::Label::Failure };
    crate::EpisodeInput {
        task: Some("square".into()),
        label_source: "bench".into(),
        tags: vec![],
        metadata: serde_json::json!({}),
        timestamps: (0..steps).map(|t| t as f64 * 0.05).collect(),
        observations,
        action,
        reward: (0..steps).map(|t| if success && t + 1 == steps { 1.0 } else { 0.0 }).collect(),
        ..episode(i, steps, label)
    }
}

/// The test episode every crate's tests build on: `demo_<i>` of task `reach`, `steps` steps at
/// 10 Hz, a 2-D `pos` observation whose values say which episode and step they are
/// (`k + 1000·i`), a constant 3-D action, no reward, done on the last step, tag `eval` and
/// metadata `{"i": i}`. A test that needs other columns overrides them with struct update
/// syntax: `EpisodeInput { observations: …, ..test_support::episode(i, steps, label) }`.
pub fn episode(i: u32, steps: usize, label: crate::Label) -> crate::EpisodeInput {
    crate::EpisodeInput {
        source_name: format!("demo_{i}"),
        source_index: i,
        task: Some("reach".into()),
        label,
        label_source: "test".into(),
        tags: vec!["eval".into()],
        metadata: serde_json::json!({ "i": i }),
        timestamps: (0..steps).map(|t| t as f64 / 10.0).collect(),
        observations: vec![crate::VectorColumn {
            name: "pos".into(),
            dim: 2,
            values: (0..steps * 2).map(|k| (k as f32) + i as f32 * 1000.0).collect(),
        }],
        action: crate::VectorColumn { name: "action".into(), dim: 3, values: vec![0.5; steps * 3] },
        reward: vec![0.0; steps],
        done: (0..steps).map(|t| t + 1 == steps).collect(),
        action_chunk: None,
        images: vec![],
        media: vec![],
        flags: Default::default(),
    }
}

/// The source of test episodes named `tag` (path `/tmp/<tag>`, hashed by its name, format `test`).
pub fn source(tag: &str) -> crate::SourceInput {
    crate::SourceInput {
        path: format!("/tmp/{tag}"),
        sha256: crate::sha256_hex(tag.as_bytes()),
        format: "test".into(),
        size_bytes: 1,
        metadata: serde_json::json!({}),
    }
}

/// A two-step [`episode`] (one-dimensional observation and action) for catalog tests, where only
/// the episode's identity, task and label matter.
pub fn two_step_episode(i: u32, task: Option<&str>, label: crate::Label) -> crate::EpisodeInput {
    crate::EpisodeInput {
        task: task.map(str::to_string),
        tags: vec![],
        metadata: serde_json::json!({}),
        observations: vec![crate::VectorColumn { name: "pos".into(), dim: 1, values: vec![0.0, 1.0] }],
        action: crate::VectorColumn { name: "action".into(), dim: 1, values: vec![0.0, 1.0] },
        reward: vec![0.0, 1.0],
        ..episode(i, 2, label)
    }
}

/// A global allocator that counts the live heap and its high-water mark, every thread's: a test
/// binary that checks memory bounds installs it (`#[global_allocator] static A: CountingAlloc =
/// CountingAlloc;`) and runs its tests one at a time.
pub struct CountingAlloc;

static HEAP_LIVE: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
static HEAP_PEAK: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

fn heap_grew(by: usize) {
    use std::sync::atomic::Ordering::Relaxed;
    let now = HEAP_LIVE.fetch_add(by, Relaxed) + by;
    HEAP_PEAK.fetch_max(now, Relaxed);
}

// SAFETY: every call is forwarded to the system allocator unchanged; only counters move.
#[allow(unsafe_code, reason = "a global allocator is an unsafe trait")]
unsafe impl std::alloc::GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: std::alloc::Layout) -> *mut u8 {
        // SAFETY: the caller's layout, forwarded unchanged.
        let p = unsafe { std::alloc::System.alloc(layout) };
        if !p.is_null() {
            heap_grew(layout.size());
        }
        p
    }
    unsafe fn alloc_zeroed(&self, layout: std::alloc::Layout) -> *mut u8 {
        // SAFETY: the caller's layout, forwarded unchanged.
        let p = unsafe { std::alloc::System.alloc_zeroed(layout) };
        if !p.is_null() {
            heap_grew(layout.size());
        }
        p
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: std::alloc::Layout) {
        // SAFETY: `ptr` came from this allocator (the system's) with this layout.
        unsafe { std::alloc::System.dealloc(ptr, layout) };
        HEAP_LIVE.fetch_sub(layout.size(), std::sync::atomic::Ordering::Relaxed);
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: std::alloc::Layout, new_size: usize) -> *mut u8 {
        // SAFETY: `ptr` came from this allocator (the system's) with this layout.
        let p = unsafe { std::alloc::System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            HEAP_LIVE.fetch_sub(layout.size(), std::sync::atomic::Ordering::Relaxed);
            heap_grew(new_size);
        }
        p
    }
}

/// The peak heap growth, in bytes above what was live when it started, while `f` runs (with
/// [`CountingAlloc`] installed; 0 without it).
pub fn peak_heap_while<T>(f: impl FnOnce() -> T) -> (usize, T) {
    use std::sync::atomic::Ordering::Relaxed;
    let before = HEAP_LIVE.load(Relaxed);
    HEAP_PEAK.store(before, Relaxed);
    let out = f();
    (HEAP_PEAK.load(Relaxed).saturating_sub(before), out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn postgres_host_and_port() {
        assert_eq!(host_port("postgres://postgres@127.0.0.1:5432/test"), "127.0.0.1:5432");
        assert_eq!(host_port("postgres://u:p%40w@db.example/x?sslmode=disable"), "db.example:5432");
        assert_eq!(host_port("postgresql://[::1]:5433/test"), "[::1]:5433");
        assert_eq!(host_port("postgres:///test"), "localhost:5432");
    }

    #[test]
    fn missing_tool_skips_or_fails_by_its_switch() {
        assert_eq!(verdict(Tool::S3, true, Ok(())), Verdict::Run);
        let Verdict::Skip(msg) = verdict(Tool::S3, false, Err("the weed binary".into())) else { panic!() };
        assert!(msg.contains("needs the weed binary") && msg.contains("UFOPS_REQUIRE_S3=1"), "{msg}");
        let Verdict::Fail(msg) = verdict(Tool::S3, true, Err("the weed binary".into())) else { panic!() };
        assert!(msg.contains("needs the weed binary") && msg.contains("requirements.txt"), "{msg}");
        // libtest names each test's thread after the test
        assert!(
            msg.contains("missing_tool_skips_or_fails_by_its_switch") || msg.starts_with("this test"),
            "{msg}"
        );
    }
}
