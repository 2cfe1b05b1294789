//! An episode's samples turned into steps (one per action message, per observation time, or per
//! tick of `rate_hz`) and then into an [`EpisodeInput`].

use std::collections::BTreeMap;

use serde_json::{json, Map, Value};

use super::assembler::{Assembler, Kind, PendingEp, Sample};
use crate::error::Result;
use crate::model::{EpisodeInput, Label, VectorColumn};

/// One column while an episode is stepped: its dimension (set by its first value), the flat
/// values, and how many steps came before its first value (`missing`).
struct Col {
    dim: Option<usize>,
    vals: Vec<f32>,
    missing: usize,
}

impl Col {
    /// The column as (dimension, values), its first value repeated over the `missing` steps
    /// before it; `None` when no step had a value.
    fn backfill(self) -> Option<(usize, Vec<f32>)> {
        let d = self.dim?;
        if self.missing == 0 {
            return Some((d, self.vals));
        }
        let first: Vec<f32> = self.vals[..d].to_vec();
        let mut v = Vec::with_capacity(self.vals.len() + self.missing * d);
        for _ in 0..self.missing {
            v.extend_from_slice(&first);
        }
        v.extend_from_slice(&self.vals);
        Some((d, v))
    }
}

/// An episode's steps before assembly: log times, rewards, the action column and one column
/// per mapped observation.
struct Steps {
    times: Vec<u64>,
    reward: Vec<f32>,
    action: Col,
    cols: Vec<Col>,
}

impl Assembler<'_> {
    pub(super) fn build(
        &self,
        p: &PendingEp,
        index: i64,
        samples: &[&Sample],
        counts: BTreeMap<String, u64>,
    ) -> Result<Option<EpisodeInput>> {
        let Steps { times, reward, action, cols } = self.steps(p, samples)?;
        if times.is_empty() {
            return Ok(None);
        }
        // No action in the whole episode: dimension 0, stored without an action column.
        let (adim, avals) = action.backfill().unwrap_or((0, Vec::new()));
        let mut observations = Vec::new();
        for (k, c) in cols.into_iter().enumerate() {
            if let Some((dim, values)) = c.backfill() {
                if dim > 0 {
                    observations.push(VectorColumn { name: self.obs_keys[k].clone(), dim, values });
                }
            }
        }
        let steps = times.len();
        let timestamps: Vec<f64> = times.iter().map(|t| t.saturating_sub(p.start) as f64 / 1e9).collect();
        let mut done = vec![false; steps];
        if let Some(d) = done.last_mut() {
            *d = true;
        }
        let name = format!("episode_{index}");
        let (label, label_source) = match self.opts.user_label(&name, index.max(0) as u32, &reward) {
            Some(l) => l,
            None => match p.success {
                Some(b) => (Label::from_bool(Some(b)), p.label_source.clone()),
                None => (Label::Unknown, String::new()),
            },
        };
        let mut md = Map::new();
        md.insert("index".into(), json!(index));
        md.insert("start_ns".into(), json!(p.start));
        md.insert("end_ns".into(), json!(p.end));
        md.insert("message_counts".into(), json!(counts));
        for (k, v) in &p.meta {
            if !matches!(k.as_str(), "index" | "start_ns" | "end_ns" | "episode") {
                md.insert(k.clone(), json!(v));
            }
        }
        let task = self.opts.task.clone().or_else(|| p.meta.get("task").cloned());
        Ok(Some(EpisodeInput {
            source_name: name,
            source_index: index.clamp(0, u32::MAX as i64) as u32,
            task,
            label,
            label_source,
            tags: Vec::new(),
            metadata: Value::Object(md),
            timestamps,
            observations,
            action: VectorColumn { name: "action".into(), dim: adim, values: avals },
            reward,
            done,
            action_chunk: None,
            images: Vec::new(),
            media: Vec::new(),
            flags: Default::default(),
        }))
    }

    /// One step per action message, else one per observation time (no action messages), or one
    /// per tick of `rate_hz`, each with the latest observations and reward.
    fn steps(&self, p: &PendingEp, samples: &[&Sample]) -> Result<Steps> {
        let nobs = self.obs_keys.len();
        let mut cols: Vec<Col> = (0..nobs).map(|_| Col { dim: None, vals: Vec::new(), missing: 0 }).collect();
        let mut latest: Vec<Option<&Vec<f32>>> = vec![None; nobs];
        let mut latest_action: Option<&Vec<f32>> = None;
        let mut latest_reward = 0f32;
        let mut action = Col { dim: None, vals: Vec::new(), missing: 0 };
        let mut times: Vec<u64> = Vec::new();
        let mut reward = Vec::new();
        let topic_of = |k: usize| self.mapping.observations[&self.obs_keys[k]].topic.clone();
        let mut step = |t: u64,
                        latest: &[Option<&Vec<f32>>],
                        act: Option<&Vec<f32>>,
                        r: f32,
                        cols: &mut Vec<Col>,
                        action: &mut Col|
         -> Result<()> {
            times.push(t);
            reward.push(r);
            self.push_col(action, act, &format!("action topic {}", self.mapping.action.topic), t)?;
            for (k, c) in cols.iter_mut().enumerate() {
                self.push_col(
                    c,
                    latest[k],
                    &format!("observation {} (topic {})", self.obs_keys[k], topic_of(k)),
                    t,
                )?;
            }
            Ok(())
        };
        let has_action = samples.iter().any(|s| matches!(s.kind, Kind::Action(_)));
        match self.mapping.rate_hz {
            None if has_action => {
                for s in samples {
                    match &s.kind {
                        Kind::Obs(k, v) => latest[*k] = Some(v),
                        Kind::Reward(r) => latest_reward = *r,
                        Kind::Action(v) => {
                            step(s.t, &latest, Some(v), latest_reward, &mut cols, &mut action)?
                        }
                        Kind::Other => {}
                    }
                }
            }
            None => {
                // No action messages: one step per observation time (all observations
                // published at that log time taken together), actions null.
                for (i, s) in samples.iter().enumerate() {
                    match &s.kind {
                        Kind::Obs(k, v) => latest[*k] = Some(v),
                        Kind::Reward(r) => latest_reward = *r,
                        _ => {}
                    }
                    let last_at_t = samples.get(i + 1).is_none_or(|n| n.t != s.t);
                    let obs_at_t = samples[..=i]
                        .iter()
                        .rev()
                        .take_while(|p| p.t == s.t)
                        .any(|p| matches!(p.kind, Kind::Obs(..)));
                    if last_at_t && obs_at_t {
                        step(s.t, &latest, None, latest_reward, &mut cols, &mut action)?;
                    }
                }
            }
            Some(rate) => {
                let dt = 1e9 / rate;
                let mut k = 0u64;
                let mut i = 0usize;
                loop {
                    let ts = p.start + (k as f64 * dt) as u64;
                    if ts > p.end || k > 10_000_000 {
                        break;
                    }
                    while i < samples.len() && samples[i].t <= ts {
                        match &samples[i].kind {
                            Kind::Obs(j, v) => latest[*j] = Some(v),
                            Kind::Reward(r) => latest_reward = *r,
                            Kind::Action(v) => latest_action = Some(v),
                            Kind::Other => {}
                        }
                        i += 1;
                    }
                    if latest_action.is_some() || action.dim.is_some() || i > 0 {
                        step(ts, &latest, latest_action, latest_reward, &mut cols, &mut action)?;
                    }
                    k += 1;
                }
            }
        }
        Ok(Steps { times, reward, action, cols })
    }

    /// Appends one step's value `v` (`None`: none seen yet) to column `c`; a value whose length
    /// differs from the column's earlier ones is refused (`what` names the column).
    fn push_col(&self, c: &mut Col, v: Option<&Vec<f32>>, what: &str, t: u64) -> Result<()> {
        match v {
            None => c.missing += 1,
            Some(v) => {
                match c.dim {
                    None => c.dim = Some(v.len()),
                    Some(d) if d != v.len() => {
                        return Err(self.err(format!(
                            "{what}: {} values at log time {t}, earlier messages had {d}",
                            v.len()
                        )));
                    }
                    _ => {}
                }
                c.vals.extend_from_slice(v);
            }
        }
        Ok(())
    }
}
