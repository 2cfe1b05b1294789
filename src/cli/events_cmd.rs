//! `ufops events`: the change feed, from the store or from `ufops serve` (`--api`), once or
//! followed.

use anyhow::{Context, Result};
use clap::Args;
use std::io::Write;
use std::time::Duration;

use super::StoreArgs;

#[derive(Args, Debug)]
pub struct EventsArgs {
    /// Events with a sequence number above this one (default 0: everything kept).
    #[arg(long, default_value_t = 0)]
    after: i64,
    /// Keep waiting for new events and print each as it commits (until interrupted).
    #[arg(long)]
    follow: bool,
    /// Only these kinds (repeatable or comma-separated): ingest.committed, label.set, vote.cast,
    /// version.created, split.frozen, job.changed, artifact.published, alias.moved,
    /// export.finished, monitor.created, review.scored, campaign.set, token.changed,
    /// automation.created, automation.deleted, automation.fired.
    #[arg(long, value_delimiter = ',')]
    kind: Vec<String>,
    /// Only events of this policy.
    #[arg(long)]
    policy: Option<String>,
    /// Stop after this many events.
    #[arg(long)]
    limit: Option<u64>,
    /// One JSON object per line (the API's event records) instead of a line of text each.
    #[arg(long)]
    json: bool,
    /// Read the feed from a `ufops serve` API (http://HOST:PORT, long polling) instead of the store.
    #[arg(long)]
    api: Option<String>,
    /// Bearer token for --api (role viewer or above).
    #[arg(long, env = "UFOPS_TOKEN", hide_env_values = true)]
    token: Option<String>,
}

/// Where the pages come from.
enum Feed {
    Store(store::Store, store::EventFilter),
    /// `query`: the filter's parameters, encoded by ureq.
    Api {
        agent: ureq::Agent,
        url: String,
        token: String,
        query: Vec<(&'static str, String)>,
    },
}

impl Feed {
    /// The next page after `after`, waiting up to `wait` for one when following.
    async fn page(&self, after: i64, wait: Duration) -> Result<store::EventPage> {
        match self {
            Feed::Store(store, filter) => {
                // Other processes write: look again every 200 ms.
                Ok(store
                    .wait_for_events(after, store::MAX_EVENT_PAGE, filter, wait, Duration::from_millis(200))
                    .await?)
            }
            Feed::Api { agent, url, token, query } => {
                let (agent, url, token) = (agent.clone(), url.clone(), token.clone());
                let mut query = query.clone();
                query.extend([("after", after.to_string()), ("wait", wait.as_secs().to_string())]);
                tokio::task::spawn_blocking(move || -> Result<store::EventPage> {
                    let mut resp = agent
                        .get(&url)
                        .query_pairs(query.iter().map(|(k, v)| (*k, v.as_str())))
                        .header("Authorization", &format!("Bearer {token}"))
                        .call()
                        .with_context(|| format!("GET {url}"))?;
                    let status = resp.status().as_u16();
                    let body = resp.body_mut().with_config().limit(64 << 20).read_to_vec()?;
                    if status != 200 {
                        let detail = serde_json::from_slice::<serde_json::Value>(&body)
                            .ok()
                            .and_then(|v| v.get("detail").and_then(|d| d.as_str()).map(str::to_string))
                            .unwrap_or_else(|| String::from_utf8_lossy(&body).into_owned());
                        anyhow::bail!("GET {url}: status {status}: {detail}");
                    }
                    serde_json::from_slice(&body).context("the API's event page")
                })
                .await?
            }
        }
    }
}

pub async fn run(args: &StoreArgs, a: EventsArgs) -> Result<()> {
    let mut filter = store::EventFilter { policy: a.policy.clone(), ..Default::default() };
    for k in a.kind.iter().filter(|k| !k.is_empty()) {
        filter.kinds.push(k.parse()?);
    }
    let feed = match &a.api {
        Some(base) => {
            let token = a.token.clone().context("--api needs a token: --token or UFOPS_TOKEN")?;
            let url = format!("{}/v1/events", base.trim_end_matches('/'));
            let mut query = vec![("limit", store::MAX_EVENT_PAGE.to_string())];
            if !a.kind.is_empty() {
                query.push(("kind", a.kind.join(",")));
            }
            if let Some(p) = &a.policy {
                query.push(("policy", p.clone()));
            }
            let agent: ureq::Agent = ureq::Agent::config_builder()
                .timeout_global(Some(Duration::from_secs(90)))
                .http_status_as_error(false)
                .build()
                .into();
            Feed::Api { agent, url, token, query }
        }
        None => Feed::Store(args.open().await?, filter),
    };
    let wait = if a.follow { Duration::from_secs(30) } else { Duration::ZERO };
    let mut after = a.after;
    let mut printed = 0u64;
    let mut out = std::io::stdout().lock();
    loop {
        let page = feed.page(after, wait).await?;
        for e in &page.events {
            if a.limit.is_some_and(|l| printed >= l) {
                return Ok(());
            }
            if a.json {
                writeln!(out, "{}", serde_json::to_string(e)?)?;
            } else {
                let scope = match (&e.policy, &e.checkpoint) {
                    (Some(p), Some(c)) => format!(" {p}/{c}"),
                    (Some(p), None) => format!(" {p}"),
                    _ => String::new(),
                };
                writeln!(
                    out,
                    "{:>8} {} {} {}{} {}",
                    e.seq,
                    e.created_at,
                    e.kind.as_str(),
                    e.subject,
                    scope,
                    e.data
                )?;
            }
            printed += 1;
        }
        out.flush()?;
        after = page.next;
        let caught_up = page.events.len() < store::MAX_EVENT_PAGE as usize;
        if a.limit.is_some_and(|l| printed >= l) || (caught_up && !a.follow) {
            return Ok(());
        }
    }
}
