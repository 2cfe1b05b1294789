"""Reads a ufops LeRobot v3.0 export with pyarrow alone, following the v3.0 layout
(meta/info.json, meta/episodes, meta/tasks.parquet, data/, videos/), and compares it with the
LeRobot dataset it was ingested from (v3.0 or v2.1): every frame's values, the episodes'
lengths, tasks, labels and video slices, and the video files byte for byte.

usage: check_lerobot_export.py EXPORT_DIR SOURCE_DIR
"""
import glob
import hashlib
import json
import os
import sys

import pyarrow as pa
import pyarrow.parquet as pq

out, src = sys.argv[1:3]
info = json.load(open(os.path.join(out, "meta/info.json")))
sinfo = json.load(open(os.path.join(src, "meta/info.json")))
assert info["codebase_version"] == "v3.0", info["codebase_version"]
assert info["fps"] == sinfo["fps"] and info["robot_type"] == sinfo["robot_type"]
assert info["ufops"]["store_version"] >= 1 and info["ufops"]["format"] == "lerobot"


def table(files):
    return pa.concat_tables([pq.read_table(f) for f in sorted(files)], promote_options="permissive")


data = table(glob.glob(os.path.join(out, "data/chunk-*/file-*.parquet")))
sdata = table(glob.glob(os.path.join(src, "data/chunk-*/*.parquet")))
assert data.num_rows == sdata.num_rows == info["total_frames"], (data.num_rows, sdata.num_rows)
for name in sdata.column_names:
    feature = sinfo["features"].get(name, {})
    if feature.get("dtype") == "image":
        a = [r["bytes"] for r in data.column(name).to_pylist()]
        b = [r["bytes"] for r in sdata.column(name).to_pylist()]
    else:
        a, b = data.column(name).to_pylist(), sdata.column(name).to_pylist()
    assert a == b, f"column {name} differs"
    assert name in info["features"], name
missing = set(data.column_names) - set(sdata.column_names)
assert missing <= {"next.reward", "next.done"}, missing  # the store's defaults when the source had none

eps = table(glob.glob(os.path.join(out, "meta/episodes/chunk-*/file-*.parquet"))).to_pylist()
if sinfo["codebase_version"].startswith("v3"):
    seps = table(glob.glob(os.path.join(src, "meta/episodes/chunk-*/file-*.parquet"))).to_pylist()
else:
    seps = [json.loads(l) for l in open(os.path.join(src, "meta/episodes.jsonl"))]
assert len(eps) == len(seps) == info["total_episodes"]
videos = [k for k, f in info["features"].items() if f["dtype"] == "video"]
for e, s in zip(eps, seps):
    assert (e["episode_index"], e["length"], e["tasks"]) == (s["episode_index"], s["length"], s["tasks"]), (e, s)
    rows = data.filter(pa.compute.equal(data.column("episode_index"), e["episode_index"]))
    assert rows.num_rows == e["length"] == e["dataset_to_index"] - e["dataset_from_index"]
    success = rows.column("next.success").to_pylist() if "next.success" in data.column_names else [None]
    assert e["ufops/label"] == ("unknown" if success[-1] is None else "success" if any(success) else "failure"), e
    for k in videos:
        if sinfo["codebase_version"].startswith("v3"):
            assert e[f"videos/{k}/from_timestamp"] == s[f"videos/{k}/from_timestamp"], (k, e, s)
            sfile = sinfo["video_path"].format(video_key=k, chunk_index=s[f"videos/{k}/chunk_index"], file_index=s[f"videos/{k}/file_index"])
        else:
            assert e[f"videos/{k}/from_timestamp"] == 0.0
            sfile = sinfo["video_path"].format(video_key=k, episode_chunk=0, episode_index=s["episode_index"])
        ofile = info["video_path"].format(video_key=k, chunk_index=e[f"videos/{k}/chunk_index"], file_index=e[f"videos/{k}/file_index"])
        digest = lambda p: hashlib.sha256(open(p, "rb").read()).hexdigest()
        assert digest(os.path.join(out, ofile)) == digest(os.path.join(src, sfile)), (ofile, sfile)
tasks = pq.read_table(os.path.join(out, "meta/tasks.parquet")).to_pylist()
assert sorted(t["task"] for t in tasks) == sorted({t for e in seps for t in e["tasks"]})
print(f"pyarrow: {len(eps)} episodes, {data.num_rows} frames, {len(videos)} video key(s): frames, episodes, tasks and videos equal the source's")
