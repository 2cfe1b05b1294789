//! Version spans: a row valid from one version until another replaces it (migration 0019). Every
//! read of a past version's labels and counts selects its rows with [`covers`].

/// `alias`'s span `[version_from, version_to)` covers the version bound as `p`: the SQL every
/// read of a past version's labels and counts goes through (migration 0019).
pub fn covers(alias: &str, p: &str) -> String {
    let a = if alias.is_empty() { String::new() } else { format!("{alias}.") };
    format!("{a}version_from <= {p} AND ({a}version_to IS NULL OR {a}version_to > {p})")
}
