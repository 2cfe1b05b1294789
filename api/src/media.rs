//! Serving a stored object with HTTP range requests (RFC 9110 §14): `206 Partial Content` with
//! `Content-Range` for one satisfiable range, `416` for an unsatisfiable one, the whole object
//! otherwise. Whole objects are streamed in chunks, never loaded at once.

use crate::error::{ApiError, ApiResult};
use axum::body::Body;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::Response;
use store::Store;

const CHUNK: u64 = 4 << 20;

fn content_type(path: &str) -> &'static str {
    match path.rsplit('.').next().unwrap_or("") {
        "mp4" | "m4v" => "video/mp4",
        "webm" => "video/webm",
        "mkv" => "video/x-matroska",
        "mov" => "video/quicktime",
        "avi" => "video/x-msvideo",
        "png" => "image/png",
        "jpg" | "jpeg" => "image/jpeg",
        "parquet" => "application/vnd.apache.parquet",
        "json" => "application/json",
        "hdf5" | "h5" => "application/x-hdf5",
        _ => "application/octet-stream",
    }
}

/// A `Range` header no byte of the representation satisfies (answered with 416).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Unsatisfiable;

/// Parses a single `bytes=` range against `size`. `Ok(None)`: no usable range (serve it all).
pub fn parse_range(value: &str, size: u64) -> Result<Option<(u64, u64)>, Unsatisfiable> {
    let Some(spec) = value.trim().strip_prefix("bytes=") else { return Ok(None) };
    if spec.contains(',') {
        return Ok(None); // multiple ranges: we answer with the whole representation
    }
    let Some((a, b)) = spec.trim().split_once('-') else { return Ok(None) };
    let (a, b) = (a.trim(), b.trim());
    let (start, end) = if a.is_empty() {
        let n: u64 = b.parse().map_err(|_| Unsatisfiable)?;
        if n == 0 {
            return Err(Unsatisfiable);
        }
        (size.saturating_sub(n), size.saturating_sub(1))
    } else {
        let start: u64 = a.parse().map_err(|_| Unsatisfiable)?;
        let end = if b.is_empty() {
            size.saturating_sub(1)
        } else {
            b.parse::<u64>().map_err(|_| Unsatisfiable)?.min(size.saturating_sub(1))
        };
        (start, end)
    };
    if size == 0 || start >= size || start > end {
        return Err(Unsatisfiable);
    }
    Ok(Some((start, end)))
}

/// Serves `path` (its size from the catalog when known, else asked of the object store).
pub async fn serve_object(
    store: &Store,
    path: &str,
    known_size: Option<u64>,
    range: Option<&HeaderValue>,
) -> ApiResult<Response> {
    let size = match known_size {
        Some(s) => s,
        None => store.object_size(path).await?,
    };
    let ctype = content_type(path);
    let range = match range.and_then(|v| v.to_str().ok()) {
        None => None,
        Some(v) => match parse_range(v, size) {
            Ok(r) => r,
            Err(Unsatisfiable) => {
                let mut e = ApiError::new(
                    StatusCode::RANGE_NOT_SATISFIABLE,
                    "range-not-satisfiable",
                    format!("range {v:?} is outside the object's {size} bytes"),
                );
                e.headers.push((
                    header::CONTENT_RANGE,
                    HeaderValue::from_str(&format!("bytes */{size}")).expect("ascii"),
                ));
                return Err(e);
            }
        },
    };
    let mut builder =
        Response::builder().header(header::CONTENT_TYPE, ctype).header(header::ACCEPT_RANGES, "bytes");
    let (status, start, end) = match range {
        Some((s, e)) => {
            builder = builder.header(header::CONTENT_RANGE, format!("bytes {s}-{e}/{size}"));
            (StatusCode::PARTIAL_CONTENT, s, e + 1)
        }
        None => (StatusCode::OK, 0, size),
    };
    builder = builder.status(status).header(header::CONTENT_LENGTH, end - start);
    let body = if end - start <= CHUNK {
        Body::from(if end > start {
            store.get_object_range(path, start..end).await?
        } else {
            bytes::Bytes::new()
        })
    } else {
        let store = store.clone();
        let path = path.to_string();
        let chunks = futures::stream::unfold(start, move |pos| {
            let store = store.clone();
            let path = path.clone();
            async move {
                if pos >= end {
                    return None;
                }
                let next = (pos + CHUNK).min(end);
                Some((store.get_object_range(&path, pos..next).await, next))
            }
        });
        Body::from_stream(chunks)
    };
    builder.body(body).map_err(|e| ApiError::internal(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::{parse_range, Unsatisfiable};
    #[test]
    fn ranges() {
        assert_eq!(parse_range("bytes=0-9", 100), Ok(Some((0, 9))));
        assert_eq!(parse_range("bytes=90-", 100), Ok(Some((90, 99))));
        assert_eq!(parse_range("bytes=-10", 100), Ok(Some((90, 99))));
        assert_eq!(parse_range("bytes=50-500", 100), Ok(Some((50, 99))));
        assert_eq!(parse_range("bytes=100-", 100), Err(Unsatisfiable));
        assert_eq!(parse_range("bytes=5-2", 100), Err(Unsatisfiable));
        assert_eq!(parse_range("bytes=0-1,5-6", 100), Ok(None));
        assert_eq!(parse_range("items=0-1", 100), Ok(None));
    }
}
