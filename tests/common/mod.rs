//! Helpers for the end-to-end tests: run the real `ufops` binary against a store.
#![allow(dead_code)]

pub mod seaweedfs;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

pub fn bin() -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_ufops"))
}

/// A store location: a data dir and optionally a Postgres catalog.
#[derive(Clone)]
pub struct Target {
    pub data_dir: PathBuf,
    pub database_url: Option<String>,
    /// `s3://bucket/prefix` (with `env` holding the endpoint and keys); None: the local directory.
    pub object_store: Option<String>,
    pub env: Vec<(&'static str, String)>,
}

impl Target {
    pub fn sqlite(dir: &Path) -> Target {
        Target { data_dir: dir.to_path_buf(), database_url: None, object_store: None, env: Vec::new() }
    }

    pub fn command(&self) -> Command {
        let mut c = Command::new(bin());
        c.arg("--data-dir").arg(&self.data_dir);
        if let Some(u) = &self.database_url {
            c.arg("--database-url").arg(u);
        }
        c.env_remove("UFOPS_DATABASE_URL").env_remove("UFOPS_OBJECT_STORE").env("CI", "true");
        if let Some(o) = &self.object_store {
            c.arg("--object-store").arg(o);
        }
        c.envs(self.env.iter().map(|(k, v)| (*k, v.as_str())));
        c
    }

    pub fn run(&self, args: &[&str]) -> Output {
        self.command().args(args).output().expect("run ufops")
    }

    /// Runs a command that must succeed and returns its stdout parsed as JSON.
    pub fn json(&self, args: &[&str]) -> serde_json::Value {
        let out = self.run(args);
        assert!(
            out.status.success(),
            "ufops {args:?} failed: {}\n{}",
            String::from_utf8_lossy(&out.stderr),
            String::from_utf8_lossy(&out.stdout)
        );
        serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
            panic!("ufops {args:?} printed no JSON ({e}): {}", String::from_utf8_lossy(&out.stdout))
        })
    }

    pub fn ok(&self, args: &[&str]) -> String {
        let out = self.run(args);
        assert!(out.status.success(), "ufops {args:?} failed: {}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8_lossy(&out.stdout).into_owned()
    }
}

/// A store with a Postgres catalog on a fresh schema; None (after a skip notice) when the test
/// Postgres is unreachable and `UFOPS_REQUIRE_POSTGRES` is not set (set: the test fails).
pub fn postgres_target(dir: &Path) -> Option<Target> {
    if !store::test_support::require_postgres() {
        return None;
    }
    let rt = tokio::runtime::Runtime::new().unwrap();
    let url = rt
        .block_on(store::create_test_schema("e2e"))
        .expect("the Postgres tests need the server at 127.0.0.1:5432 (UFOPS_TEST_POSTGRES)");
    Some(Target { data_dir: dir.to_path_buf(), database_url: Some(url), object_store: None, env: Vec::new() })
}

/// Every file under the local object directory, relative to it.
pub fn object_files(data_dir: &Path) -> Vec<String> {
    fn walk(root: &Path, dir: &Path, out: &mut Vec<String>) {
        for e in std::fs::read_dir(dir).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                out.push(p.strip_prefix(root).unwrap().to_string_lossy().into_owned());
            }
        }
    }
    let root = data_dir.join("objects");
    let mut out = Vec::new();
    if root.exists() {
        walk(&root, &root, &mut out);
    }
    out.sort();
    out
}

/// The fixtures: `$UFOPS_FIXTURES`, else the repository's own `fixtures/` (see its README).
pub fn fixtures() -> PathBuf {
    std::env::var("UFOPS_FIXTURES")
        .map(PathBuf::from)
        .unwrap_or_else(|_| Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures"))
}
