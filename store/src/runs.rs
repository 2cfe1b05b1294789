//! Evaluation runs: how an episode was produced. An ingest may name a run — the base policy, or
//! the policy steered by best-of-N, classifier guidance (CG) or flow guidance with a verifier
//! artifact — and every episode it writes carries it (catalog `runs`, `episodes.run_id`). A run's
//! id is derived from its content, so two ingests of the same run share a row.

use crate::catalog::RowExt;
use crate::model::check_name;
use crate::{Store, StoreError};
use serde::{Deserialize, Serialize};

/// How a run's actions were chosen.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "method", rename_all = "lowercase")]
pub enum Steering {
    /// The policy as it is.
    Base,
    /// Best-of-N: the verifier picks the best of `n` sampled chunks.
    Bon { n: u32 },
    /// Classifier guidance of a diffusion sampler with strength `lambda`.
    Cg { lambda: f64 },
    /// Guidance of a flow-matching sampler with strength `lambda`.
    Flow { lambda: f64 },
}

impl std::fmt::Display for Steering {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Steering::Base => f.write_str("base"),
            Steering::Bon { n } => write!(f, "bon:{n}"),
            Steering::Cg { lambda } => write!(f, "cg:{lambda}"),
            Steering::Flow { lambda } => write!(f, "flow:{lambda}"),
        }
    }
}

impl std::str::FromStr for Steering {
    type Err = StoreError;
    /// `base`, `bon:N`, `cg:LAMBDA` or `flow:LAMBDA` (N ≥ 1, λ finite and ≥ 0).
    fn from_str(s: &str) -> Result<Self, StoreError> {
        let bad = |why: &str| {
            StoreError::invalid(format!(
                "invalid steering {s:?}: {why} (expected base, bon:N, cg:LAMBDA or flow:LAMBDA)"
            ))
        };
        let (method, arg) = match s.split_once(':') {
            Some((m, a)) => (m, Some(a)),
            None => (s, None),
        };
        let lambda = |a: Option<&str>| -> Result<f64, StoreError> {
            let a = a.ok_or_else(|| bad("missing λ"))?;
            let l: f64 = a.parse().map_err(|_| bad("λ is not a number"))?;
            if !l.is_finite() || l < 0.0 {
                return Err(bad("λ must be finite and ≥ 0"));
            }
            Ok(l)
        };
        match method {
            "base" if arg.is_none() => Ok(Steering::Base),
            "bon" => {
                let n: u32 = arg
                    .ok_or_else(|| bad("missing N"))?
                    .parse()
                    .map_err(|_| bad("N is not a whole number"))?;
                if n == 0 {
                    return Err(bad("N must be at least 1"));
                }
                Ok(Steering::Bon { n })
            }
            "cg" => Ok(Steering::Cg { lambda: lambda(arg)? }),
            "flow" => Ok(Steering::Flow { lambda: lambda(arg)? }),
            _ => Err(bad("unknown method")),
        }
    }
}

/// A run as an ingest names it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunInput {
    pub name: String,
    pub steering: Steering,
    /// The verifier artifact that steered it (none for the base policy).
    #[serde(default)]
    pub artifact_id: Option<String>,
    /// Free-form tags (e.g. `flow-twin`, `off-policy`).
    #[serde(default)]
    pub tags: Vec<String>,
}

impl RunInput {
    pub fn new(name: &str, steering: Steering) -> Self {
        RunInput { name: name.to_string(), steering, artifact_id: None, tags: vec![] }
    }

    /// The run an ingest names by its optional parts (the CLI's `--run`, `--steering`,
    /// `--run-artifact`, `--run-tag`; the API's query of the same names): none when no part is
    /// given. Steering defaults to `base`, and the name to the steering as written (`base`,
    /// `bon:10`, `cg:0.5`), so rollouts steered alike share a run and the base policy's are the
    /// scoreboard's default baseline. Checked with [`RunInput::validate`].
    pub fn from_parts(
        name: Option<&str>,
        steering: Option<&str>,
        artifact_id: Option<&str>,
        tags: &[String],
    ) -> Result<Option<Self>, StoreError> {
        if name.is_none() && steering.is_none() && artifact_id.is_none() && tags.is_empty() {
            return Ok(None);
        }
        let steering: Steering = steering.map(str::parse).transpose()?.unwrap_or(Steering::Base);
        let run = RunInput {
            name: name.map_or_else(|| steering.to_string(), str::to_string),
            steering,
            artifact_id: artifact_id.map(str::to_string),
            tags: tags.to_vec(),
        };
        run.validate()?;
        Ok(Some(run))
    }

    /// Checks names and tags (hostile input is an error naming the problem).
    pub fn validate(&self) -> Result<(), StoreError> {
        check_name("run", &self.name)?;
        if let Some(a) = &self.artifact_id {
            check_name("artifact", a)?;
        }
        for t in &self.tags {
            check_name("run tag", t)?;
        }
        if self.tags.len() > 64 {
            return Err(StoreError::invalid(format!("a run has at most 64 tags, not {}", self.tags.len())));
        }
        Ok(())
    }

    /// The run's id: `run-` and 16 hex digits of the sha256 of its canonical content.
    pub fn id(&self) -> String {
        let mut tags = self.tags.clone();
        tags.sort();
        tags.dedup();
        let canon = serde_json::json!([self.name, self.steering.to_string(), self.artifact_id, tags]);
        format!("run-{}", &crate::sha256_hex(canon.to_string().as_bytes())[..16])
    }
}

/// A run as the catalog holds it.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunRecord {
    pub id: String,
    pub name: String,
    pub steering: Steering,
    pub artifact_id: Option<String>,
    pub tags: Vec<String>,
    pub created_at: String,
}

pub fn run_from_row(r: &sqlx::any::AnyRow) -> Result<RunRecord, StoreError> {
    Ok(RunRecord {
        id: r.s("id")?,
        name: r.s("name")?,
        steering: r.s("steering")?.parse()?,
        artifact_id: r.os("artifact_id")?,
        tags: serde_json::from_str(&r.s("tags")?)?,
        created_at: r.s("created_at")?,
    })
}

/// Inserts the run's row if it is not there yet (inside an ingest's transaction), after checking
/// that its artifact exists.
pub(crate) async fn ensure_run(
    tx: &mut crate::catalog::Tx,
    run: &RunInput,
    now: &str,
) -> Result<String, StoreError> {
    run.validate()?;
    if let Some(a) = &run.artifact_id {
        if sqlx::query("SELECT id FROM artifacts WHERE id = $1")
            .bind(a)
            .fetch_optional(&mut **tx)
            .await?
            .is_none()
        {
            return Err(StoreError::not_found("artifact", a));
        }
    }
    let id = run.id();
    let mut tags = run.tags.clone();
    tags.sort();
    tags.dedup();
    sqlx::query(
        "INSERT INTO runs (id, name, steering, artifact_id, tags, created_at) VALUES ($1, $2, $3, $4, $5, $6) \
         ON CONFLICT (id) DO NOTHING",
    )
    .bind(&id)
    .bind(&run.name)
    .bind(run.steering.to_string())
    .bind(run.artifact_id.clone())
    .bind(serde_json::to_string(&tags)?)
    .bind(now)
    .execute(&mut **tx)
    .await?;
    Ok(id)
}

impl Store {
    /// Every run, by name then id; `name` filters.
    pub async fn runs(&self, name: Option<&str>) -> Result<Vec<RunRecord>, StoreError> {
        let rows = sqlx::query(
            "SELECT id, name, steering, artifact_id, tags, created_at FROM runs WHERE ($1 = '' OR name = $1) \
             ORDER BY name, id",
        )
        .bind(name.unwrap_or(""))
        .fetch_all(&self.catalog().pool)
        .await?;
        rows.iter().map(run_from_row).collect()
    }

    /// One run by id.
    pub async fn run(&self, id: &str) -> Result<RunRecord, StoreError> {
        let row =
            sqlx::query("SELECT id, name, steering, artifact_id, tags, created_at FROM runs WHERE id = $1")
                .bind(id)
                .fetch_optional(&self.catalog().pool)
                .await?
                .ok_or_else(|| StoreError::not_found("run", id))?;
        run_from_row(&row)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn steering_parses_and_prints_canonically() {
        for (s, v) in [
            ("base", Steering::Base),
            ("bon:30", Steering::Bon { n: 30 }),
            ("cg:0.1", Steering::Cg { lambda: 0.1 }),
            ("cg:3", Steering::Cg { lambda: 3.0 }),
            ("flow:1.5", Steering::Flow { lambda: 1.5 }),
        ] {
            assert_eq!(s.parse::<Steering>().unwrap(), v);
            assert_eq!(v.to_string(), s);
        }
        assert_eq!("cg:3.0".parse::<Steering>().unwrap().to_string(), "cg:3");
        for bad in
            ["", "bon", "bon:0", "bon:-1", "bon:x", "cg", "cg:nan", "cg:inf", "cg:-1", "base:1", "ddim:3"]
        {
            let e = bad.parse::<Steering>().unwrap_err().to_string();
            assert!(e.contains("invalid steering"), "{bad}: {e}");
        }
    }

    #[test]
    fn run_ids_depend_on_content_not_tag_order() {
        let mut a = RunInput::new("c-bon", Steering::Bon { n: 10 });
        a.tags = vec!["x".into(), "y".into()];
        let mut b = a.clone();
        b.tags = vec!["y".into(), "x".into(), "x".into()];
        assert_eq!(a.id(), b.id());
        b.steering = Steering::Bon { n: 30 };
        assert_ne!(a.id(), b.id());
        assert!(RunInput::new(" bad", Steering::Base).validate().is_err());
    }

    #[test]
    fn a_run_given_by_its_parts_is_named_after_its_steering_by_default() {
        assert_eq!(RunInput::from_parts(None, None, None, &[]).unwrap(), None);
        let bon = RunInput::from_parts(None, Some("bon:10"), Some("art-1"), &[]).unwrap().unwrap();
        assert_eq!(
            (bon.name.as_str(), bon.steering, bon.artifact_id.as_deref()),
            ("bon:10", Steering::Bon { n: 10 }, Some("art-1"))
        );
        let tagged = RunInput::from_parts(None, None, None, &["eval-3".into()]).unwrap().unwrap();
        assert_eq!((tagged.name.as_str(), tagged.steering, tagged.tags.len()), ("base", Steering::Base, 1));
        let named = RunInput::from_parts(Some("night"), Some("cg:0.5"), None, &[]).unwrap().unwrap();
        assert_eq!((named.name.as_str(), named.steering), ("night", Steering::Cg { lambda: 0.5 }));
        assert!(RunInput::from_parts(None, Some("bon:0"), None, &[])
            .unwrap_err()
            .to_string()
            .contains("invalid steering"));
        assert!(RunInput::from_parts(None, None, None, &[" x".into()]).is_err());
    }
}
