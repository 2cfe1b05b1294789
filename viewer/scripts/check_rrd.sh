#!/usr/bin/env bash
# Checks a .rrd written by the viewer crate with the official rerun-sdk from PyPI, pinned to the
# same version as the re_sdk crate we write with: `rerun rrd verify` then `rerun rrd print`.
#
# usage: viewer/scripts/check_rrd.sh FILE.rrd
#   RERUN_SDK_VERSION  pinned version (default 0.36.3 = re_sdk in viewer/Cargo.toml)
#   RERUN_VENV         venv to install into (default ~/.cache/ufops/rerun-sdk-$RERUN_SDK_VERSION)
#   PYTHON             interpreter used to create the venv (default python3)
set -euo pipefail

if [ $# -ne 1 ]; then
    echo "usage: $0 FILE.rrd" >&2
    exit 2
fi
FILE=$1
if [ ! -f "$FILE" ]; then
    echo "check_rrd: no such file: $FILE" >&2
    exit 2
fi

VERSION=${RERUN_SDK_VERSION:-0.36.3}
VENV=${RERUN_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/ufops/rerun-sdk-$VERSION}
PY=${PYTHON:-python3}

installed_version() {
    "$VENV/bin/python" -c 'import importlib.metadata as m; print(m.version("rerun-sdk"))' 2>/dev/null || true
}

if [ "$(installed_version)" != "$VERSION" ]; then
    echo "check_rrd: installing rerun-sdk==$VERSION into $VENV" >&2
    mkdir -p "$(dirname "$VENV")"
    if ! "$PY" -m venv "$VENV" >&2; then
        echo "check_rrd: ERROR: cannot create a venv with $PY (install python3-venv)" >&2
        exit 3
    fi
    if ! "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check "rerun-sdk==$VERSION" >&2; then
        echo "check_rrd: ERROR: pip could not install rerun-sdk==$VERSION from PyPI" \
             "(no network, or no wheel for this platform/python); cannot verify $FILE" >&2
        exit 3
    fi
fi
if [ "$(installed_version)" != "$VERSION" ]; then
    echo "check_rrd: ERROR: rerun-sdk $VERSION not importable from $VENV after install" >&2
    exit 3
fi

RERUN="$VENV/bin/rerun"
echo "== $("$RERUN" --version)"
echo "== rerun rrd verify $FILE"
"$RERUN" rrd verify "$FILE"
echo "== rerun rrd print $FILE"
"$RERUN" rrd print "$FILE"
