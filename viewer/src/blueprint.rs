//! The rerun blueprint of a recording: trajectories left, score / steering / action / state plots right,
//! a grid of camera views under the trajectories.

use re_sdk::blueprint::{
    Blueprint, ContainerLike, Grid, Horizontal, Spatial2DView, Spatial3DView, TimeSeriesView, Vertical,
};
use store::Label;

/// What one episode put where: the blueprint's view contents are built from these.
pub(crate) struct EpisodeEntities {
    /// Position in the episode listing (episodes are logged as they arrive from the store).
    pub(crate) index: usize,
    pub(crate) base: String,
    pub(crate) label: Label,
    pub(crate) has_score: bool,
    /// Logged `steering` (best-of-N telemetry: score spread and chosen score per step).
    pub(crate) has_steering: bool,
    /// `(camera key, entity path)` of each camera logged, in the steps' column order.
    pub(crate) cameras: Vec<(String, String)>,
}

/// Trajectories (2-D or 3-D) left; score, action and state plots right; cameras below them.
pub(crate) fn blueprint(eps: &[EpisodeEntities], pos_dims: Option<usize>, scored: bool) -> Blueprint {
    let mut spatial_excl: Vec<String> = vec!["+ /episodes/**".into()];
    for e in eps.iter().filter(|e| !e.cameras.is_empty()) {
        spatial_excl.push(format!("- /{}/camera/**", e.base));
        spatial_excl.push(format!("- /{}/image/**", e.base));
    }
    let trajectories: ContainerLike = match pos_dims {
        Some(3) => Spatial3DView::new("trajectories").with_origin("/").with_contents(spatial_excl).into(),
        _ => Spatial2DView::new("trajectories").with_origin("/").with_contents(spatial_excl).into(),
    };
    let per_ep = |suffix: &str, only: &dyn Fn(&EpisodeEntities) -> bool| -> Vec<String> {
        eps.iter().filter(|e| only(e)).map(|e| format!("+ /{}/{suffix}", e.base)).collect()
    };
    let mut plots: Vec<ContainerLike> = Vec::new();
    if scored {
        let mut c = vec!["+ /summary/score/**".to_string()];
        c.extend(per_ep("score", &|e| e.has_score));
        plots.push(TimeSeriesView::new("verifier score").with_origin("/").with_contents(c).into());
    }
    if eps.iter().any(|e| e.has_steering) {
        let c = per_ep("steering", &|e| e.has_steering);
        plots.push(
            TimeSeriesView::new("best-of-N: candidates' scores").with_origin("/").with_contents(c).into(),
        );
    }
    plots.push(
        TimeSeriesView::new("actions").with_origin("/").with_contents(per_ep("action", &|_| true)).into(),
    );
    let mut state = per_ep("state/**", &|_| true);
    state.extend(per_ep("reward", &|_| true));
    plots.push(TimeSeriesView::new("state & reward").with_origin("/").with_contents(state).into());
    // Camera views: a success and a failure first, then whatever comes; one row per episode
    // with each of its cameras side by side (at most 8 views, at most 4 episodes).
    let per_row = eps.iter().map(|e| e.cameras.len()).max().unwrap_or(0);
    let max_eps = 8usize.checked_div(per_row).map_or(0, |k| k.clamp(1, 4));
    let shown =
        eps.iter().filter(|e| !e.cameras.is_empty()).fold(Vec::<&EpisodeEntities>::new(), |mut v, e| {
            if v.len() < max_eps && (v.iter().all(|x| x.label != e.label) || v.len() >= 2) {
                v.push(e);
            }
            v
        });
    let mut cams: Vec<ContainerLike> = Vec::new();
    for e in shown {
        let name = e.base.trim_start_matches("episodes/").to_string();
        for (key, path) in &e.cameras {
            cams.push(
                Spatial2DView::new(format!("{name} · {key}"))
                    .with_origin(format!("/{path}"))
                    .with_contents([format!("+ /{path}")])
                    .into(),
            );
        }
    }
    let right: ContainerLike = Vertical::new(plots).into();
    let root: ContainerLike = if cams.is_empty() {
        Horizontal::new([trajectories, right]).into()
    } else {
        let grid = Grid::new(cams).with_grid_columns(per_row as u32);
        let left: ContainerLike = Vertical::new([trajectories, grid.into()]).into();
        Horizontal::new([left, right]).into()
    };
    Blueprint::new(root).with_auto_views(false)
}
