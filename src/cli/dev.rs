//! Hidden developer commands the end-to-end tests drive (e.g. a synthetic writer to kill).

use super::StoreArgs;
use anyhow::Result;
use store::{EpisodeInput, Label, SourceInput, VectorColumn};

#[derive(clap::Subcommand, Debug)]
pub enum DevCommand {
    /// Ingest a synthetic source of random episodes (deterministic for a seed).
    Synth {
        #[arg(long, default_value_t = 10)]
        episodes: u32,
        #[arg(long, default_value_t = 100)]
        steps: usize,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        #[arg(long, default_value = "synth")]
        policy: String,
        #[arg(long, default_value = "ckpt-0")]
        checkpoint: String,
        /// Roll over to a new data file past this many bytes.
        #[arg(long)]
        max_file_bytes: Option<usize>,
        /// The chance of each episode's success label.
        #[arg(long, default_value_t = 0.5)]
        success_rate: f32,
        /// The evaluation run of the episodes (see `ufops ingest --run`).
        #[arg(long)]
        run: Option<String>,
        #[arg(long)]
        steering: Option<String>,
        #[arg(long)]
        run_artifact: Option<String>,
        /// Steering telemetry of the episodes (a sidecar of best-of-N records, as `ufops ingest
        /// --steering-log` takes; `episode_index` i is episode_i).
        #[arg(long, value_name = "FILE")]
        steering_log: Option<std::path::PathBuf>,
    },
    /// Check every visible version: its episodes' steps read back whole, its label snapshot
    /// file matches; prints a JSON report and fails on any problem.
    Verify,
}

pub async fn run(args: &StoreArgs, cmd: DevCommand) -> Result<()> {
    match cmd {
        DevCommand::Synth {
            episodes,
            steps,
            seed,
            policy,
            checkpoint,
            max_file_bytes,
            success_rate,
            run,
            steering,
            run_artifact,
            steering_log,
        } => {
            let store = args.open_or_create().await?;
            let run = super::serve_cmds::run_input(
                run.as_deref(),
                steering.as_deref(),
                run_artifact.as_deref(),
                &[],
            )?;
            let mut key = format!("synth:{seed}:{episodes}:{steps}:{policy}:{checkpoint}");
            if let Some(r) = &run {
                key.push_str(&format!(":{}:{success_rate}", r.id()));
            }
            let mut sidecar = match &steering_log {
                Some(p) => {
                    key.push_str(&format!(":{}", store::sha256_hex(&std::fs::read(p)?)));
                    Some(ingest::steering::SteeringSidecar::open(p)?)
                }
                None => None,
            };
            let sha = store::sha256_hex(key.as_bytes());
            let source = SourceInput {
                path: format!("synth://{seed}"),
                sha256: sha,
                format: "synth".into(),
                size_bytes: 0,
                metadata: serde_json::json!({ "seed": seed }),
            };
            let mut w = store.begin_ingest(source, &policy, &checkpoint).await?;
            if let Some(n) = max_file_bytes {
                w = w.with_max_file_bytes(n);
            }
            if let Some(r) = run {
                w.set_run(r)?;
            }
            let mut state = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let mut rnd = move || {
                state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((state >> 33) as f64 / (1u64 << 31) as f64) as f32
            };
            for i in 0..episodes {
                let obs: Vec<f32> = (0..steps * 3).map(|_| rnd()).collect();
                let act: Vec<f32> = (0..steps * 2).map(|_| rnd() - 0.5).collect();
                let label = if rnd() < success_rate { Label::Success } else { Label::Failure };
                let ep = EpisodeInput {
                    source_name: format!("episode_{i}"),
                    source_index: i,
                    task: Some("synthetic".into()),
                    label,
                    label_source: "synth".into(),
                    tags: vec![],
                    metadata: serde_json::json!({}),
                    timestamps: (0..steps).map(|t| t as f64 * 0.1).collect(),
                    observations: vec![VectorColumn { name: "pos".into(), dim: 3, values: obs }],
                    action: VectorColumn { name: "action".into(), dim: 2, values: act },
                    reward: (0..steps)
                        .map(|t| if t + 1 == steps && label == Label::Success { 1.0 } else { 0.0 })
                        .collect(),
                    done: (0..steps).map(|t| t + 1 == steps).collect(),
                    action_chunk: None,
                    images: vec![],
                    media: vec![],
                    flags: Default::default(),
                };
                match sidecar.as_mut().map(|sc| sc.take(u64::from(i), steps)).transpose()?.flatten() {
                    Some(log) => w.add_episode_steered(ep, log).await?,
                    None => w.add_episode(ep).await?,
                };
            }
            if let Some(sc) = sidecar {
                sc.finish()?;
            }
            let c = w.commit("synthetic episodes").await?;
            println!("version {} ({} episodes)", c.version, c.episodes);
            Ok(())
        }
        DevCommand::Verify => verify(args).await,
    }
}

async fn verify(args: &StoreArgs) -> Result<()> {
    use arrow::array::{Array, StringArray};
    let store = args.open().await?;
    let versions = store.versions().await?;
    let mut problems = Vec::new();
    let mut checked = 0usize;
    for (i, v) in versions.iter().enumerate() {
        if v.version != i as i64 + 1 {
            problems.push(format!(
                "version numbers are not dense: found {} at position {}",
                v.version,
                i + 1
            ));
        }
        let eps =
            store.episodes(&store::EpisodeFilter { version: Some(v.version), ..Default::default() }).await?;
        if eps.len() as i64 != v.episode_count {
            problems.push(format!(
                "version {} lists {} episodes, recorded {}",
                v.version,
                eps.len(),
                v.episode_count
            ));
        }
        // The labels files alone (a full one and the deltas after it) give the same labels.
        match store.read_labels_files(v.version).await {
            Ok(rows)
                if rows.len() == eps.len() && {
                    let frozen: std::collections::HashMap<&str, (store::Label, i64)> =
                        eps.iter().map(|e| (e.id.as_str(), (e.label, e.label_revision))).collect();
                    rows.iter().all(|r| frozen.get(r.episode_id.as_str()) == Some(&(r.label, r.revision)))
                } => {}
            Ok(rows) => problems.push(format!(
                "version {}: its labels files hold {} rows that differ from the catalog's {} episodes",
                v.version,
                rows.len(),
                eps.len()
            )),
            Err(e) => problems.push(format!("version {}: labels files unreadable: {e}", v.version)),
        }
        // Every episode of the version, read in one pass grouped by steps file.
        let mut locations = Vec::with_capacity(eps.len());
        for e in &eps {
            match store::EpisodeLocation::try_from(e) {
                Ok(l) => locations.push(l),
                Err(err) => problems.push(format!("episode {} in version {}: {err}", e.id, v.version)),
            }
        }
        let mut read = vec![false; locations.len()];
        let by_id: std::collections::HashMap<&str, &store::EpisodeRecord> =
            eps.iter().map(|e| (e.id.as_str(), e)).collect();
        let mut steps = store.read_episodes(locations.clone());
        while let Some(item) = steps.next().await {
            match item {
                Ok(got) => {
                    read[got.index] = true;
                    let e = by_id[locations[got.index].episode_id.as_str()];
                    let batch = got.steps;
                    let ids = batch
                        .column_by_name("episode_id")
                        .and_then(|c| c.as_any().downcast_ref::<StringArray>().cloned());
                    let ok_ids = ids.is_some_and(|a| (0..a.len()).all(|k| a.value(k) == e.id));
                    if batch.num_rows() as i64 != e.length || !ok_ids {
                        problems.push(format!(
                            "episode {} in version {}: {} rows, expected {}",
                            e.id,
                            v.version,
                            batch.num_rows(),
                            e.length
                        ));
                    }
                }
                Err(err) => {
                    for &i in &err.indexes {
                        read[i] = true;
                        problems.push(format!(
                            "episode {} in version {}: {}",
                            locations[i].episode_id, v.version, err.error
                        ));
                    }
                }
            }
        }
        for (i, done) in read.iter().enumerate() {
            if !done {
                problems
                    .push(format!("episode {} in version {}: not read", locations[i].episode_id, v.version));
            }
        }
        checked += eps.len();
    }
    let referenced = store.referenced_objects().await?.len();
    super::print_json(&serde_json::json!({
        "versions": versions.len(), "episodes_checked": checked, "referenced_objects": referenced, "problems": problems,
        "object_store": store.fetch_counts(),
    }))?;
    if !problems.is_empty() {
        anyhow::bail!("{} problems in the store", problems.len());
    }
    Ok(())
}
