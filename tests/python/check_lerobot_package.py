"""Loads a ufops LeRobot v3.0 export with PyPI's `lerobot` (LeRobotDataset, local root, no Hub)
and checks that every frame it returns equals the export's own data files: the numeric features,
images (decoded from the stored PNG bytes), mp4 video frames (lerobot decodes them with its
`video_backend="pyav"`; each is compared with the same mp4 decoded here independently with PyAV,
frame by presentation time), indices and timestamps, and that its episode and frame counts match
meta/info.json. pyav, not lerobot's default torchcodec: torchcodec needs system FFmpeg libraries,
PyAV's wheel ships its own.

usage: check_lerobot_package.py EXPORT_DIR
"""
import glob
import io
import json
import os
import sys

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from PIL import Image
import av

out = sys.argv[1]
info = json.load(open(os.path.join(out, "meta/info.json")))
ds = LeRobotDataset("ufops/export", root=out, video_backend="pyav")
assert ds.meta.info["codebase_version"] == "v3.0"
assert len(ds) == info["total_frames"], (len(ds), info["total_frames"])
assert ds.num_episodes == info["total_episodes"], (ds.num_episodes, info["total_episodes"])

data = pa.concat_tables([pq.read_table(f) for f in sorted(glob.glob(os.path.join(out, "data/chunk-*/file-*.parquet")))])
rows = data.to_pylist()
by_index = {r["index"]: r for r in rows}
features = info["features"]
episodes = {
    r["episode_index"]: r
    for f in sorted(glob.glob(os.path.join(out, "meta/episodes/chunk-*/file-*.parquet")))
    for r in pq.read_table(f).to_pylist()
}
decoded = {}  # mp4 path -> [(pts seconds, H x W x 3 uint8)], decoded once with PyAV


def video_frame(key, episode, timestamp):
    """The frame of `key`'s mp4 shown at the episode's `timestamp`, decoded with PyAV (not lerobot)."""
    ep = episodes[episode]
    path = os.path.join(out, info["video_path"].format(
        video_key=key, chunk_index=ep[f"videos/{key}/chunk_index"], file_index=ep[f"videos/{key}/file_index"]))
    if path not in decoded:
        with av.open(path) as container:
            stream = container.streams.video[0]
            decoded[path] = [(float(f.pts * stream.time_base), f.to_ndarray(format="rgb24")) for f in container.decode(stream)]
    at = ep[f"videos/{key}/from_timestamp"] + timestamp
    pts, frame = min(decoded[path], key=lambda pf: abs(pf[0] - at))
    assert abs(pts - at) < 0.5 / info["fps"], (key, episode, timestamp, pts)
    return frame


checked = 0
video_frames = 0
for i in range(len(ds)):
    item = ds[i]
    row = by_index[int(item["index"])]
    for key, feat in features.items():
        if key not in item:
            continue
        got = item[key]
        if feat["dtype"] == "image":
            want = np.asarray(Image.open(io.BytesIO(row[key]["bytes"])).convert("RGB"), dtype=np.float32) / 255.0
            got = got.numpy().transpose(1, 2, 0)  # lerobot returns C x H x W in [0, 1]
            assert got.shape == want.shape, (key, got.shape, want.shape)
            assert np.allclose(got, want, atol=1e-6), key
        elif feat["dtype"] == "video":
            want = video_frame(key, int(item["episode_index"]), float(item["timestamp"])).astype(np.float32) / 255.0
            got = got.numpy().transpose(1, 2, 0)
            assert got.shape == want.shape, (key, got.shape, want.shape)
            assert np.allclose(got, want, atol=1e-6), (key, i, float(np.abs(got - want).max()))
            video_frames += 1
        elif feat["dtype"] in ("float32", "float64"):
            want = np.asarray(row[key], dtype=np.float32).reshape(np.asarray(got).shape)
            assert np.array_equal(np.asarray(got, dtype=np.float32), want), (key, i)
        elif feat["dtype"] in ("int64", "int32", "bool"):
            assert np.array_equal(np.asarray(got).reshape(-1), np.asarray(row[key]).reshape(-1)), (key, i)
    checked += 1
print(json.dumps({"frames": checked, "video_frames": video_frames, "episodes": ds.num_episodes, "features": sorted(k for k in features if k in ds[0])}))
