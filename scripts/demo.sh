#!/usr/bin/env bash
# The main job of the README: the paper's pedagogical experiment end to end on the embedded store.
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck source=scripts/env.sh
source scripts/env.sh
# The dev profile optimises dependencies and the numeric crates and shares its build with the tests.
cargo run --locked --bin ufops -- demo "$@"
