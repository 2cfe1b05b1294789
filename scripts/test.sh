#!/usr/bin/env bash
# The test command of the README: installs what a fresh machine lacks, then runs every test.
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck source=scripts/env.sh
source scripts/env.sh
ensure_python_deps
ensure_postgres
ensure_browser
export UFOPS_REQUIRE_BROWSER=1
# The numpy reference of the verifier (trainer/tests/parity.rs, tests/verifier_parity.rs) must run.
export UFOPS_REQUIRE_PYTHON=1
cargo test --workspace --locked "$@"
