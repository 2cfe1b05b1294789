//! `ufops ingest` says what it left out on `warning:` lines (no Rust debug strings), and
//! `ufops export` writes LeRobot v3.0 / robomimic exports, refuses what it cannot write with one
//! clear line and a non-zero exit, and leaves nothing behind then.

mod common;
use common::*;

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

#[test]
fn ingest_prints_labels_and_warnings_in_words() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(&dir.path().join("store"));
    let f = fixtures();
    // Every labeled episode of a recording where two have no action messages.
    let out = t.run(&["ingest", f.join("mcap/ros2_no_actions_eval.mcap").to_str().unwrap(), "--policy", "p", "--checkpoint", "c"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let stdout = text(&out.stdout);
    assert!(stdout.contains("5 episodes") && stdout.contains("labels: 3 success, 2 failure, 0 unknown"), "{stdout}");
    assert!(!stdout.contains("LabelCounts") && !stdout.contains('{'), "{stdout}");
    assert!(!text(&out.stderr).contains("warning"), "{}", text(&out.stderr));
    // A truncated recording ingested with --recover: what was left out, one warning per line.
    let out = t.run(&["ingest", f.join("mcap/truncated.mcap").to_str().unwrap(), "--policy", "p", "--checkpoint", "c2", "--recover"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let stderr = text(&out.stderr);
    let warnings: Vec<&str> = stderr.lines().filter(|l| l.starts_with("warning: ")).collect();
    assert!(warnings.iter().any(|w| w.contains("truncated MCAP") && w.contains("complete episodes: 0, 1, 2")), "{stderr}");
    assert!(!stderr.contains("note:"), "{stderr}");
}

#[test]
fn export_writes_lerobot_and_robomimic_and_refuses_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(&dir.path().join("store"));
    let f = fixtures();
    t.ok(&["ingest", f.join("lerobot/v30_eval_video").to_str().unwrap(), "--policy", "act", "--checkpoint", "last"]);
    let ds = dir.path().join("ds");
    let stdout = t.ok(&["export", ds.to_str().unwrap(), "--format", "lerobot", "--label", "success"]);
    assert!(stdout.contains("exported 4 episodes") && stdout.contains("labels: 4 success, 0 failure, 0 unknown"), "{stdout}");
    let info: serde_json::Value = serde_json::from_slice(&std::fs::read(ds.join("meta/info.json")).unwrap()).unwrap();
    assert_eq!(info["total_episodes"], 4);
    assert!(ds.join("videos/observation.images.front/chunk-000/file-000.mp4").is_file());
    // The JSON report, a robomimic file of the same version.
    let h5 = dir.path().join("all.hdf5");
    let rep = t.json(&["export", h5.to_str().unwrap(), "--format", "robomimic", "--json"]);
    assert_eq!(rep["episodes"], 8);
    assert!(rep["warnings"][0].as_str().unwrap().contains("video"), "{rep}");
    assert!(h5.is_file());

    // Refusals: one line on stderr, non-zero exit, nothing written.
    for (args, want) in [
        (vec!["export", ds.to_str().unwrap(), "--format", "lerobot"], "already exists"),
        (vec!["export", dir.path().join("x").to_str().unwrap(), "--format", "csv"], "expected lerobot or robomimic"),
        (vec!["export", dir.path().join("y").to_str().unwrap(), "--format", "lerobot", "--policy", "nobody"], "no episodes"),
        (vec!["export", dir.path().join("z").to_str().unwrap(), "--format", "lerobot", "--version", "99"], "version"),
    ] {
        let out = t.run(&args);
        let err = text(&out.stderr);
        assert!(!out.status.success(), "{args:?}");
        assert!(err.starts_with("error: ") && err.contains(want) && err.lines().count() == 1, "{args:?}: {err}");
    }
    // Episodes without actions cannot be a LeRobot dataset: refused, no folder left behind.
    t.ok(&["ingest", f.join("mcap/ros2_no_actions_eval.mcap").to_str().unwrap(), "--policy", "p", "--checkpoint", "c"]);
    let out = t.run(&["export", dir.path().join("mcap").to_str().unwrap(), "--format", "lerobot", "--policy", "p"]);
    assert!(!out.status.success());
    assert!(text(&out.stderr).contains("no actions"), "{}", text(&out.stderr));
    let left: Vec<String> = std::fs::read_dir(dir.path()).unwrap().flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect();
    assert!(!left.iter().any(|n| n == "mcap" || n.contains(".tmp-")), "{left:?}");
}
