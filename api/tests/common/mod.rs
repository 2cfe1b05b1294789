//! Test support: stores on SQLite and Postgres, synthetic episodes, a fake job runner that
//! "trains" by publishing a tiny artifact and ingests a JSON upload format, an HTTP client.
#![allow(dead_code)]

use api::{JobContext, JobRunner};
use futures::future::BoxFuture;
use serde_json::{json, Value};
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
pub use store::test_support::{episode, source};
use store::*;
use store_artifacts::{Artifacts, NewArtifact};
use store_jobs::JobRecord;

pub mod load;

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Db {
    Sqlite,
    Postgres,
}

pub async fn open_store(db: Db, dir: &Path) -> Store {
    match db {
        Db::Sqlite => Store::open(&StoreConfig::local(dir)).await.unwrap(),
        Db::Postgres => {
            let url = create_test_schema("api")
                .await
                .expect("the Postgres tests need a server (UFOPS_TEST_POSTGRES)");
            Store::open(&StoreConfig {
                data_dir: dir.into(),
                database_url: Some(url),
                object_store_url: None,
            })
            .await
            .unwrap()
        }
    }
}

/// Ingests `n` episodes (alternating success/failure) of `pol/<ckpt>`; returns their ids.
pub async fn ingest(store: &Store, tag: &str, ckpt: &str, n: u32) -> Vec<String> {
    let mut w = store.begin_ingest(source(tag), "pol", ckpt).await.unwrap();
    let mut ids = Vec::new();
    for i in 0..n {
        let label = if i % 2 == 0 { Label::Success } else { Label::Failure };
        ids.push(w.add_episode(episode(i, 5 + i as usize % 4, label)).await.unwrap());
    }
    w.commit("test ingest").await.unwrap();
    ids
}

/// Ingests `n` episodes that all reference one fake video (`media.front`); returns
/// `(episode ids, video bytes)`.
pub async fn ingest_with_video(
    store: &Store,
    dir: &Path,
    tag: &str,
    ckpt: &str,
    n: u32,
) -> (Vec<String>, Vec<u8>) {
    let video: Vec<u8> = (0..100_000u32).map(|i| (i.wrapping_mul(2654435761) >> 13) as u8).collect();
    let vpath = dir.join(format!("{tag}.mp4"));
    std::fs::write(&vpath, &video).unwrap();
    let sha = sha256_hex(&video);
    let mut w = store.begin_ingest(source(tag), "pol", ckpt).await.unwrap();
    w.add_media(&MediaFile {
        sha256: sha.clone(),
        local_path: vpath,
        content_type: "video/mp4".into(),
        size_bytes: video.len() as u64,
    })
    .await
    .unwrap();
    let mut ids = Vec::new();
    for i in 0..n {
        let label = if i % 2 == 0 { Label::Success } else { Label::Failure };
        let mut ep = episode(i, 6, label);
        ep.media = vec![MediaColumn {
            name: "front".into(),
            sha256: sha.clone(),
            timestamps: ep.timestamps.clone(),
        }];
        ids.push(w.add_episode(ep).await.unwrap());
    }
    w.commit("video ingest").await.unwrap();
    (ids, video)
}

/// Writes a tiny but well-formed verifier artifact directory (per trainer/ARTIFACT.md).
pub fn write_fake_artifact(dir: &Path, kind: &str, lineage: Value) {
    std::fs::create_dir_all(dir).unwrap();
    let header = br#"{"head.weight":{"dtype":"F32","shape":[1,2],"data_offsets":[0,8]}}"#;
    let mut weights = (header.len() as u64).to_le_bytes().to_vec();
    weights.extend_from_slice(header);
    weights.extend_from_slice(&1.0f32.to_le_bytes());
    weights.extend_from_slice(&(-1.0f32).to_le_bytes());
    let config = serde_json::to_vec_pretty(&json!({
        "schema_version": 1,
        "kind": kind,
        "architecture": {"variant": "lowdim"},
        "gamma": if kind == "q" { json!(0.99) } else { Value::Null },
        "metrics": {"val_loss": 0.5},
        "lineage": lineage,
    }))
    .unwrap();
    std::fs::write(dir.join("model.safetensors"), &weights).unwrap();
    std::fs::write(dir.join("config.json"), &config).unwrap();
    let manifest = json!({"schema_version": 1, "files": {
        "config.json": sha256_hex(&config), "model.safetensors": sha256_hex(&weights)}});
    std::fs::write(dir.join("manifest.json"), serde_json::to_vec_pretty(&manifest).unwrap()).unwrap();
}

/// One run of a job as the fake runner saw it.
#[derive(Debug, Clone)]
pub struct Run {
    pub job_id: String,
    pub worker: String,
    pub start: Instant,
    pub end: Option<Instant>,
}

/// The fake runner: `train` publishes a fake artifact for the split's checkpoint; `ingest`
/// reads the uploaded JSON (`{"episodes": [{"label": "success", "steps": 6}, ...]}`) into the
/// store; `sleep` just takes `run_ms`. Every run is recorded.
pub struct TestRunner {
    pub run_ms: u64,
    pub runs: Mutex<Vec<Run>>,
    pub tmp: tempfile::TempDir,
}

impl TestRunner {
    pub fn new(run_ms: u64) -> Arc<TestRunner> {
        Arc::new(TestRunner { run_ms, runs: Mutex::new(Vec::new()), tmp: tempfile::tempdir().unwrap() })
    }

    async fn run_job(&self, store: &Store, job: &JobRecord, ctx: JobContext) -> Result<Value, String> {
        let idx = {
            let mut runs = self.runs.lock().unwrap();
            runs.push(Run {
                job_id: job.id.clone(),
                worker: ctx.worker_id.clone(),
                start: Instant::now(),
                end: None,
            });
            runs.len() - 1
        };
        let steps = 5u64;
        for k in 0..steps {
            tokio::time::sleep(Duration::from_millis(self.run_ms / steps)).await;
            ctx.progress(json!({"epoch": k + 1, "train_loss": 1.0 / (k + 1) as f64}));
            if ctx.is_cancelled() {
                return Err("cancelled".into());
            }
        }
        let out = match job.kind {
            store_jobs::JobKind::Train => {
                let split_id = job.spec["split_id"].as_str().ok_or("no split_id")?;
                let kind = job.spec["kind"].as_str().ok_or("no kind")?;
                let split = store.split(split_id).await.map_err(|e| e.to_string())?;
                let dir = self.tmp.path().join(&job.id).join(job.attempts.to_string());
                write_fake_artifact(
                    &dir,
                    kind,
                    json!({"split_id": split.id, "version": split.version, "job": job.id}),
                );
                let a = store
                    .publish_artifact(NewArtifact {
                        dir: &dir,
                        policy: &split.policy,
                        checkpoint: &split.checkpoint,
                        kind,
                        split_id: Some(&split.id),
                        job_id: Some(&job.id),
                    })
                    .await
                    .map_err(|e| e.to_string())?;
                json!({"artifact_id": a.id, "metrics": {"val_loss": 0.5}})
            }
            store_jobs::JobKind::Ingest => {
                let path = job.spec["path"].as_str().ok_or("no path")?;
                let data = std::fs::read(path).map_err(|e| e.to_string())?;
                let doc: Value = serde_json::from_slice(&data).map_err(|e| e.to_string())?;
                let src = SourceInput {
                    path: path.to_string(),
                    sha256: job.spec["sha256"].as_str().ok_or("no sha256")?.to_string(),
                    format: "test-json".into(),
                    size_bytes: data.len() as u64,
                    metadata: json!({}),
                };
                let policy = job.spec["policy"].as_str().ok_or("no policy")?;
                let ckpt = job.spec["checkpoint"].as_str().ok_or("no checkpoint")?;
                let mut w = store.begin_ingest(src, policy, ckpt).await.map_err(|e| e.to_string())?;
                for (i, e) in doc["episodes"].as_array().ok_or("no episodes")?.iter().enumerate() {
                    let label: Label = e["label"]
                        .as_str()
                        .unwrap_or("unknown")
                        .parse()
                        .map_err(|e: StoreError| e.to_string())?;
                    let steps = e["steps"].as_u64().unwrap_or(5) as usize;
                    w.add_episode(episode(i as u32, steps, label)).await.map_err(|e| e.to_string())?;
                }
                let c = w.commit("uploaded").await.map_err(|e| e.to_string())?;
                json!({"version": c.version, "episodes": c.episodes})
            }
            // The other kinds only take their time here (the lease and retry tests use them).
            store_jobs::JobKind::Export | store_jobs::JobKind::Score | store_jobs::JobKind::Scoreboard => {
                json!({"slept_ms": self.run_ms})
            }
        };
        self.runs.lock().unwrap()[idx].end = Some(Instant::now());
        Ok(out)
    }
}

impl JobRunner for TestRunner {
    fn run<'a>(
        &'a self,
        store: &'a Store,
        job: &'a JobRecord,
        ctx: JobContext,
    ) -> BoxFuture<'a, Result<Value, String>> {
        Box::pin(self.run_job(store, job, ctx))
    }
}

/// A server on 127.0.0.1:0 with an in-process worker, and one token per role.
pub struct TestServer {
    pub base: String,
    pub store: Store,
    pub server: Option<api::RunningServer>,
    pub tokens: std::collections::BTreeMap<&'static str, String>,
    pub runner: Arc<TestRunner>,
    pub dir: tempfile::TempDir,
    pub http: reqwest::Client,
}

impl TestServer {
    pub async fn start(db: Db, worker: bool) -> TestServer {
        Self::start_with(db, worker, |_| {}).await
    }

    /// [`TestServer::start`] with the server's configuration adjusted by `adjust`.
    pub async fn start_with(db: Db, worker: bool, adjust: impl FnOnce(&mut api::ServeConfig)) -> TestServer {
        let dir = tempfile::tempdir().unwrap();
        let store = open_store(db, dir.path()).await;
        let runner = TestRunner::new(50);
        let mut cfg = api::ServeConfig::new(dir.path());
        cfg.addr = "127.0.0.1:0".parse().unwrap();
        cfg.run_worker_in_process = worker;
        cfg.worker_lease_ms = 2_000;
        adjust(&mut cfg);
        let server = api::spawn(store.clone(), cfg, runner.clone()).await.unwrap();
        let mut tokens = std::collections::BTreeMap::new();
        for (name, role) in [
            ("viewer", Role::Viewer),
            ("labeler", Role::Labeler),
            ("trainer", Role::Trainer),
            ("admin", Role::Admin),
        ] {
            let (secret, _) = store.create_token(&format!("{name}-user"), role).await.unwrap();
            tokens.insert(name, secret);
        }
        TestServer {
            base: format!("http://{}", server.addr),
            store,
            server: Some(server),
            tokens,
            runner,
            dir,
            http: reqwest::Client::builder().pool_max_idle_per_host(64).build().unwrap(),
        }
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    pub fn req(&self, method: reqwest::Method, path: &str, role: &str) -> reqwest::RequestBuilder {
        self.http.request(method, self.url(path)).bearer_auth(&self.tokens[role])
    }

    pub async fn get_json(&self, path: &str, role: &str) -> Value {
        let r = self.req(reqwest::Method::GET, path, role).send().await.unwrap();
        let status = r.status();
        let body = r.text().await.unwrap();
        assert!(status.is_success(), "GET {path}: {status} {body}");
        serde_json::from_str(&body).unwrap()
    }

    /// Polls a job until it leaves queued/running.
    pub async fn wait_job(&self, id: &str) -> Value {
        let t0 = Instant::now();
        loop {
            let j = self.get_json(&format!("/v1/jobs/{id}"), "viewer").await;
            let st = j["state"].as_str().unwrap().to_string();
            if st != "queued" && st != "running" {
                return j;
            }
            assert!(t0.elapsed() < Duration::from_secs(30), "job {id} stuck: {j}");
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    pub async fn stop(mut self) {
        if let Some(s) = self.server.take() {
            s.shutdown().await.unwrap();
        }
    }
}
