//! The labeling web page end to end in real headless Chromium: a temp store with the LeRobot
//! v3.0 video fixture ingested (labels reset to unknown: a labeling campaign) and the v3.0
//! fixture without video, two labelers' tokens, `ufops serve` on a free loopback port, then
//! `node tests/web/label_e2e.mjs` (playwright-core driving Debian's `chromium`): sign in, label
//! three episodes with the keyboard only, auto-advance, a conflict from a second session resolved,
//! bulk labels, the low-dim view, and a robomimic file with two image cameras (generated with
//! h5py: both cameras shown, loaded frame by frame as the timeline moves, screenshot
//! `robomimic_cameras.png`). The labels are then checked through the HTTP API. The second
//! test does the same for the scoreboard page (`tests/web/scoreboard_e2e.mjs`), the third the
//! verifier-ordered review queue and its score on the timeline (`tests/web/review_e2e.mjs`).
//!
//! The harness (prerequisites, running a script, screenshots) is `common::browser`.

use crate::common::browser::{self, api};
use crate::common::{self, Target};
use serde_json::Value;
use std::process::Command;
use std::time::Duration;

/// The two cameras of [`write_robomimic_images`]'s file, stored as `kind`.
fn two_cameras(kind: &str) -> Vec<(String, String)> {
    ["agentview_image", "robot0_eye_in_hand_image"]
        .iter()
        .map(|c| (c.to_string(), kind.to_string()))
        .collect()
}

/// A robomimic rollout file with two image observations (`agentview_image`,
/// `robot0_eye_in_hand_image`, 84×84 RGB, drawn so that every step differs), written with h5py
/// the way robomimic writes its files: 2 demos of `steps` steps, low-dim `robot0_eef_pos`.
fn write_robomimic_images(path: &std::path::Path, steps: usize) {
    let code = r#"
import json, sys
import h5py, numpy as np
path, T = sys.argv[1], int(sys.argv[2])
with h5py.File(path, "w") as f:
    data = f.create_group("data")
    data.attrs["env_args"] = json.dumps({"env_name": "Lift", "type": 1, "env_kwargs": {"control_freq": 20}})
    data.attrs["total"] = 2 * T
    for d in range(2):
        g = data.create_group(f"demo_{d}")
        g.attrs["num_samples"] = T
        t = np.arange(T)
        g.create_dataset("actions", data=np.stack([np.sin(t / 9 + d), np.cos(t / 7), np.sin(t / 5) * 0.5,
                                                   np.zeros(T), np.zeros(T), np.zeros(T), np.sign(np.sin(t / 11))], 1))
        g.create_dataset("rewards", data=np.zeros(T))
        g.create_dataset("dones", data=(t == T - 1).astype(np.int64))
        o = g.create_group("obs")
        o.create_dataset("robot0_eef_pos", data=np.stack([np.cos(t / 20), np.sin(t / 20), t / T], 1))
        agent = np.zeros((T, 84, 84, 3), np.uint8)
        agent[..., 2] = 90 + 40 * d
        hand = np.full((T, 84, 84, 3), 60, np.uint8)
        yy, xx = np.mgrid[0:84, 0:84]
        for k in range(T):
            x = int(4 + (k * 3) % 64)
            agent[k, 30:50, x:x + 16] = (230, 40, 40)        # the red cube slides along
            agent[k, 78:84, : max(1, 84 * (k + 1) // T)] = (40, 220, 80)  # time bar
            r = 6 + (k * 2) % 30
            hand[k][(yy - 42) ** 2 + (xx - 42) ** 2 < r * r] = (240, 210, 40)  # the gripper's view zooms
            hand[k, : (k % 84) + 1, 0:4] = (255, 255, 255)
        o.create_dataset("agentview_image", data=agent)
        o.create_dataset("robot0_eye_in_hand_image", data=hand)
"#;
    let out = Command::new("python3")
        .args(["-c", code, path.to_str().unwrap(), &steps.to_string()])
        .output()
        .expect("run python3");
    assert!(out.status.success(), "writing the robomimic file: {}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn labeling_page_in_headless_chromium() {
    if !browser::available() {
        return;
    }
    let fixtures = common::fixtures().join("lerobot");
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    let video = fixtures.join("v30_eval_video");
    let lowdim = fixtures.join("v30_unlabeled");
    t.json(&[
        "ingest",
        video.to_str().unwrap(),
        "--policy",
        "toy-dp",
        "--checkpoint",
        "step-80000",
        "--json",
    ]);
    t.json(&["ingest", lowdim.to_str().unwrap(), "--policy", "lowdim", "--checkpoint", "c0", "--json"]);
    // Image cameras: a robomimic file with two image observations (PNG columns in the store).
    let image_steps = 300;
    let images = store::test_support::require_python(&["h5py", "numpy"]).then(|| {
        let h5 = dir.path().join("lift_two_cameras.hdf5");
        write_robomimic_images(&h5, image_steps);
        t.json(&[
            "ingest",
            h5.to_str().unwrap(),
            "--policy",
            "robomimic-img",
            "--checkpoint",
            "c0",
            "--json",
        ]);
        "robomimic-img"
    });
    // The campaign: the video episodes' labels are reset to unknown for people to judge.
    let eps = t.json(&["episodes", "--policy", "toy-dp", "--json"]);
    let eps = eps.as_array().expect("episode list");
    assert_eq!(eps.len(), 8, "the v3.0 video fixture has 8 episodes");
    for e in eps {
        t.ok(&[
            "label",
            e["id"].as_str().unwrap(),
            "unknown",
            "--actor",
            "campaign",
            "--note",
            "to be judged by people",
        ]);
    }
    let admin = t.token("admin", "admin");
    let alice = t.token("alice", "labeler");
    let bob = t.token("bob", "labeler");
    let srv = t.serve(&["--no-worker"]);

    // The page and its assets are served from the binary, with types and cache headers.
    let (st, _) = api(&srv, "GET", "/", "", None);
    assert_eq!(st, 303, "GET / redirects to the page");
    let (st, _) = api(&srv, "GET", "/ui/", "", None);
    assert_eq!(st, 200, "GET /ui/");
    let (st, _) = api(&srv, "GET", "/ui/nope.js", "", None);
    assert_eq!(st, 404);

    if images.is_some() {
        // The episode lists both image cameras; a frame is a PNG, cached for good.
        let (_, page) = api(&srv, "GET", "/v1/episodes?policy=robomimic-img", &admin, None);
        let id = page["episodes"][0]["id"].as_str().expect("an image episode").to_string();
        let (st, d) = api(&srv, "GET", &format!("/v1/episodes/{id}"), &admin, None);
        assert_eq!(st, 200, "{d}");
        assert_eq!(browser::cameras(&d), two_cameras("image"), "{d}");
        let (st, _) = api(&srv, "GET", &format!("/v1/episodes/{id}/frames/agentview_image/3"), &admin, None);
        assert_eq!(st, 200);
        let (st, v) = api(
            &srv,
            "GET",
            &format!("/v1/episodes/{id}/frames/agentview_image/{image_steps}"),
            &admin,
            None,
        );
        assert_eq!(st, 404, "past the last step: {v}");
    }
    browser::forget_screenshot("robomimic_cameras.png");
    let result = browser::run_script(
        "label_e2e.mjs",
        &srv.url,
        &[
            ("UFOPS_TOKEN_A", alice),
            ("UFOPS_TOKEN_B", bob),
            ("UFOPS_IMAGE_POLICY", images.unwrap_or("").to_string()),
            ("UFOPS_IMAGE_STEPS", image_steps.to_string()),
        ],
    );
    if images.is_some() {
        let c = &result["image_cameras"];
        assert_eq!(c["cameras"], 2, "{c}");
        // On demand: a window around the frames shown, never the episode's every frame.
        let fetched = c["frame_requests"].as_u64().unwrap();
        assert!(fetched > 0 && fetched < 2 * image_steps as u64 / 2, "{fetched} frame requests: {c}");
        browser::assert_screenshot("robomimic_cameras.png");
    }

    // Every label the browser set, checked through the API.
    let labeled = result["labeled"].as_array().expect("labeled");
    assert!(labeled.len() >= 6, "3 keyboard + 1 conflict + 2 bulk: {labeled:?}");
    for l in labeled {
        let id = l["episode_id"].as_str().unwrap();
        let (st, v) = api(&srv, "GET", &format!("/v1/episodes/{id}"), &admin, None);
        assert_eq!(st, 200, "{v}");
        assert_eq!(v["episode"]["label"], l["label"], "episode {id}: {v}");
        assert_eq!(v["episode"]["label_source"], "human");
        assert_eq!(
            v["episode"]["label_actor"], "alice",
            "episode {id}: the signed-in user's name is on the label"
        );
    }
    // The conflict: bob's failure, then alice's success applied knowingly over it.
    let c = &result["conflict"];
    let id = c["episode_id"].as_str().expect("conflict episode");
    let (_, v) = api(&srv, "GET", &format!("/v1/episodes/{id}"), &admin, None);
    let hist: Vec<(String, String)> = v["history"]
        .as_array()
        .unwrap()
        .iter()
        .map(|h| (h["actor"].as_str().unwrap().to_string(), h["new_label"].as_str().unwrap().to_string()))
        .collect();
    let n = hist.len();
    assert!(n >= 3, "{hist:?}");
    assert_eq!(hist[n - 2], ("bob".to_string(), "failure".to_string()), "{hist:?}");
    assert_eq!(hist[n - 1], ("alice".to_string(), "success".to_string()), "{hist:?}");
    // Nothing else was touched: the remaining video episodes are still unknown.
    let (_, page) = api(&srv, "GET", "/v1/episodes?policy=toy-dp&label=unknown", &admin, None);
    assert_eq!(page["episodes"].as_array().unwrap().len(), 8 - labeled.len(), "{page}");

    println!(
        "labeling speed: keyboard actions per labeled episode {}; verdict key -> next episode playable: \
         in-page median {:.0} ms max {:.0} ms, wall-clock (playwright) median {} ms max {} ms",
        result["keyboard_actions_per_labeled_episode"],
        result["advance_in_page_ms"]["median"].as_f64().unwrap_or(f64::NAN),
        result["advance_in_page_ms"]["max"].as_f64().unwrap_or(f64::NAN),
        result["advance_wall_ms"]["median"],
        result["advance_wall_ms"]["max"],
    );
}

/// The robomimic file's two cameras stored as H.264 video (`ufops ingest --images video`): the
/// episode lists them as video cameras, a frame is served decoded (PNG) by the frames route, and
/// `tests/web/video_e2e.mjs` checks that Debian's Chromium decodes and plays the codec (the
/// pixels drawn from each video are the file's), screenshot `robomimic_video_cameras.png`.
#[test]
fn robomimic_video_cameras_in_headless_chromium() {
    if !browser::available() {
        return;
    }
    if !store::test_support::require_python(&["h5py", "numpy"]) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    let steps = 120;
    let h5 = dir.path().join("lift_two_cameras.hdf5");
    write_robomimic_images(&h5, steps);
    let r = t.json(&[
        "ingest",
        h5.to_str().unwrap(),
        "--policy",
        "robomimic-vid",
        "--checkpoint",
        "c0",
        "--images",
        "video",
        "--json",
    ]);
    assert_eq!(r["media_files"], 4, "one video per episode and camera: {r}");
    let admin = t.token("admin", "admin");
    let alice = t.token("alice", "labeler");
    let srv = t.serve(&["--no-worker"]);
    let (_, page) = api(&srv, "GET", "/v1/episodes?policy=robomimic-vid", &admin, None);
    let id = page["episodes"][0]["id"].as_str().expect("an episode").to_string();
    let (st, d) = api(&srv, "GET", &format!("/v1/episodes/{id}"), &admin, None);
    assert_eq!(st, 200, "{d}");
    assert_eq!(browser::cameras(&d), two_cameras("video"), "{d}");
    let (st, v) = api(&srv, "GET", &format!("/v1/episodes/{id}/frames/agentview_image/7"), &admin, None);
    assert_eq!(st, 200, "a video camera's frame, decoded: {v}");
    let (st, v) =
        api(&srv, "GET", &format!("/v1/episodes/{id}/frames/agentview_image/{steps}"), &admin, None);
    assert_eq!(st, 404, "past the last step: {v}");

    browser::forget_screenshot("robomimic_video_cameras.png");
    let result = browser::run_script(
        "video_e2e.mjs",
        &srv.url,
        &[("UFOPS_TOKEN", alice), ("UFOPS_POLICY", "robomimic-vid".to_string())],
    );
    assert_eq!(result["cameras"], 2, "{result}");
    browser::assert_screenshot("robomimic_video_cameras.png");
}

/// The scoreboard page (`/ui/scoreboard.html`) in headless Chromium: synthetic evaluation runs of
/// policy `synth` (a base run and two steered ones of checkpoint c1, a base run of c2, episodes
/// without a run, a few labels taken back to unknown and frozen; the steered runs name a
/// classifier trained on the base run), a viewer signs in, the page draws every row with its
/// interval bars and the verifier's reliability diagram, its CSV and JSON links return the same
/// rows, a second baseline is chosen; `tests/web/scoreboard_e2e.mjs` writes `scoreboard.png` to the artifacts
/// directory. The rows the page shows are checked against `ufops scoreboard --format json`.
#[test]
fn scoreboard_page_in_headless_chromium() {
    if !browser::available() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    let synth =
        |ckpt: &str, seed: &str, n: &str, rate: &str, run: Option<(&str, &str)>, artifact: Option<&str>| {
            let mut args = vec![
                "dev",
                "synth",
                "--policy",
                "synth",
                "--checkpoint",
                ckpt,
                "--seed",
                seed,
                "--episodes",
                n,
                "--steps",
                "20",
                "--success-rate",
                rate,
            ];
            if let Some((name, steering)) = run {
                args.extend(["--run", name, "--steering", steering]);
            }
            if let Some(a) = artifact {
                args.extend(["--run-artifact", a]);
            }
            t.ok(&args);
        };
    synth("c1", "1", "120", "0.5", Some(("base", "base")), None);
    // A classifier trained on the base run: its quality on the split's held-out episodes is what
    // the page's verifier column and calibration plot show.
    t.train("synth", "c1", "classifier", r#"{"epochs": 3, "chunk_len": 16}"#, &[]);
    let arts = t.json(&["artifacts", "--policy", "synth", "--json"]);
    let art = arts[0]["id"].as_str().unwrap().to_string();
    assert!(
        arts[0]["config"]["metrics"]["final"]["val_calibration"]["ece"].is_number(),
        "{}",
        arts[0]["config"]["metrics"]
    );
    // A failure monitor calibrated from it: the verifier column shows its held-out figures.
    let monitor = t.json(&["monitor", "calibrate", "--artifact", &art, "--alpha", "0.25", "--json"]);
    synth("c1", "2", "120", "0.9", Some(("c-bon10", "bon:10")), Some(&art));
    synth("c1", "3", "60", "0.55", Some(("c-cg3", "cg:3")), Some(&art));
    synth("c2", "4", "60", "0.6", Some(("base", "base")), None);
    synth("c2", "5", "20", "0.7", None, None);
    let eps = t.json(&["episodes", "--policy", "synth", "--checkpoint", "c1", "--json"]);
    for e in eps.as_array().unwrap().iter().take(6) {
        t.ok(&["label", e["id"].as_str().unwrap(), "unknown"]);
    }
    t.ok(&["snapshot"]);
    // A protected alias moved to the steered run on a decided comparison (the page lists it).
    t.ok(&["alias", "move", "--policy", "synth", "--alias", "prod", "--to", "c1/base", "--protect"]);
    t.ok(&["alias", "move", "--policy", "synth", "--alias", "prod", "--to", "c1/c-bon10"]);
    let want = t.json(&["scoreboard", "--policy", "synth", "--format", "json"]);
    let viewer = t.token("vera", "viewer");
    let srv = t.serve(&["--no-worker"]);
    let (st, _) = api(&srv, "GET", "/ui/scoreboard.html", "", None);
    assert_eq!(st, 200, "the scoreboard page is served");
    browser::forget_screenshot("scoreboard.png");
    let result = browser::run_script("scoreboard_e2e.mjs", &srv.url, &[("UFOPS_TOKEN", viewer)]);
    browser::assert_screenshot("scoreboard.png");

    // The page's rows are the store's: same runs and checkpoints, same counts and intervals.
    let want = want["rows"].as_array().unwrap();
    let shown = result["first"]["rows"].as_array().unwrap();
    assert_eq!(shown.len(), want.len());
    assert_eq!(want.len(), 5, "c1: base, c-bon10, c-cg3; c2: base, no run");
    let pct = |x: &Value| format!("{:.1}", 100.0 * x.as_f64().unwrap());
    for (s, w) in shown.iter().zip(want) {
        assert_eq!((&s["checkpoint"], &s["run"]), (&w["checkpoint"], &w["run_name"]));
        let cells: Vec<&str> = s["cells"].as_array().unwrap().iter().map(|c| c.as_str().unwrap()).collect();
        let labeled = w["successes"].as_u64().unwrap() + w["failures"].as_u64().unwrap();
        assert_eq!(cells[5], format!("{}/{labeled}", w["successes"]));
        assert_eq!(
            cells[6],
            format!("{}% [{}, {}]", pct(&w["rate"]), pct(&w["wilson_95"][0]), pct(&w["wilson_95"][1]))
        );
        assert_eq!(cells[7], w["unlabeled"].to_string());
        if let Some(b) = w["baseline"].as_object() {
            let pp = |x: &Value| {
                let v = 100.0 * x.as_f64().unwrap();
                format!("{}{v:.1}", if v >= 0.0 { "+" } else { "" })
            };
            let ci = &b["newcombe_95"];
            assert_eq!(cells[8], format!("{} pp [{}, {}]", pp(&b["diff"]), pp(&ci[0]), pp(&ci[1])));
        }
    }
    // Each badge is `ufops compare`'s decision for the row against its baseline (the pooled one:
    // the synthetic runs have one task).
    let mut badges = 0;
    for (s, w) in shown.iter().zip(want) {
        let Some(b) = w["baseline"].as_object() else { continue };
        let (a, bb) = (
            format!("{}/{}", b["checkpoint"].as_str().unwrap(), b["run_name"].as_str().unwrap()),
            format!("{}/{}", w["checkpoint"].as_str().unwrap(), w["run_name"].as_str().unwrap()),
        );
        let out = t.run(&["compare", "--policy", "synth", "--a", &a, "--b", &bb, "--format", "json"]);
        let c: Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(out.status.code(), Some(c["exit_code"].as_i64().unwrap() as i32));
        assert_eq!(s["sequential"], c["pooled"]["decision"], "{a} vs {bb}: {}", s["sequential_text"]);
        badges += 1;
    }
    assert_eq!(badges, 3, "c-bon10, c-cg3 and c2's rows without a run have a baseline");
    let aliases = result["first"]["aliases"].as_array().unwrap();
    assert_eq!(aliases.len(), 1);
    let text = aliases[0]["text"].as_str().unwrap();
    assert!(text.starts_with("prod → c1/c-bon10 (protected)") && text.contains("against c1/base"), "{text}");
    let unlabeled: u64 = want.iter().map(|w| w["unlabeled"].as_u64().unwrap()).sum();
    assert_eq!(unlabeled, 6, "the labels taken back are unlabeled at the snapshot");
    assert_eq!(result["download"]["csv_lines"].as_u64().unwrap() as usize, want.len() + 1);
    // The calibration plot: one reliability diagram for the one verifier, with a point per
    // non-empty bin of its held-out samples.
    let plots = result["first"]["calibration"].as_array().unwrap();
    assert_eq!(plots.len(), 1, "{plots:?}");
    assert_eq!(plots[0]["artifact"], art.as_str());
    let bins = arts[0]["config"]["metrics"]["final"]["val_calibration"]["bins"].as_array().unwrap();
    let nonempty = bins.iter().filter(|b| b["count"].as_u64().unwrap() > 0).count();
    assert_eq!(plots[0]["points"].as_u64().unwrap() as usize, nonempty);
    // The monitor under the verifier's AUROC / ECE, on the two rows steered by its artifact.
    let monitors = result["first"]["monitors"].as_array().unwrap();
    assert_eq!(monitors.len(), 2, "{monitors:?}");
    assert!(monitors.iter().all(|m| m["id"] == monitor["id"]), "{monitors:?}");
    let text = monitors[0]["text"].as_str().unwrap();
    assert!(text.starts_with("alarm α 0.25: false ") && text.contains(" · caught "), "{text}");
    // How much the chunk matters (the trainer's observation-only twin), on the same two rows, as
    // the artifact records it; a flagged verifier says so.
    let s = &arts[0]["config"]["metrics"]["final"]["action_sensitivity"];
    let lines = result["first"]["sensitivity"].as_array().unwrap();
    assert_eq!(lines.len(), 2, "{lines:?}");
    let n = |x: &Value| format!("{:.3}", x.as_f64().unwrap());
    let text = lines[0]["text"].as_str().unwrap();
    assert!(
        text.starts_with(&format!("action {} · obs-only {}", n(&s["action_auc"]), n(&s["obs_only_auc"]))),
        "{text}"
    );
    assert_eq!(lines[0]["flagged"], s["flagged"].to_string().as_str());
    assert_eq!(text.contains("unlikely to steer well"), s["flagged"] == true, "{text}");
}

/// Several labelers in headless Chromium: six synthetic episodes of
/// policy `synth`, all unknown, in a blind campaign needing two labelers, with failure causes.
/// `tests/web/consensus_e2e.mjs` has alice and bob label four of them with the keyboard (bob
/// blind until he votes, one disagreement) and the admin settle the dispute on the page; κ from
/// the API and the page equals κ computed in the script. Checked again here through the API:
/// each episode's label and source, and κ recomputed from the verdicts the script reports.
#[test]
fn consensus_page_in_headless_chromium() {
    if !browser::available() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    t.ok(&[
        "dev",
        "synth",
        "--policy",
        "synth",
        "--checkpoint",
        "c1",
        "--seed",
        "7",
        "--episodes",
        "6",
        "--steps",
        "20",
        "--success-rate",
        "0.5",
    ]);
    let eps = t.json(&["episodes", "--policy", "synth", "--json"]);
    for e in eps.as_array().unwrap() {
        t.ok(&["label", e["id"].as_str().unwrap(), "unknown", "--actor", "campaign"]);
    }
    let admin = t.token("admin", "admin");
    let alice = t.token("alice", "labeler");
    let bob = t.token("bob", "labeler");
    let srv = t.serve(&["--no-worker"]);
    let (st, v) =
        api(&srv, "PUT", "/v1/campaigns/synth", &admin, Some(r#"{"labels_needed": 2, "blind": true}"#));
    assert_eq!(st, 200, "{v}");
    let (st, v) = api(
        &srv,
        "PUT",
        "/v1/tasks/*/failure-causes",
        &admin,
        Some(r#"{"causes": ["missed grasp", "collision", "timeout"]}"#),
    );
    assert_eq!(st, 200, "{v}");

    let result = browser::run_script(
        "consensus_e2e.mjs",
        &srv.url,
        &[("UFOPS_TOKEN_A", alice), ("UFOPS_TOKEN_B", bob), ("UFOPS_TOKEN_ADMIN", admin.clone())],
    );

    let alice_v = result["alice"].as_object().unwrap();
    let bob_v = result["bob"].as_object().unwrap();
    assert_eq!(alice_v.len(), 4);
    let disputed = result["disputed"].as_str().unwrap();
    for (id, a) in alice_v {
        let (st, v) = api(&srv, "GET", &format!("/v1/episodes/{id}"), &admin, None);
        assert_eq!(st, 200, "{v}");
        let (label, source) = (&v["episode"]["label"], &v["episode"]["label_source"]);
        if id == disputed {
            assert_eq!((label.as_str(), source.as_str()), (Some("failure"), Some("adjudication")), "{v}");
        } else {
            assert_eq!(a, &bob_v[id]);
            assert_eq!((label, source.as_str()), (a, Some("consensus")), "{v}");
        }
    }
    let span_ep = result["span_episode"].as_str().unwrap();
    let (_, v) = api(&srv, "GET", &format!("/v1/episodes/{span_ep}"), &admin, None);
    let last = v["history"].as_array().unwrap().last().unwrap().clone();
    assert_eq!(
        last["data"]["spans"][0]["end_step"], 3,
        "the span alice marked is in the label event: {last}"
    );
    // The two episodes nobody labeled are still unknown.
    let (_, page) = api(&srv, "GET", "/v1/episodes?policy=synth&label=unknown", &admin, None);
    assert_eq!(page["episodes"].as_array().unwrap().len(), 2, "{page}");
    // κ once more, from the reported verdicts, against the API.
    let n = alice_v.len() as f64;
    let po = alice_v.iter().filter(|(id, a)| &&bob_v[id.as_str()] == a).count() as f64 / n;
    let share =
        |m: &serde_json::Map<String, Value>, c: &str| m.values().filter(|v| *v == c).count() as f64 / n;
    let pe: f64 = ["success", "failure"].iter().map(|c| share(alice_v, c) * share(bob_v, c)).sum();
    let kappa = (po - pe) / (1.0 - pe);
    let (_, ag) = api(&srv, "GET", "/v1/agreement?policy=synth", &admin, None);
    assert!((ag["pairs"][0]["kappa"].as_f64().unwrap() - kappa).abs() < 1e-12, "{ag} vs {kappa}");
    assert_eq!(
        (ag["agreed"].as_u64(), ag["settled"].as_u64(), ag["disputed"].as_u64()),
        (Some(3), Some(1), Some(0)),
        "{ag}"
    );
    println!(
        "consensus: kappa {kappa:.4} (API {}, page {}), alpha {}",
        result["kappa_api"], result["kappa_page"], ag["krippendorff_alpha"]
    );
}

/// The review queue in the page: the Lift rollouts scored by a trained classifier (a score
/// job through the API), the order selector set to "uncertain first": the page's queue is the
/// API's order, nearest 0.5 first, and the score is plotted on the timeline (screenshot
/// `review-uncertain-score-timeline.png`). Before the score job the same order tells the labeler
/// there are no scores yet and gives the command that stores them, and for a policy with no
/// classifier (`lift-new`) the commands that train one first (`review-no-scores.png`).
#[test]
fn review_queue_in_headless_chromium() {
    if !browser::available() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let t = Target::sqlite(dir.path());
    t.ok(&["init"]);
    common::lift_with_classifier(&t);
    let synth =
        ["--checkpoint", "e0", "--seed", "9", "--episodes", "6", "--steps", "20", "--success-rate", "0.5"];
    t.ok(&[&["dev", "synth", "--policy", "lift-new"][..], &synth[..]].concat());
    let trainer = t.token("curator", "trainer");
    let alice = t.token("alice", "labeler");
    let srv = t.serve(&[]);
    let (st, page) = api(&srv, "GET", "/v1/episodes?policy=bc&order=uncertain&limit=1000", &alice, None);
    assert_eq!(st, 200, "{page}");
    assert!(
        page["review"].as_array().unwrap().iter().all(|r| r["score"].is_null()),
        "not scored yet: {page}"
    );
    browser::forget_screenshot("review-no-scores.png");
    browser::run_script(
        "review_e2e.mjs",
        &srv.url,
        &[("UFOPS_TOKEN_A", alice.clone()), ("UFOPS_UNSCORED", "1".into())],
    );
    browser::assert_screenshot("review-no-scores.png");
    let (st, job) =
        api(&srv, "POST", "/v1/review/score", &trainer, Some(r#"{"policy": "bc", "checkpoint": "e600"}"#));
    assert_eq!(st, 201, "{job}");
    let job_id = job["id"].as_str().unwrap().to_string();
    let t0 = std::time::Instant::now();
    loop {
        let (_, j) = api(&srv, "GET", &format!("/v1/jobs/{job_id}"), &trainer, None);
        match j["state"].as_str() {
            Some("succeeded") => break,
            Some("failed") | Some("cancelled") => panic!("score job: {j}"),
            _ => assert!(t0.elapsed() < Duration::from_secs(120), "score job still running: {j}"),
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    let (st, page) = api(&srv, "GET", "/v1/episodes?policy=bc&order=uncertain&limit=1000", &alice, None);
    assert_eq!(st, 200, "{page}");
    let expect: Vec<&str> =
        page["episodes"].as_array().unwrap().iter().map(|e| e["id"].as_str().unwrap()).collect();
    let scores: Vec<f64> =
        page["review"].as_array().unwrap().iter().map(|r| r["score"].as_f64().unwrap()).collect();
    assert!(scores.windows(2).all(|w| (w[0] - 0.5).abs() <= (w[1] - 0.5).abs()), "{scores:?}");

    browser::run_script(
        "review_e2e.mjs",
        &srv.url,
        &[("UFOPS_TOKEN_A", alice), ("UFOPS_EXPECT", expect.join(","))],
    );
}
