"""Reads a ufops store with nothing but its files and pyarrow (and duckdb/polars when installed),
and checks them against what the `ufops` CLI reported.

usage: check_store.py DATA_DIR EXPECTED.json
EXPECTED.json: {"version": N, "labels_path": "...", "episodes": [ufops episodes --version N --json]}
"""
import json
import os
import sys

import pyarrow.parquet as pq


def main():
    data_dir, expected_path = sys.argv[1], sys.argv[2]
    objects = os.path.join(data_dir, "objects")
    expected = json.load(open(expected_path))
    episodes = {e["id"]: e for e in expected["episodes"]}

    # The version's label snapshot lists every episode with its label and where its steps are.
    labels = pq.read_table(os.path.join(objects, expected["labels_path"])).to_pylist()
    assert len(labels) == len(episodes), (len(labels), len(episodes))
    for row in labels:
        e = episodes[row["episode_id"]]
        assert row["label"] == e["label"], (row, e["label"])
        assert row["success"] == {"success": True, "failure": False, "unknown": None}[e["label"]]
        assert row["length"] == e["length"]
        assert row["label_revision"] == e["label_revision"]

        steps = pq.ParquetFile(os.path.join(objects, row["data_file"])).read_row_group(row["row_group"])
        steps = steps.slice(row["row_offset"], row["row_count"])
        assert steps.num_rows == e["length"], (steps.num_rows, e["length"])
        assert set(steps.column("episode_id").to_pylist()) == {e["id"]}
        assert steps.column("t").to_pylist() == list(range(e["length"]))
        pos = steps.column("obs.pos")
        assert pos.type.list_size == 3 and str(pos.type.value_type) == "float", pos.type
        assert steps.schema.field("action").type.list_size == 2
        assert steps.column("policy").to_pylist()[0] == e["policy"]
    print(f"pyarrow: {len(labels)} episodes of version {expected['version']} match")

    try:
        import duckdb
    except ImportError:
        duckdb = None
    if duckdb is not None:
        glob = os.path.join(objects, "steps", "*.parquet")
        n = duckdb.sql(f"SELECT count(*) FROM read_parquet('{glob}')").fetchall()[0][0]
        total = sum(e["length"] for e in episodes.values())
        assert n >= total, (n, total)
        lbl = os.path.join(objects, expected["labels_path"])
        s = duckdb.sql(f"SELECT count(*) FROM read_parquet('{lbl}') WHERE label = 'success'").fetchall()[0][0]
        assert s == sum(1 for e in episodes.values() if e["label"] == "success")
        print(f"duckdb: {n} step rows, {s} successes")
    try:
        import polars as pl
    except ImportError:
        pl = None
    if pl is not None:
        df = pl.read_parquet(os.path.join(objects, expected["labels_path"]))
        assert df.height == len(episodes)
        print(f"polars: {df.height} label rows")


if __name__ == "__main__":
    main()
