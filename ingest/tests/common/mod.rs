#![allow(dead_code)]
use std::path::PathBuf;

/// The fixtures: `$UFOPS_FIXTURES`, else the repository's own `fixtures/` (see its README).
pub fn fixtures() -> PathBuf {
    if let Ok(p) = std::env::var("UFOPS_FIXTURES") {
        return PathBuf::from(p);
    }
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../fixtures")
}

pub fn expected(rel: &str) -> serde_json::Value {
    let p = fixtures().join(rel);
    serde_json::from_str(&std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display())))
        .unwrap()
}
