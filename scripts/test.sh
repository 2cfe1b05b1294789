#!/usr/bin/env bash
# The test command of the README: installs what a fresh machine lacks, then runs every test.
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck source=scripts/env.sh
source scripts/env.sh
ensure_python_deps
ensure_python_package_deps
ensure_postgres
ensure_browser
# Every test that needs an external tool fails when it is missing (instead of skipping):
# store::test_support::require reads these switches.
export UFOPS_REQUIRE_PYTHON=1 UFOPS_REQUIRE_S3=1 UFOPS_REQUIRE_POSTGRES=1 UFOPS_REQUIRE_BROWSER=1
# Guard rails first: cheap next to the tests, and a red one stops before them (scripts/check.sh).
bash scripts/check.sh
cargo test --workspace --locked "$@"
# The Python package `ufops` (clients/python): built, installed and tested (pytest).
test_python_package
