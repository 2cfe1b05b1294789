#!/usr/bin/env bash
# The guard rails (run by scripts/test.sh, CI and the pre-commit hook in .githooks/): the
# workspace is formatted by rustfmt.toml, clippy finds nothing, and the docs build without a
# warning (broken intra-doc links included), and workspace-hack/Cargo.toml is current.
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck source=scripts/env.sh
source scripts/env.sh
cargo fmt --all --check
cargo clippy --workspace --all-targets --locked -- -D warnings
RUSTDOCFLAGS="-D warnings" cargo doc --workspace --no-deps --locked
# The Python extension's build reuses the workspace's (workspace-hack/Cargo.toml is current).
python3 scripts/workspace_hack.py --check
