//! The recording's summary: the mean verifier score per step of successes and of failures,
//! their gap and where it opens (`summary/score/*`), and a markdown overview (`summary/info`).

use super::{Recorder, BLUE, GREEN, RED};
use crate::{rr, ViewError, ViewOptions, ViewReport};
use re_sdk::log::TimeColumn;
use re_sdk_types::archetypes::{Scalars, SeriesLines, TextDocument};
use re_sdk_types::components::MediaType;
use std::collections::HashMap;
use store::Label;

/// Per-step score sums of one label.
#[derive(Default)]
pub(super) struct ScoreAcc {
    sum: Vec<f64>,
    count: Vec<u32>,
    total: f64,
    n: u64,
}

impl ScoreAcc {
    pub(super) fn add(&mut self, scores: &[f32]) {
        if self.sum.len() < scores.len() {
            self.sum.resize(scores.len(), 0.0);
            self.count.resize(scores.len(), 0);
        }
        for (i, s) in scores.iter().enumerate() {
            if s.is_finite() {
                self.sum[i] += *s as f64;
                self.count[i] += 1;
                self.total += *s as f64;
                self.n += 1;
            }
        }
    }
    fn means(&self) -> Vec<Option<f64>> {
        self.sum.iter().zip(&self.count).map(|(s, &c)| (c > 0).then(|| s / c as f64)).collect()
    }
    fn mean(&self) -> Option<f32> {
        (self.n > 0).then(|| (self.total / self.n as f64) as f32)
    }
}

impl Recorder<'_> {
    /// Summary: mean score of successes vs failures per step, and their gap.
    pub(super) fn log_score_summary(&mut self) -> Result<(), ViewError> {
        let empty = ScoreAcc::default();
        let s = self.acc.get(&Label::Success).unwrap_or(&empty);
        let f = self.acc.get(&Label::Failure).unwrap_or(&empty);
        self.report.mean_score_success = s.mean();
        self.report.mean_score_failure = f.mean();
        for (name, a, color) in [("success", s, GREEN), ("failure", f, RED)] {
            let means = a.means();
            let steps: Vec<i64> = (0..means.len() as i64).filter(|&i| means[i as usize].is_some()).collect();
            if steps.is_empty() {
                continue;
            }
            let vals: Vec<f64> = means.iter().flatten().copied().collect();
            let path = format!("summary/score/{name}");
            self.out
                .rec
                .log_static(
                    path.as_str(),
                    &SeriesLines::new()
                        .with_colors([color])
                        .with_names([format!("mean score ({name})")])
                        .with_widths([3.0f32]),
                )
                .map_err(rr)?;
            let cols = Scalars::new(vals).columns_of_unit_batches().map_err(rr)?.collect::<Vec<_>>();
            self.out.send(path, &[TimeColumn::new_sequence("step", steps)], cols)?;
        }
        let (sm, fm) = (s.means(), f.means());
        let gap: Vec<(i64, f64)> = sm
            .iter()
            .zip(&fm)
            .enumerate()
            .filter_map(|(i, (a, b))| Some((i as i64, (*a)? - (*b)?)))
            .collect();
        if !gap.is_empty() {
            self.log_score_gap(&gap)?;
        }
        Ok(())
    }

    /// The gap (success mean − failure mean) per step, its maximum and where it opens.
    fn log_score_gap(&mut self, gap: &[(i64, f64)]) -> Result<(), ViewError> {
        let path = "summary/score/gap";
        self.out
            .rec
            .log_static(
                path,
                &SeriesLines::new()
                    .with_colors([BLUE])
                    .with_names(["success − failure"])
                    .with_widths([2.0f32]),
            )
            .map_err(rr)?;
        let cols =
            Scalars::new(gap.iter().map(|g| g.1)).columns_of_unit_batches().map_err(rr)?.collect::<Vec<_>>();
        self.out.send(
            path.to_string(),
            &[TimeColumn::new_sequence("step", gap.iter().map(|g| g.0))],
            cols,
        )?;
        let (best_step, best) =
            gap.iter().copied().fold((0, f64::NEG_INFINITY), |acc, g| if g.1 > acc.1 { g } else { acc });
        self.report.max_separation = Some((best_step, best as f32));
        if best > 0.0 {
            // The earliest step after which the gap never drops below half its maximum.
            let mut from = None;
            for (i, g) in gap.iter().rev() {
                if *g >= best / 2.0 {
                    from = Some(*i);
                } else {
                    break;
                }
            }
            self.report.separates_from_step = from;
        }
        Ok(())
    }

    /// The static markdown overview at `summary/info`.
    pub(super) fn log_summary_info(&mut self) -> Result<(), ViewError> {
        self.out
            .rec
            .log_static(
                "summary/info",
                &TextDocument::new(summary_markdown(self.opts, &self.report, &self.lengths))
                    .with_media_type(MediaType::markdown()),
            )
            .map_err(rr)?;
        self.out.entities.insert("summary/info".into());
        Ok(())
    }
}

fn summary_markdown(opts: &ViewOptions, r: &ViewReport, lengths: &HashMap<Label, Vec<usize>>) -> String {
    let mut s = format!("# {} / {}\n\n", opts.policy, opts.checkpoint);
    if let Some(split) = &opts.split_id {
        s.push_str(&format!("split `{split}`\n\n"));
    }
    s.push_str("| label | episodes | mean length |\n|---|---|---|\n");
    for (l, n) in [(Label::Success, r.success), (Label::Failure, r.failure), (Label::Unknown, r.unknown)] {
        let lens = lengths.get(&l).map(Vec::as_slice).unwrap_or(&[]);
        let mean = if lens.is_empty() { 0.0 } else { lens.iter().sum::<usize>() as f64 / lens.len() as f64 };
        s.push_str(&format!("| {l} | {n} | {mean:.1} |\n"));
    }
    if !r.position_dims.is_empty() {
        s.push_str(&format!("\ntrajectory: {}\n", r.position_dims.join(", ")));
    }
    if r.scored {
        let f = |x: Option<f32>| x.map(|v| format!("{v:.3}")).unwrap_or_else(|| "–".into());
        s.push_str(&format!(
            "\nverifier score: mean {} on successes, {} on failures\n",
            f(r.mean_score_success),
            f(r.mean_score_failure)
        ));
        if let Some((step, gap)) = r.max_separation {
            s.push_str(&format!("\nlargest gap {gap:.3} at step {step}"));
            if let Some(from) = r.separates_from_step {
                s.push_str(&format!("; gap ≥ half of it from step {from} on"));
            }
            s.push('\n');
        }
    }
    s
}
