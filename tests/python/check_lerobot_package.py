"""Loads a ufops LeRobot v3.0 export with PyPI's `lerobot` (LeRobotDataset, local root, no Hub)
and checks that every frame it returns equals the export's own data files: the numeric features,
images (decoded from the stored PNG bytes), indices and timestamps, and that its episode and
frame counts match meta/info.json.

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

out = sys.argv[1]
info = json.load(open(os.path.join(out, "meta/info.json")))
ds = LeRobotDataset("ufops/export", root=out)
assert ds.meta.info["codebase_version"] == "v3.0"
assert len(ds) == info["total_frames"], (len(ds), info["total_frames"])
assert ds.num_episodes == info["total_episodes"], (ds.num_episodes, info["total_episodes"])

data = pa.concat_tables([pq.read_table(f) for f in sorted(glob.glob(os.path.join(out, "data/chunk-*/file-*.parquet")))])
rows = data.to_pylist()
by_index = {r["index"]: r for r in rows}
features = info["features"]
checked = 0
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
        elif feat["dtype"] in ("float32", "float64"):
            want = np.asarray(row[key], dtype=np.float32).reshape(np.asarray(got).shape)
            assert np.array_equal(np.asarray(got, dtype=np.float32), want), (key, i)
        elif feat["dtype"] in ("int64", "int32", "bool"):
            assert np.array_equal(np.asarray(got).reshape(-1), np.asarray(row[key]).reshape(-1)), (key, i)
    checked += 1
print(json.dumps({"frames": checked, "episodes": ds.num_episodes, "features": sorted(k for k in features if k in ds[0])}))
