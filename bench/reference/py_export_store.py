#!/usr/bin/env python3
"""Baseline for `cargo bench -p export`: what a user writes in Python to export a ufops store
version with pyarrow / h5py alone, following store/README.md ("Label snapshot schema"): read the
version's label snapshot, read each steps file's row groups, slice the episodes, and write
  lerobot:   data/chunk-000/file-000.parquet (observation.*, action, next.*, timestamp, indices),
             meta/episodes parquet, meta/tasks.parquet, meta/info.json, meta/stats.json
  robomimic: data/demo_i/{obs/*, actions, rewards, dones} + attributes, one HDF5 file.
Prints `rows`, `seconds` and `peak_rss_mb` (ru_maxrss) on the last line as JSON.

usage: py_export_store.py OBJECTS_DIR LABELS_PATH lerobot|robomimic OUT
"""
import json
import os
import resource
import sys
import time

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq


def episodes(objects, labels_path):
    labels = pq.read_table(os.path.join(objects, labels_path)).to_pylist()
    by_file = {}
    for i, r in enumerate(labels):
        by_file.setdefault(r["data_file"], []).append((i, r))
    for data_file, rows in by_file.items():
        f = pq.ParquetFile(os.path.join(objects, data_file))
        for rg in sorted({r["row_group"] for _, r in rows}):
            table = f.read_row_group(rg)
            for i, r in rows:
                if r["row_group"] == rg:
                    yield i, r, table.slice(r["row_offset"], r["row_count"])


def lerobot(objects, labels_path, out):
    os.makedirs(os.path.join(out, "data/chunk-000"))
    os.makedirs(os.path.join(out, "meta/episodes/chunk-000"))
    writer, eps, tasks, frames, stats = None, [], {}, 0, {}
    for i, r, steps in episodes(objects, labels_path):
        n = steps.num_rows
        task = r["task"] or "(no task)"
        tasks.setdefault(task, len(tasks))
        cols = {}
        for name in steps.column_names:
            if name.startswith("obs."):
                cols["observation." + name[4:]] = steps.column(name)
        cols["action"] = steps.column("action")
        cols["next.reward"] = steps.column("reward")
        cols["next.done"] = steps.column("done")
        succ = np.zeros(n, bool)
        succ[-1] = r["success"] is True
        cols["next.success"] = pa.array(succ) if r["success"] is not None else pa.nulls(n, pa.bool_())
        cols["timestamp"] = pc.cast(steps.column("timestamp"), pa.float32())
        cols["frame_index"] = pa.array(np.arange(n, dtype=np.int64))
        cols["episode_index"] = pa.array(np.full(n, i, np.int64))
        cols["index"] = pa.array(np.arange(frames, frames + n, dtype=np.int64))
        cols["task_index"] = pa.array(np.full(n, tasks[task], np.int64))
        t = pa.table(cols)
        for k in ("action", "observation.", "next.reward"):
            for name in [c for c in t.column_names if c.startswith(k)]:
                col = t.column(name).combine_chunks()
                x = col.values.to_numpy().reshape(n, -1) if pa.types.is_fixed_size_list(col.type) else col.to_numpy().reshape(n, 1)
                s = stats.setdefault(name, [np.full(x.shape[1], np.inf), np.full(x.shape[1], -np.inf), np.zeros(x.shape[1]), np.zeros(x.shape[1]), 0])
                s[0] = np.minimum(s[0], x.min(0)); s[1] = np.maximum(s[1], x.max(0))
                s[2] += x.sum(0, dtype=np.float64); s[3] += (x.astype(np.float64) ** 2).sum(0); s[4] += n
        if writer is None:
            writer = pq.ParquetWriter(os.path.join(out, "data/chunk-000/file-000.parquet"), t.schema, compression="zstd")
        writer.write_table(t)
        eps.append({"episode_index": i, "tasks": [task], "length": n, "data/chunk_index": 0, "data/file_index": 0,
                    "dataset_from_index": frames, "dataset_to_index": frames + n})
        frames += n
    writer.close()
    pq.write_table(pa.Table.from_pylist(eps), os.path.join(out, "meta/episodes/chunk-000/file-000.parquet"))
    pq.write_table(pa.table({"task_index": list(tasks.values()), "task": list(tasks.keys())}), os.path.join(out, "meta/tasks.parquet"))
    json.dump({k: {"min": s[0].tolist(), "max": s[1].tolist(), "mean": (s[2] / s[4]).tolist(),
                   "std": np.sqrt(np.maximum(s[3] / s[4] - (s[2] / s[4]) ** 2, 0)).tolist(), "count": [s[4]]}
               for k, s in stats.items()}, open(os.path.join(out, "meta/stats.json"), "w"))
    json.dump({"codebase_version": "v3.0", "total_episodes": len(eps), "total_frames": frames}, open(os.path.join(out, "meta/info.json"), "w"))
    return frames


def robomimic(objects, labels_path, out):
    import h5py
    frames = 0
    with h5py.File(out, "w") as f:
        data = f.create_group("data")
        for i, r, steps in episodes(objects, labels_path):
            n = steps.num_rows
            g = data.create_group(f"demo_{i}")
            obs = g.create_group("obs")
            for name in steps.column_names:
                if name.startswith("obs."):
                    col = steps.column(name).combine_chunks()
                    obs.create_dataset(name[4:], data=col.values.to_numpy().reshape(n, -1))
            act = steps.column("action").combine_chunks()
            g.create_dataset("actions", data=act.values.to_numpy().reshape(n, -1))
            g.create_dataset("rewards", data=steps.column("reward").to_numpy().astype(np.float64))
            g.create_dataset("dones", data=steps.column("done").to_numpy(zero_copy_only=False).astype(np.uint8))
            g.attrs["num_samples"] = n
            if r["success"] is not None:
                g.attrs["success"] = int(r["success"])
            frames += n
        data.attrs["total"] = frames
        data.attrs["env_args"] = json.dumps({"env_name": "square", "env_kwargs": {}})
    return frames


if __name__ == "__main__":
    objects, labels_path, fmt, out = sys.argv[1:5]
    t0 = time.perf_counter()
    rows = (lerobot if fmt == "lerobot" else robomimic)(objects, labels_path, out)
    secs = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"rows": rows, "seconds": secs, "peak_rss_mb": rss}))
