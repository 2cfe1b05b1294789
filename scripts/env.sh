# Shared set-up for the scripts: a cargo target dir reused across clones, and the few things a
# fresh machine lacks (Python packages for interop tests; a running Postgres).

# Reuse a target dir outside the clone when one exists (CI clones afresh every time).
if [ -z "${CARGO_TARGET_DIR:-}" ]; then
  export CARGO_TARGET_DIR="${HOME}/.cache/ufops-target"
  mkdir -p "$CARGO_TARGET_DIR"
fi

ensure_python_deps() {
  if ! python3 -c 'import numpy, pyarrow, safetensors, duckdb' 2>/dev/null; then
    python3 -m pip install -q --disable-pip-version-check -r tests/python/requirements.txt
  fi
}

ensure_postgres() {
  # Our machines run Postgres on 127.0.0.1:5432 (database "test", trust auth); start it if stopped.
  if command -v pg_isready >/dev/null && ! pg_isready -h 127.0.0.1 -p 5432 -q; then
    if command -v pg_ctlcluster >/dev/null; then
      pg_ctlcluster --skip-systemctl-redirect "$(ls /etc/postgresql | head -1)" main start || true
    fi
  fi
}
