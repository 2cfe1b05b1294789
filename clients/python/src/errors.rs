//! The exception hierarchy of the package (`ufops.errors` re-exports it) and the mapping of the
//! Rust crates' errors onto it, each keeping the Rust message.
//!
//! ```text
//! UfopsError
//! ├── ArtifactError        an artifact that is malformed or does not fit this client
//! │   └── IntegrityError   a file whose sha256 is not the manifest's, corrupt store data
//! ├── FetchError           talking to `ufops serve` failed (connection, status)
//! │   └── AuthError        401 / 403: the token is missing, wrong or lacks the role
//! ├── NotFoundError        an unknown artifact, alias, episode, split or version
//! ├── StoreError           the catalog or the object storage failed
//! └── ConflictError        (ufops.Client, in Python) a label changed since it was read
//! ```
//! Bad arrays or arguments are `TypeError` (dtype, type) and `ValueError` (shape, value).

use pyo3::create_exception;
use pyo3::exceptions::{PyException, PyValueError};
use pyo3::prelude::*;

create_exception!(
    ufops,
    UfopsError,
    PyException,
    "Base class of every error ufops raises (bad inputs are TypeError / ValueError)."
);
create_exception!(
    ufops,
    ArtifactError,
    UfopsError,
    "A verifier artifact is malformed or not one this client can run."
);
create_exception!(
    ufops,
    IntegrityError,
    ArtifactError,
    "A file does not hash to the sha256 its manifest (or the catalog) records."
);
create_exception!(ufops, FetchError, UfopsError, "Fetching from a `ufops serve` API failed.");
create_exception!(ufops, AuthError, FetchError, "The API refused the token (HTTP 401 or 403).");
create_exception!(ufops, NotFoundError, UfopsError, "No such artifact, alias, episode, split or version.");
create_exception!(ufops, StoreError, UfopsError, "The store's catalog or object storage failed.");

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("UfopsError", py.get_type::<UfopsError>())?;
    m.add("ArtifactError", py.get_type::<ArtifactError>())?;
    m.add("IntegrityError", py.get_type::<IntegrityError>())?;
    m.add("FetchError", py.get_type::<FetchError>())?;
    m.add("AuthError", py.get_type::<AuthError>())?;
    m.add("NotFoundError", py.get_type::<NotFoundError>())?;
    m.add("StoreError", py.get_type::<StoreError>())?;
    Ok(())
}

pub fn from_verifier(e: verifier::VerifierError) -> PyErr {
    use verifier::VerifierError as E;
    let msg = e.to_string();
    match e {
        E::Input(_) => PyValueError::new_err(msg),
        E::HashMismatch { .. } => IntegrityError::new_err(msg),
        E::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => NotFoundError::new_err(msg),
        E::Io { .. } | E::Fetch { .. } => FetchError::new_err(msg),
        _ => ArtifactError::new_err(msg),
    }
}

pub fn from_steer(e: steer::SteerError) -> PyErr {
    match e {
        steer::SteerError::Verifier(v) => from_verifier(v),
        steer::SteerError::Input(_) => PyValueError::new_err(e.to_string()),
        steer::SteerError::Http(ref m) => {
            // steer's HTTP errors read "GET URL: status NNN: detail" (the API's problem+json detail).
            let status =
                m.split("status ").nth(1).and_then(|s| s.get(..3)).and_then(|s| s.parse::<u16>().ok());
            let msg = e.to_string();
            match status {
                Some(401 | 403) => AuthError::new_err(msg),
                Some(404) => NotFoundError::new_err(msg),
                _ => FetchError::new_err(msg),
            }
        }
        steer::SteerError::Model(_) => UfopsError::new_err(e.to_string()),
    }
}

pub fn from_store(e: store::StoreError) -> PyErr {
    use store::StoreError as E;
    let msg = e.to_string();
    match e {
        E::NotFound { .. } => NotFoundError::new_err(msg),
        E::Invalid(_) => PyValueError::new_err(msg),
        E::Corrupt(_) => IntegrityError::new_err(msg),
        _ => StoreError::new_err(msg),
    }
}
