//! Loading a verifier from a `ufops serve` API (feature `http`): a robot pulls
//! `POLICY/CHECKPOINT/KIND@ALIAS` (or an artifact id) with a bearer token.
//!
//! The alias is resolved to an artifact id once, and every file is then fetched by that id, so an
//! alias moved mid-download cannot mix two artifacts. The id is the sha256 prefix of
//! `manifest.json`, and each file is checked against the manifest, so a wrong or corrupted
//! download is refused, never loaded.

use crate::error::{Result, SteerError};
use std::time::Duration;
use verifier::{artifact_id, is_plain_name, Manifest, Verifier, VerifierError, MANIFEST_FILE};

/// Largest file accepted from the server (a low-dim verifier is a few MB).
const MAX_FILE_BYTES: u64 = 1 << 30;

/// Where to fetch from: the API's base URL (`http://host:8080`) and a token with role viewer or above.
#[derive(Debug, Clone)]
pub struct ApiSource {
    pub base_url: String,
    pub token: String,
    pub timeout: Duration,
}

impl ApiSource {
    pub fn new(base_url: impl Into<String>, token: impl Into<String>) -> Self {
        ApiSource {
            base_url: base_url.into().trim_end_matches('/').to_string(),
            token: token.into(),
            timeout: Duration::from_secs(60),
        }
    }
}

fn is_plain(s: &str) -> bool {
    is_plain_name(s)
}

/// The API path of the artifact record: `POLICY/CHECKPOINT/KIND@ALIAS` → the alias route,
/// anything else → an artifact id.
fn record_path(reference: &str) -> Result<String> {
    let parts: Vec<&str> = reference.split('/').collect();
    match parts.as_slice() {
        [policy, checkpoint, kind_at_alias]
            if [policy, checkpoint, kind_at_alias].iter().all(|p| is_plain(p)) =>
        {
            if !kind_at_alias.contains('@') {
                return Err(SteerError::Input(format!(
                    "{reference:?}: expected POLICY/CHECKPOINT/KIND@ALIAS"
                )));
            }
            Ok(format!("/v1/policies/{policy}/checkpoints/{checkpoint}/verifiers/{kind_at_alias}"))
        }
        [id] if is_plain(id) && !id.contains('@') => Ok(format!("/v1/artifacts/{id}")),
        _ => Err(SteerError::Input(format!(
            "{reference:?} is neither an artifact id nor POLICY/CHECKPOINT/KIND@ALIAS"
        ))),
    }
}

struct Client {
    agent: ureq::Agent,
    src: ApiSource,
}

impl Client {
    fn get(&self, path: &str) -> Result<Vec<u8>> {
        let url = format!("{}{path}", self.src.base_url);
        let err = |msg: String| SteerError::Http(format!("GET {url}: {msg}"));
        let mut resp = self
            .agent
            .get(&url)
            .header("Authorization", &format!("Bearer {}", self.src.token))
            .call()
            .map_err(|e| err(e.to_string()))?;
        let status = resp.status().as_u16();
        let body = resp
            .body_mut()
            .with_config()
            .limit(MAX_FILE_BYTES)
            .read_to_vec()
            .map_err(|e| err(format!("reading the body: {e}")))?;
        if !(200..300).contains(&status) {
            // The API answers problem+json: its `detail` says what is wrong.
            let detail = serde_json::from_slice::<serde_json::Value>(&body)
                .ok()
                .and_then(|v| v.get("detail").and_then(|d| d.as_str()).map(str::to_string))
                .unwrap_or_else(|| String::from_utf8_lossy(&body[..body.len().min(300)]).into_owned());
            return Err(err(format!("status {status}: {detail}")));
        }
        Ok(body)
    }
}

/// An artifact fetched over HTTP, every file checked against its manifest.
#[derive(Debug, Clone)]
pub struct FetchedArtifact {
    pub id: String,
    /// `manifest.json` first, then the files it lists, in its order.
    pub files: Vec<(String, Vec<u8>)>,
}

impl FetchedArtifact {
    fn file(&self, name: &str) -> Option<&[u8]> {
        self.files.iter().find(|(n, _)| n == name).map(|(_, b)| b.as_slice())
    }

    /// The verifier, loaded through the core from the fetched (and re-checked) files.
    pub fn verifier(&self) -> Result<Verifier> {
        let manifest =
            self.file(MANIFEST_FILE).ok_or_else(|| SteerError::Http("no manifest.json fetched".into()))?;
        let v = Verifier::load_with(manifest, |name| {
            self.file(name)
                .map(<[u8]>::to_vec)
                .ok_or_else(|| VerifierError::Fetch { file: name.into(), message: "not fetched".into() })
        })?;
        Ok(v)
    }

    /// Writes the files into `dir` (an artifact directory [`Verifier::load_dir`] reads).
    pub fn write_to(&self, dir: &std::path::Path) -> Result<()> {
        let io = |p: &std::path::Path, e: std::io::Error| VerifierError::Io {
            path: p.display().to_string(),
            source: e,
        };
        std::fs::create_dir_all(dir).map_err(|e| io(dir, e))?;
        for (name, bytes) in &self.files {
            let p = dir.join(name);
            std::fs::write(&p, bytes).map_err(|e| io(&p, e))?;
        }
        Ok(())
    }
}

/// Fetches `reference` (an artifact id or `POLICY/CHECKPOINT/KIND@ALIAS`) from a ufops API:
/// resolves it to an artifact id, fetches `manifest.json`, checks that it hashes to that id,
/// then fetches and checks every file it lists.
pub fn fetch_artifact(src: &ApiSource, reference: &str) -> Result<FetchedArtifact> {
    let path = record_path(reference)?;
    let agent: ureq::Agent = ureq::Agent::config_builder()
        .timeout_global(Some(src.timeout))
        .http_status_as_error(false)
        .build()
        .into();
    let client = Client { agent, src: src.clone() };
    let record: serde_json::Value = serde_json::from_slice(&client.get(&path)?)
        .map_err(|e| SteerError::Http(format!("{path}: the artifact record is not JSON: {e}")))?;
    let id = record
        .get("id")
        .and_then(|v| v.as_str())
        .filter(|id| is_plain(id))
        .ok_or_else(|| SteerError::Http(format!("{path}: the artifact record has no valid id")))?
        .to_string();
    let manifest = client.get(&format!("/v1/artifacts/{id}/files/{MANIFEST_FILE}"))?;
    let actual = artifact_id(&manifest);
    if actual != id {
        return Err(VerifierError::HashMismatch { file: MANIFEST_FILE.into(), expected: id, actual }.into());
    }
    // The core's checks: schema, plain file names, each file's sha256.
    let m = Manifest::parse(&manifest)?;
    let mut files = vec![(MANIFEST_FILE.to_string(), manifest.clone())];
    for name in m.files.keys() {
        let bytes = client.get(&format!("/v1/artifacts/{id}/files/{name}"))?;
        m.check(name, &bytes)?;
        files.push((name.clone(), bytes));
    }
    Ok(FetchedArtifact { id, files })
}

/// Loads a verifier from a ufops API (see [`fetch_artifact`]).
pub fn load_verifier(src: &ApiSource, reference: &str) -> Result<Verifier> {
    fetch_artifact(src, reference)?.verifier()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn references_map_to_api_paths() {
        assert_eq!(
            record_path("nav/base/classifier@latest").unwrap(),
            "/v1/policies/nav/checkpoints/base/verifiers/classifier@latest"
        );
        assert_eq!(record_path("0123abcd0123abcd").unwrap(), "/v1/artifacts/0123abcd0123abcd");
        for bad in ["", "a/b", "a/b/c", "../x/y@z", "a/b/c@d/e", "a b/c/d@e", "x@y"] {
            assert!(record_path(bad).is_err(), "{bad:?} accepted");
        }
    }

    #[test]
    fn unreachable_server_is_a_clear_error() {
        // Port 9 (discard) on loopback: nothing listens there on our machines.
        let src = ApiSource { timeout: Duration::from_secs(2), ..ApiSource::new("http://127.0.0.1:9", "t") };
        match load_verifier(&src, "p/c/classifier@latest") {
            Err(SteerError::Http(msg)) => assert!(msg.contains("127.0.0.1:9"), "{msg}"),
            Err(e) => panic!("unexpected error {e}"),
            Ok(_) => panic!("loaded from nowhere"),
        }
    }
}
