#!/usr/bin/env bash
# Cameras in rerun recordings: `ufops view` on a generated ALOHA dataset (scripts/gen_aloha.py, 3 cameras)
# and on the LeRobot v3.0 video fixture (fixtures/lerobot/v30_eval_video, AV1 mp4) writes every
# camera; PyPI rerun-sdk at the workspace's re_sdk version runs `rerun rrd verify` on both; each
# recording is opened in rerun's own web viewer (`rerun --serve-web FILE.rrd`, loopback) in Debian's
# headless Chromium (tests/web/rerun_web_screenshot.mjs) and screenshotted; then the ALOHA
# episodes on the labeling page (`ufops serve`, tests/web/page_screenshot.mjs: the 3-camera grid).
# Look at the PNGs.
#
# Not part of CI: rerun-sdk is a ~100 MB wheel (installed once into a cached venv by
# viewer/scripts/check_rrd.sh), and the screenshot is evidence to look at, not an assertion.
#
# usage: scripts/rerun_web_screenshot.sh [OUT_DIR]   (default target/rerun_web; needs a built ufops:
#        cargo build --bin ufops)
#   ALOHA_EPISODES / ALOHA_STEPS  size of the generated ALOHA dataset (default 2 x 40, 480x640)
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
ensure_browser
OUT=$(realpath -m "${1:-target/rerun_web}")
UFOPS=${UFOPS_BIN:-$CARGO_TARGET_DIR/debug/ufops}
VERSION=$(awk '/^name = "re_sdk"$/ { getline; gsub(/[^0-9.]/, ""); print; exit }' Cargo.lock)
RERUN_VENV=${RERUN_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/ufops/rerun-sdk-$VERSION}
rm -rf "$OUT" && mkdir -p "$OUT"
export UFOPS_DATA_DIR="$OUT/store"

"$UFOPS" init >/dev/null
python3 scripts/gen_aloha.py "$OUT/aloha" --episodes "${ALOHA_EPISODES:-2}" --steps "${ALOHA_STEPS:-40}" --cameras 3 >/dev/null
"$UFOPS" ingest "$OUT/aloha" --policy aloha --checkpoint c0
"$UFOPS" ingest fixtures/lerobot/v30_eval_video --policy lerobot-video --checkpoint c0
"$UFOPS" view --policy aloha --checkpoint c0 --out "$OUT/aloha.rrd" | tee "$OUT/aloha.view.txt"
"$UFOPS" view --policy lerobot-video --checkpoint c0 --episodes 2 --out "$OUT/lerobot_video.rrd" | tee "$OUT/lerobot_video.view.txt"
grep -q "cameras cam_high, cam_left_wrist, cam_low" "$OUT/aloha.view.txt"
grep -q "cameras images.front" "$OUT/lerobot_video.view.txt"

port=9790
for name in aloha lerobot_video; do
  # check_rrd.sh installs rerun-sdk==$VERSION once and runs `rerun rrd verify` and `rerun rrd print`.
  RERUN_SDK_VERSION=$VERSION RERUN_VENV=$RERUN_VENV viewer/scripts/check_rrd.sh "$OUT/$name.rrd" >"$OUT/$name.print.txt"
  # The wheel's binary itself: bin/rerun is a Python wrapper whose child would outlive a kill.
  "$(echo "$RERUN_VENV"/lib/python3*/site-packages/rerun_sdk/rerun_cli/rerun)" --serve-web --web-viewer-port $port --port $((port + 1)) "$OUT/$name.rrd" >"$OUT/$name.serve.log" 2>&1 &
  server=$!
  for _ in $(seq 50); do curl -sf -o /dev/null "http://127.0.0.1:$port/" && break; sleep 0.2; done
  (cd tests/web && node rerun_web_screenshot.mjs \
      "http://127.0.0.1:$port/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A$((port + 1))%2Fproxy" "$OUT/${name}_web.png" 25000)
  kill -0 "$server" || { echo "rerun --serve-web exited early:"; cat "$OUT/$name.serve.log"; exit 1; }
  kill "$server" 2>/dev/null || true; wait "$server" 2>/dev/null || true
  port=$((port + 2))
done
# The same ALOHA store on the labeling page: the 3-camera grid, screenshotted.
TOKEN=$("$UFOPS" token create --name screenshot --role labeler --json | python3 -c 'import json, sys; print(json.load(sys.stdin)["token"])')
"$UFOPS" serve --addr 127.0.0.1:$port --no-worker >"$OUT/serve.log" 2>&1 &
server=$!
for _ in $(seq 50); do curl -s -o /dev/null "http://127.0.0.1:$port/" && break; sleep 0.2; done
(cd tests/web && UFOPS_URL=http://127.0.0.1:$port UFOPS_TOKEN=$TOKEN UFOPS_POLICY=aloha OUT_PNG="$OUT/aloha_page.png" \
    node page_screenshot.mjs) | tee "$OUT/aloha_page.txt"
kill "$server" 2>/dev/null || true; wait "$server" 2>/dev/null || true
grep -q '"cameras":\["cam_high","cam_left_wrist","cam_low"\]' "$OUT/aloha_page.txt"
ls -la "$OUT"/*.png "$OUT"/*.rrd
