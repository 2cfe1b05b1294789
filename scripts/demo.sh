#!/usr/bin/env bash
# The main job of the README: the paper's pedagogical experiment end to end on the embedded store.
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck source=scripts/env.sh
source scripts/env.sh
cargo run --release --locked --bin ufops -- demo "$@"
