#!/usr/bin/env bash
# Runs every ingest fuzz target for a bounded time (default 60 s each), seeded with the fixtures.
# Usage: ingest/fuzz/run.sh [SECONDS] [TARGET...]
# Needs cargo-fuzz (installed if missing). Rust stable works with RUSTC_BOOTSTRAP=1.
set -euo pipefail
cd "$(dirname "$0")"
SECS="${1:-60}"; shift || true
TARGETS=("$@"); [ ${#TARGETS[@]} -eq 0 ] && TARGETS=(robomimic lerobot lerobot_eval mcap cdr)
FIX="${UFOPS_FIXTURES:-$(cd ../.. && pwd)/fixtures}"
command -v cargo-fuzz >/dev/null || cargo install cargo-fuzz
export RUSTC_BOOTSTRAP=1
# a target dir of its own (sanitizer builds do not mix with normal ones)
export CARGO_TARGET_DIR="${FUZZ_TARGET_DIR:-${CARGO_TARGET_DIR:-$HOME/.cache/ufops-target-ingest}/fuzz}"

seed() { # seed corpus from the fixtures
  local t=$1 d=corpus/$1; mkdir -p "$d"
  case $t in
    robomimic) cp -f "$FIX"/robomimic/lift_rollouts_lowdim.hdf5 "$d"/ 2>/dev/null || true ;;
    mcap) cp -f "$FIX"/mcap/*.mcap "$FIX"/mcap/conformance/*.mcap "$d"/ 2>/dev/null || true ;;
    lerobot)
      for ds in v30_eval_video v30_unlabeled; do
        { cat "$FIX/lerobot/$ds/meta/info.json"; printf '\0'; cat "$FIX/lerobot/$ds/data/chunk-000/file-000.parquet"; } > "$d/$ds.bin" || true
      done ;;
    lerobot_eval)
      { cat "$FIX/lerobot_eval/v04/ckpt-a/eval_info.json"; printf '\0'; cat "$FIX/lerobot_eval/v04/ckpt-a/videos/pusht_0/eval_episode_2.mp4"; } > "$d/v04.bin" || true ;;
    cdr) printf 'string name\nfloat64[] position\n\0\0\1\0\0\2\0\0\0x\0\0\0\1\0\0\0\0\0\0\0\0\0\0\0\0\0\370\77' > "$d/joint.bin" ;;
  esac
}

status=0
for t in "${TARGETS[@]}"; do
  seed "$t"
  echo "== fuzz $t for ${SECS}s"
  if ! cargo fuzz run "$t" "corpus/$t" -- -max_total_time="$SECS" -rss_limit_mb=4096 -max_len=4000000 -timeout=30; then
    echo "!! $t found a crash (see fuzz/artifacts/$t)"; status=1
  fi
done
exit $status
