#!/usr/bin/env bash
# ALOHA camera episodes at full size: scripts/gen_aloha.py writes 3 cameras
# at 480x640, 10 episodes of 400 steps, raw and JPEG-compressed (--compress); each variant is
# ingested (`ufops ingest --format aloha`), exported back (`ufops export --format aloha`) and
# compared with h5py, every dataset (dtype, shape, every value) and attribute
# (tests/python/check_aloha_roundtrip.py). The export is written from the store alone, so equality
# means the store holds every value h5py reads from the source. Prints time and sizes per stage.
# Small sizes of the same path run in CI (tests/export_cli.rs, ingest/tests/aloha).
#
# usage: scripts/aloha_full_size.sh [OUT_DIR]   (default target/aloha_full; ~11 GB raw source +
#        store + export for the raw variant: check `df -h`; needs a built ufops: cargo build --bin ufops,
#        and GNU time, Debian's `time`, for the peak RSS)
#   EPISODES / STEPS  override the size (default 10 x 400)
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
OUT=$(realpath -m "${1:-target/aloha_full}")
UFOPS=${UFOPS_BIN:-$CARGO_TARGET_DIR/debug/ufops}
EPISODES=${EPISODES:-10}
STEPS=${STEPS:-400}
size() { du -sb "$1" | awk '{ printf "%.1f MB", $1 / 1e6 }'; }
stage() { # name, command...: runs it and prints its wall time and peak RSS (GNU time's %M)
  local name=$1; shift
  local t0=$(date +%s.%N) rss="$OUT/$variant.$name.rss"
  /usr/bin/time -f %M -o "$rss" "$@" >"$OUT/$variant.$name.log" 2>&1 || { cat "$OUT/$variant.$name.log"; exit 1; }
  printf '%-10s %-9s %6.1f s  peak RSS %5d MB\n' "$variant" "$name" "$(echo "$(date +%s.%N) - $t0" | bc)" \
    "$(( $(tail -1 "$rss") / 1024 ))"
}
rm -rf "$OUT" && mkdir -p "$OUT"
for variant in raw compressed; do
  flag=""; [ $variant = compressed ] && flag="--compress"
  export UFOPS_DATA_DIR="$OUT/$variant-store"
  "$UFOPS" init >/dev/null
  stage generate python3 scripts/gen_aloha.py "$OUT/$variant-src" --episodes "$EPISODES" --steps "$STEPS" --cameras 3 $flag
  stage ingest "$UFOPS" ingest "$OUT/$variant-src" --format aloha --policy aloha-$variant --checkpoint c0
  stage export "$UFOPS" export --format aloha "$OUT/$variant-export"
  stage compare python3 tests/python/check_aloha_roundtrip.py "$OUT/$variant-src" "$OUT/$variant-export"
  echo "$variant: source $(size "$OUT/$variant-src"), store $(size "$UFOPS_DATA_DIR"), export $(size "$OUT/$variant-export"); $(tail -1 "$OUT/$variant.compare.log")"
  # The raw variant's three copies are ~33 GB: keep only the figures.
  rm -rf "$OUT/$variant-src" "$OUT/$variant-export"
done
