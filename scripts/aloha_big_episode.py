#!/usr/bin/env python3
"""Memory and throughput of `ufops ingest --format aloha` on one ~2 GB ALOHA episode: peak RSS
must not depend on the episode's length (the cameras stream to the store a page at a time).

Writes one episode of 3 raw cameras at 480x640 (724 steps: 2.0 GB of frames) twice under
target/aloha_big/ (generated data, never in git):

    raw/episode_0.hdf5    the frames stored raw (chunked a frame per chunk), ~2 GB on disk
    gzip/episode_0.hdf5   the same arrays gzip-compressed (level 4): small on disk, as synthetic
                          frames compress (smooth gradients and moving soft blobs)

then, for each: h5py reading the same datasets (cameras a 64-frame slice at a time, qpos, qvel,
effort, action) for the reference throughput, and `/usr/bin/time -v ufops ingest --format aloha`
into a fresh store for the ingest's wall time and peak RSS. Throughput is MB of raw frames per
second; the ratio is ingest / h5py, both in the same run. With `--export`, the stored episode is
also written back (`/usr/bin/time -v ufops export --format aloha`: its wall time and peak RSS)
and compared with the source under h5py (tests/python/check_aloha_roundtrip.py). Results go to
target/aloha_big/results.json and are printed as a table.

    python3 scripts/aloha_big_episode.py [--ufops PATH] [--steps 724] [--export] [--keep]

`--ufops` defaults to the shared target dir's debug binary (`cargo build -p ufops` first; a
release build is `cargo build --release -p ufops` and `--ufops $CARGO_TARGET_DIR/release/ufops`).
"""

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time

import h5py
import numpy as np

H, W, CAMS = 480, 640, ["cam_high", "cam_left_wrist", "cam_right_wrist"]
SLICE = 64


def frames(t0, n, steps, cam):
    """(n, H, W, 3) uint8 frames t0..t0+n of camera `cam`: a colour gradient and two soft blobs
    moving along smooth paths, drawn at 1/16 resolution and scaled up (16x16 blocks), with no
    noise: gzip makes them small, as it does a camera's flat backgrounds."""
    h, w = H // 16, W // 16
    yy = (np.arange(h, dtype=np.float32) / h)[:, None]
    xx = (np.arange(w, dtype=np.float32) / w)[None, :]
    base = np.stack(
        [
            np.broadcast_to(0.35 + 0.3 * xx + 0.05 * cam, (h, w)),
            np.broadcast_to(0.3 + 0.35 * yy, (h, w)),
            0.45 + 0.2 * (1 - xx) * yy,
        ],
        axis=-1,
    )
    out = np.empty((n, H, W, 3), dtype=np.uint8)
    for k in range(n):
        s = (t0 + k) / max(steps - 1, 1)
        img = base.copy()
        for b, col in enumerate([(0.9, 0.2, 0.1), (0.1, 0.3, 0.9)]):
            cy = 0.5 + 0.3 * np.sin(2 * np.pi * s + b + cam)
            cx = 0.5 + 0.3 * np.cos(2 * np.pi * s + 2 * b + cam)
            a = (np.exp(-((yy - cy) ** 2) / 0.02) * np.exp(-((xx - cx) ** 2) / 0.02))[..., None]
            img += (np.array(col, dtype=np.float32) - img) * a
        small = np.clip(img * 255.0, 0, 255).astype(np.uint8)
        out[k] = small.repeat(16, axis=0).repeat(16, axis=1)
    return out


def write_episode(path, steps, gzip):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    rng = np.random.default_rng(0)
    t = np.linspace(0, 1, steps)[:, None]
    qpos = np.sin(2 * np.pi * rng.uniform(0.5, 2, 14) * t + rng.uniform(0, 6, 14)).astype(np.float32)
    comp = {"compression": "gzip", "compression_opts": 4} if gzip else {}
    with h5py.File(path, "w") as f:
        f.attrs["sim"] = False
        obs = f.create_group("observations")
        obs.create_dataset("qpos", data=qpos)
        obs.create_dataset("qvel", data=np.gradient(qpos, axis=0).astype(np.float32))
        obs.create_dataset("effort", data=(qpos * 0.5).astype(np.float32))
        f.create_dataset("action", data=(qpos + 0.01).astype(np.float32))
        images = obs.create_group("images")
        for k, cam in enumerate(CAMS):
            d = images.create_dataset(cam, (steps, H, W, 3), dtype="uint8", chunks=(1, H, W, 3), **comp)
            for t0 in range(0, steps, SLICE):
                n = min(SLICE, steps - t0)
                d[t0 : t0 + n] = frames(t0, n, steps, k)


def h5py_read(path):
    """Seconds to read every dataset the ingest reads, and the camera bytes read."""
    start = time.perf_counter()
    frame_bytes = 0
    with h5py.File(path, "r") as f:
        for k in ["observations/qpos", "observations/qvel", "observations/effort", "action"]:
            f[k][...]
        for cam in CAMS:
            d = f[f"observations/images/{cam}"]
            for t0 in range(0, d.shape[0], SLICE):
                frame_bytes += d[t0 : t0 + SLICE].nbytes
    return time.perf_counter() - start, frame_bytes


def ingest(ufops, path, store):
    shutil.rmtree(store, ignore_errors=True)
    subprocess.run([ufops, "--data-dir", store, "init"], check=True, capture_output=True)
    cmd = ["/usr/bin/time", "-v", ufops, "--data-dir", store, "ingest", path, "--format", "aloha",
           "--policy", "act", "--checkpoint", "big"]
    start = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if r.returncode != 0:
        sys.exit(f"ufops ingest failed:\n{r.stdout}\n{r.stderr}")
    rss_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", r.stderr).group(1))
    return wall, rss_kb * 1024, " ".join(cmd[2:])


def timed(cmd):
    """Runs `cmd` under GNU time: (wall seconds, peak RSS bytes); exits on failure."""
    start = time.perf_counter()
    r = subprocess.run(["/usr/bin/time", "-v", *cmd], capture_output=True, text=True)
    wall = time.perf_counter() - start
    if r.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{r.stdout}\n{r.stderr}")
    rss_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", r.stderr).group(1))
    return wall, rss_kb * 1024


def export(ufops, store, src_dir, out):
    """Exports the store as ALOHA to `out` and compares it with the source folder under h5py."""
    shutil.rmtree(out, ignore_errors=True)
    cmd = [ufops, "--data-dir", store, "export", out, "--format", "aloha"]
    wall, rss = timed(cmd)
    check = os.path.join(os.path.dirname(__file__), "..", "tests", "python", "check_aloha_roundtrip.py")
    r = subprocess.run([sys.executable, check, src_dir, out], capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"the export differs from the source:\n{r.stdout}\n{r.stderr}")
    return wall, rss, " ".join(cmd[1:]), r.stdout.strip()


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    target = os.environ.get("CARGO_TARGET_DIR", os.path.expanduser("~/.cache/ufops-target"))
    p.add_argument("--ufops", default=os.path.join(target, "debug", "ufops"))
    p.add_argument("--steps", type=int, default=724, help="724 steps x 3 cameras x 480x640x3 = 2.0 GB")
    p.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "..", "target", "aloha_big"))
    p.add_argument("--keep", action="store_true", help="keep the generated files and stores")
    p.add_argument("--export", action="store_true", help="also export the episode back and measure it")
    a = p.parse_args()
    out = os.path.abspath(a.out)
    results = []
    for variant, gzip in [("raw", False), ("gzip", True)]:
        path = os.path.join(out, variant, "episode_0.hdf5")
        if not os.path.exists(path):
            t = time.perf_counter()
            write_episode(path, a.steps, gzip)
            print(f"wrote {path} ({os.path.getsize(path) / 1e6:.1f} MB) in {time.perf_counter() - t:.0f} s")
        h5_s, frame_bytes = h5py_read(path)
        wall, rss, cmd = ingest(a.ufops, path, os.path.join(out, f"store_{variant}"))
        r = {
            "variant": variant,
            "file_mb": os.path.getsize(path) / 1e6,
            "frames_mb": frame_bytes / 1e6,
            "h5py_s": h5_s,
            "h5py_mb_s": frame_bytes / 1e6 / h5_s,
            "ingest_s": wall,
            "ingest_mb_s": frame_bytes / 1e6 / wall,
            "ratio": (frame_bytes / wall) / (frame_bytes / h5_s),
            "peak_rss_mb": rss / 1e6,
            "command": cmd,
        }
        if a.export:
            store = os.path.join(out, f"store_{variant}")
            exp = os.path.join(out, f"export_{variant}")
            wall, rss, cmd, check = export(a.ufops, store, os.path.dirname(path), exp)
            r.update(export_s=wall, export_peak_rss_mb=rss / 1e6, export_command=cmd, export_check=check)
            if not a.keep:
                shutil.rmtree(exp, ignore_errors=True)
        results.append(r)
        print(json.dumps(r))
        if not a.keep:
            shutil.rmtree(os.path.join(out, f"store_{variant}"), ignore_errors=True)
    with open(os.path.join(out, "results.json"), "w") as f:
        json.dump(results, f, indent=1)
    print(f"\n{'file':<6} {'on disk':>9} {'frames':>9} {'h5py MB/s':>10} {'ingest MB/s':>12} {'ratio':>6} {'peak RSS':>9}")
    for r in results:
        print(
            f"{r['variant']:<6} {r['file_mb']:>7.0f}MB {r['frames_mb']:>7.0f}MB {r['h5py_mb_s']:>10.0f} "
            f"{r['ingest_mb_s']:>12.1f} {r['ratio']:>6.3f} {r['peak_rss_mb']:>7.0f}MB"
        )
    for r in results:
        if "export_s" in r:
            print(f"{r['variant']:<6} export {r['export_s']:.1f} s, peak RSS {r['export_peak_rss_mb']:.0f}MB; {r['export_check']}")
    if any(r["peak_rss_mb"] > 600 for r in results):
        sys.exit("peak RSS above 600 MB")
    if any(r.get("export_peak_rss_mb", 0) > 300 for r in results):
        sys.exit("export peak RSS above 300 MB")


if __name__ == "__main__":
    main()
