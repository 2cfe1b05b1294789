//! Trajectories: which observation dims form an episode's position (`key` or `key[i,j]` position
//! keys, or the first 2- or 3-dim observation), drawn as a static strip of the whole path plus a
//! point per step.

use super::{EpisodeSteps, Recorder};
use crate::{rr, ViewError};
use re_sdk_types::archetypes::{LineStrips2D, LineStrips3D, Points2D, Points3D};

/// One position spec resolved against a steps schema: `(column, dim indices)`.
type PositionSpec = Vec<(String, Vec<usize>)>;

/// Parses `key` or `key[i,j]` position keys against the observation keys of a batch.
fn resolve_positions(keys: &[String], obs: &[(String, usize)]) -> Result<Option<PositionSpec>, String> {
    if keys.is_empty() {
        return Ok(obs
            .iter()
            .find(|(_, d)| *d == 2 || *d == 3)
            .map(|(k, d)| vec![(k.clone(), (0..*d).collect())]));
    }
    let mut spec = Vec::new();
    for raw in keys {
        let raw = raw.trim();
        let (key, idx) = match raw.split_once('[') {
            Some((k, rest)) => {
                let inner =
                    rest.strip_suffix(']').ok_or_else(|| format!("position key {raw:?}: missing ']'"))?;
                let idx = inner
                    .split(',')
                    .map(|s| {
                        s.trim()
                            .parse::<usize>()
                            .map_err(|_| format!("position key {raw:?}: bad index {s:?}"))
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                (k.trim(), Some(idx))
            }
            None => (raw, None),
        };
        let key = key.strip_prefix(store::steps::OBS_PREFIX).unwrap_or(key);
        let Some((_, dim)) = obs.iter().find(|(k, _)| k == key) else {
            return Ok(None);
        };
        let idx = idx.unwrap_or_else(|| (0..*dim).collect());
        if let Some(bad) = idx.iter().find(|&&i| i >= *dim) {
            return Err(format!("position key {raw:?}: index {bad} out of range (dim {dim})"));
        }
        spec.push((key.to_string(), idx));
    }
    let total: usize = spec.iter().map(|(_, i)| i.len()).sum();
    if total != 2 && total != 3 {
        return Err(format!("position keys {keys:?} give {total} dims, expected 2 or 3"));
    }
    Ok(Some(spec))
}

fn spec_names(spec: &PositionSpec) -> Vec<String> {
    spec.iter().flat_map(|(k, idx)| idx.iter().map(move |i| format!("{k}[{i}]"))).collect()
}

/// The position of every step: the spec's dims, concatenated, one `Vec` per row.
fn position_points(e: &EpisodeSteps<'_>, spec: &PositionSpec) -> Result<Vec<Vec<f32>>, ViewError> {
    let mut cols: Vec<(usize, Vec<f32>)> = Vec::new();
    for (key, _) in spec {
        cols.push(store::steps::vector_column(e.batch, &format!("{}{key}", store::steps::OBS_PREFIX))?);
    }
    Ok((0..e.n)
        .map(|row| {
            spec.iter()
                .zip(&cols)
                .flat_map(|((_, idx), (dim, vals))| idx.iter().map(move |&i| vals[row * dim + i]))
                .collect()
        })
        .collect())
}

impl Recorder<'_> {
    /// Trajectory: a static strip (the whole path) and a point per step (where it is now).
    /// An episode without the position dims is counted in the report and drawn without one.
    pub(super) fn log_trajectory(&mut self, e: &EpisodeSteps<'_>) -> Result<(), ViewError> {
        let spec = resolve_positions(&self.opts.position_keys, &e.obs).map_err(ViewError::Invalid)?;
        let Some(spec) = spec else {
            self.report.without_position += 1;
            return Ok(());
        };
        let pts = position_points(e, &spec)?;
        let d = pts[0].len();
        if self.report.position_dims.is_empty() {
            self.report.position_dims = spec_names(&spec);
        }
        if *self.pos_dims.get_or_insert(d) != d {
            return Err(ViewError::Invalid(format!(
                "episode {} has a {d}-D position, earlier episodes {}-D",
                e.ep.id,
                self.pos_dims.unwrap_or(0)
            )));
        }
        self.draw_trajectory(e, &pts, d)
    }

    /// Logs the strip and the per-step points of `pts` (`d` = 2 or 3 dims each).
    fn draw_trajectory(&mut self, e: &EpisodeSteps<'_>, pts: &[Vec<f32>], d: usize) -> Result<(), ViewError> {
        let (n, color, idx, rec) = (e.n, e.color, &e.idx, self.out.rec);
        let strip_path = format!("{}/trajectory", e.base);
        let point_path = format!("{}/position", e.base);
        let lbl = format!("{} {}", e.ep.id, e.label);
        if d == 2 {
            let p2: Vec<[f32; 2]> = pts.iter().map(|p| [p[0], p[1]]).collect();
            rec.log_static(
                strip_path.as_str(),
                &LineStrips2D::new([p2.clone()]).with_colors([color]).with_labels([lbl]),
            )
            .map_err(rr)?;
            let arch = Points2D::new(p2).with_colors(vec![color; n]).with_radii(vec![0.02f32; n]);
            self.out.send(point_path, idx, arch.columns_of_unit_batches().map_err(rr)?.collect())?;
        } else {
            let p3: Vec<[f32; 3]> = pts.iter().map(|p| [p[0], p[1], p[2]]).collect();
            rec.log_static(
                strip_path.as_str(),
                &LineStrips3D::new([p3.clone()]).with_colors([color]).with_labels([lbl]),
            )
            .map_err(rr)?;
            let arch = Points3D::new(p3).with_colors(vec![color; n]).with_radii(vec![0.01f32; n]);
            self.out.send(point_path, idx, arch.columns_of_unit_batches().map_err(rr)?.collect())?;
        }
        self.out.entities.insert(strip_path);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn position_keys_resolve() {
        let obs = vec![("agent".to_string(), 5), ("pos".to_string(), 2), ("eef".to_string(), 3)];
        assert_eq!(resolve_positions(&[], &obs).unwrap(), Some(vec![("pos".into(), vec![0, 1])]));
        assert_eq!(
            resolve_positions(&["eef".into()], &obs).unwrap(),
            Some(vec![("eef".into(), vec![0, 1, 2])])
        );
        assert_eq!(
            resolve_positions(&["obs.agent[3, 4]".into()], &obs).unwrap(),
            Some(vec![("agent".into(), vec![3, 4])])
        );
        assert!(resolve_positions(&["agent".into()], &obs).is_err(), "5 dims");
        assert!(resolve_positions(&["agent[9,1]".into()], &obs).is_err());
        assert_eq!(resolve_positions(&["missing".into()], &obs).unwrap(), None);
    }
}
