"""Reads a ufops store with nothing but its files and pyarrow (and duckdb/polars when installed),
and checks them against what the `ufops` CLI reported.

usage: check_store.py DATA_DIR EXPECTED.json
EXPECTED.json: {"version": N, "versions": [ufops versions --json],
                "episodes": [ufops episodes --version N --json]}
"""
import json
import os
import sys

import pyarrow.parquet as pq


def labels_files(versions, n):
    """The labels files of version n, in the order to apply them (store/README.md, "Label files"):
    back from n to a full file (or a version's checkpoint), then forward."""
    chain = []
    for v in sorted(versions, key=lambda v: -v["version"]):
        if v["version"] > n:
            continue
        if v.get("labels_checkpoint"):
            chain.append(v["labels_checkpoint"])
            break
        chain.append(v["labels_path"])
        if v["labels_kind"] == "full":
            break
    return chain[::-1]


def read_labels(objects, files):
    rows = {}
    for f in files:
        for r in pq.read_table(os.path.join(objects, f)).to_pylist():
            if r.get("removed"):
                rows.pop(r["episode_id"], None)
            else:
                rows[r["episode_id"]] = r
    return list(rows.values())


def main():
    data_dir, expected_path = sys.argv[1], sys.argv[2]
    objects = os.path.join(data_dir, "objects")
    expected = json.load(open(expected_path))
    episodes = {e["id"]: e for e in expected["episodes"]}

    # The version's labels files list every episode with its label and where its steps are.
    files = labels_files(expected["versions"], expected["version"])
    assert len(files) >= 2, f"a chain of deltas was expected here, got {files}"
    labels = read_labels(objects, files)
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
        paths = [os.path.join(objects, f) for f in files]
        s = duckdb.sql(
            "SELECT count(*) FROM (SELECT label, removed, row_number() OVER (PARTITION BY episode_id "
            "ORDER BY list_position($paths, filename) DESC) AS newest "
            "FROM read_parquet($paths, filename = true, union_by_name = true)) "
            "WHERE newest = 1 AND NOT coalesce(removed, false) AND label = 'success'",
            params={"paths": paths},
        ).fetchall()[0][0]
        assert s == sum(1 for e in episodes.values() if e["label"] == "success")
        print(f"duckdb: {n} step rows, {s} successes")
    try:
        import polars as pl
    except ImportError:
        pl = None
    if pl is not None:
        df = (
            pl.concat(
                [pl.read_parquet(os.path.join(objects, f)).with_columns(pl.lit(i).alias("file")) for i, f in enumerate(files)],
                how="diagonal",
            )
            .sort("file")
            .unique(subset="episode_id", keep="last")
            .filter(~pl.col("removed").fill_null(False))
        )
        assert df.height == len(episodes)
        print(f"polars: {df.height} label rows")


if __name__ == "__main__":
    main()
