//! The labeling web page and the scoreboard page of `ufops serve`, as static assets compiled into
//! the binary.
//!
//! This crate owns `web/assets/` (`index.html`, `scoreboard.html`, plain ES modules, CSS and the
//! vendored uPlot charting library) and the routes that serve them: `GET /` (redirect), `GET /ui` and
//! `GET /ui/{file}`, with their content types, cache headers (`no-cache` + a content `ETag` for
//! the page's own files, one year `immutable` for the versioned vendor files) and a strict
//! Content-Security-Policy. It holds no data and needs no token: the page signs in through
//! `POST /ui/session` (owned by the `api` crate) and then calls the `/v1` API with its cookie.
//! Nothing is fetched from the network at run time; there is no build step.

use axum::extract::Path;
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Redirect, Response};
use axum::routing::get;
use axum::Router;

/// One file of the page.
pub struct Asset {
    /// The name under `/ui/`.
    pub name: &'static str,
    pub body: &'static [u8],
    pub content_type: &'static str,
    /// Versioned file name (vendor): cache for a year; otherwise revalidate with the ETag.
    pub immutable: bool,
    /// FNV-1a 64 of the body, computed at compile time.
    pub hash: u64,
}

const fn fnv1a(b: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut i = 0;
    while i < b.len() {
        h ^= b[i] as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
        i += 1;
    }
    h
}

macro_rules! asset {
    ($name:literal, $ctype:literal, $immutable:literal) => {{
        const BODY: &[u8] = include_bytes!(concat!(env!("CARGO_MANIFEST_DIR"), "/assets/", $name));
        Asset { name: $name, body: BODY, content_type: $ctype, immutable: $immutable, hash: fnv1a(BODY) }
    }};
}

/// Every file of the page (a fixed list: nothing else under `/ui/` exists).
pub static ASSETS: &[Asset] = &[
    asset!("index.html", "text/html; charset=utf-8", false),
    asset!("style.css", "text/css; charset=utf-8", false),
    asset!("app.js", "text/javascript; charset=utf-8", false),
    asset!("dom.js", "text/javascript; charset=utf-8", false),
    asset!("state.js", "text/javascript; charset=utf-8", false),
    asset!("signin.js", "text/javascript; charset=utf-8", false),
    asset!("queue.js", "text/javascript; charset=utf-8", false),
    asset!("episode.js", "text/javascript; charset=utf-8", false),
    asset!("labeling.js", "text/javascript; charset=utf-8", false),
    asset!("keys.js", "text/javascript; charset=utf-8", false),
    asset!("api.js", "text/javascript; charset=utf-8", false),
    asset!("player.js", "text/javascript; charset=utf-8", false),
    asset!("cameras.js", "text/javascript; charset=utf-8", false),
    asset!("plots.js", "text/javascript; charset=utf-8", false),
    asset!("consensus.js", "text/javascript; charset=utf-8", false),
    asset!("review_queue.js", "text/javascript; charset=utf-8", false),
    asset!("takeovers.js", "text/javascript; charset=utf-8", false),
    asset!("steering.js", "text/javascript; charset=utf-8", false),
    asset!("scoreboard.html", "text/html; charset=utf-8", false),
    asset!("scoreboard.js", "text/javascript; charset=utf-8", false),
    asset!("vendor/uPlot-1.6.32.iife.min.js", "text/javascript; charset=utf-8", true),
    asset!("vendor/uPlot-1.6.32.min.css", "text/css; charset=utf-8", true),
    asset!("vendor/uPlot-LICENSE.txt", "text/plain; charset=utf-8", true),
];

/// The asset called `name` (relative to `/ui/`), if any.
pub fn asset(name: &str) -> Option<&'static Asset> {
    let name = if name.is_empty() { "index.html" } else { name };
    ASSETS.iter().find(|a| a.name == name)
}

const CSP: &str = "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; \
    media-src 'self' blob:; connect-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'";

fn respond(a: &Asset, headers: &HeaderMap) -> Response {
    let etag = format!("\"{:016x}\"", a.hash);
    let cache = if a.immutable { "public, max-age=31536000, immutable" } else { "no-cache" };
    let fresh = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim().trim_start_matches("W/") == etag || t.trim() == "*"));
    let mut resp = if fresh { StatusCode::NOT_MODIFIED.into_response() } else { a.body.into_response() };
    let h = resp.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(a.content_type));
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static(cache));
    if let Ok(v) = HeaderValue::from_str(&etag) {
        h.insert(header::ETAG, v);
    }
    h.insert(header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff"));
    h.insert(header::REFERRER_POLICY, HeaderValue::from_static("no-referrer"));
    if a.name.ends_with(".html") {
        h.insert(header::CONTENT_SECURITY_POLICY, HeaderValue::from_static(CSP));
        h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    }
    resp
}

fn not_found(name: &str) -> Response {
    let detail = format!("no page asset {name:?}");
    let body = format!(
        "{{\"type\":\"urn:ufops:problem:not-found\",\"title\":\"Not Found\",\"status\":404,\"detail\":{}}}",
        json_string(&detail)
    );
    (StatusCode::NOT_FOUND, [(header::CONTENT_TYPE, "application/problem+json")], body).into_response()
}

fn json_string(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if (c as u32) < 0x20 => out.push_str(&format!("\\u{:04x}", c as u32)),
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

async fn index(headers: HeaderMap) -> Response {
    match asset("index.html") {
        Some(a) => respond(a, &headers),
        None => not_found("index.html"),
    }
}

async fn file(Path(name): Path<String>, headers: HeaderMap) -> Response {
    match asset(&name) {
        Some(a) => respond(a, &headers),
        None => not_found(&name),
    }
}

/// `GET /` → `/ui/`, `GET /ui` → `/ui/`, `GET /ui/` (the page) and `GET /ui/{file}`.
/// Open routes (no token): the assets hold no data. `/ui/session` is not served here.
pub fn router<S: Clone + Send + Sync + 'static>() -> Router<S> {
    Router::new()
        .route("/", get(|| async { Redirect::to("/ui/") }))
        .route("/ui", get(|| async { Redirect::to("/ui/") }))
        .route("/ui/", get(index))
        .route("/ui/{*file}", get(file))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn assets_exist_and_have_types() {
        for a in ASSETS {
            assert!(!a.body.is_empty(), "{} is empty", a.name);
            assert!(!a.content_type.is_empty());
        }
        assert!(asset("").is_some());
        assert!(asset("../Cargo.toml").is_none());
        assert!(asset("vendor/uPlot-1.6.32.iife.min.js").unwrap().immutable);
    }

    #[test]
    fn every_imported_module_is_served() {
        for a in ASSETS.iter().filter(|a| a.name.ends_with(".js") && !a.name.starts_with("vendor/")) {
            let text = std::str::from_utf8(a.body).expect("utf-8");
            for line in text.lines().filter(|l| l.starts_with("import ")) {
                let Some(module) = line.split("from './").nth(1).and_then(|r| r.split('\'').next()) else {
                    continue;
                };
                assert!(asset(module).is_some(), "{} imports {module}, which is not in ASSETS", a.name);
            }
        }
    }

    #[test]
    fn page_loads_nothing_from_the_network() {
        for a in ASSETS.iter().filter(|a| !a.name.starts_with("vendor/")) {
            // The SVG namespace is a name, not a URL anything fetches.
            let text = std::str::from_utf8(a.body).expect("utf-8").replace("http://www.w3.org/2000/svg", "");
            assert!(
                !text.contains("http://") && !text.contains("https://"),
                "{} references a remote URL",
                a.name
            );
        }
    }
}
