"""ufops.Store (read-only) against the CLI and the Parquet files themselves: episodes equal what
`ufops episodes --json` lists (now and pinned to a version), steps equal the rows of the steps
files read directly with polars, splits and artifacts equal the catalog's."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Dict, List

import pytest

import ufops
from conftest import Ufops, require

pl = require("polars")
assert_frame_equal = require("polars.testing").assert_frame_equal


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Ufops:
    """300 synthetic episodes over several steps files, one relabeled after a snapshot."""
    u = Ufops(tmp_path_factory.mktemp("data"))
    u.run("init")
    u.run("dev", "synth", "--episodes", "200", "--steps", "25", "--seed", "1", "--max-file-bytes", "200000")
    u.run("dev", "synth", "--episodes", "100", "--steps", "12", "--seed", "2", "--checkpoint", "ckpt-1")
    return u


def cli_frame(records: List[Dict[str, Any]]) -> Any:
    return ufops.store.episodes_frame(records)


def test_episodes_equal_the_cli(data: Ufops) -> None:
    s = ufops.Store(data.data_dir)
    df = s.episodes()
    cli = data.json("episodes", "--json")
    assert df.height == len(cli) == 300
    assert_frame_equal(df, cli_frame(cli))
    assert df["id"].to_list() == [e["id"] for e in cli]
    # Every field of the record is a column (the schema comes from the store, not a copy here).
    assert df.columns == list(cli[0].keys())
    assert df.schema["tags"] == pl.List(pl.Utf8) and df.schema["length"] == pl.Int64
    # Filters go to the catalog.
    assert_frame_equal(s.episodes(checkpoint="ckpt-1"), cli_frame(data.json("episodes", "--checkpoint", "ckpt-1", "--json")))
    assert s.episodes(limit=7).height == 7


def test_episodes_pinned_to_a_version(data: Ufops) -> None:
    s = ufops.Store(data.data_dir)
    before = s.head_version()
    ep = s.episodes(checkpoint="ckpt-1", limit=1).row(0, named=True)
    new = "failure" if ep["label"] == "success" else "success"
    data.run("label", ep["id"], new, "--actor", "pytest")
    data.run("snapshot", "--message", "relabel")
    assert s.head_version() == before + 1
    old = s.episodes(version=before)
    assert_frame_equal(old, cli_frame(data.json("episodes", "--version", str(before), "--json")))
    now = s.episodes().filter(pl.col("id") == ep["id"]).row(0, named=True)
    then = old.filter(pl.col("id") == ep["id"]).row(0, named=True)
    assert (now["label"], then["label"]) == (new, ep["label"])
    assert s.versions().height == len(data.json("versions", "--json"))


def test_steps_equal_the_parquet_files(data: Ufops) -> None:
    s = ufops.Store(data.data_dir)
    eps = s.episodes()
    assert eps["data_file"].n_unique() > 1, "the store should span several steps files"
    ids = eps["id"].to_list()[::-1][:60] + [eps["id"][0]]  # many files, any order
    steps = s.steps(ids)
    files = {f: pl.read_parquet(data.data_dir / "objects" / f) for f in eps["data_file"].unique().to_list()}
    expected = []
    for i in ids:
        f = eps.filter(pl.col("id") == i)["data_file"][0]
        expected.append(files[f].filter(pl.col("episode_id") == i))
    assert_frame_equal(steps, pl.concat(expected))
    one = s.steps(ids[0])
    assert one.height == eps.filter(pl.col("id") == ids[0])["length"][0]
    assert one["episode_id"].unique().to_list() == [ids[0]]


def test_splits_and_artifacts(trained: Ufops) -> None:
    s = ufops.Store(trained.data_dir)
    splits = s.splits()
    assert [x["id"] for x in splits] == [x["id"] for x in json.loads(trained.run("split", "list", "--json"))]
    members = s.split_episodes(splits[0]["id"])
    assert members.height == splits[0]["train_episodes"] + splits[0]["val_episodes"]
    assert set(members["part"].unique().to_list()) <= {"train", "val"}
    arts = s.artifacts()
    assert sorted(a["kind"] for a in arts) == ["classifier", "q"]
    assert all("latest" in a["aliases"] for a in arts)
    v = s.verifier(f"{arts[0]['policy']}/{arts[0]['checkpoint']}/{arts[0]['kind']}@latest")
    assert v.id == arts[0]["id"]


def test_bad_store_requests(data: Ufops, tmp_path: Path) -> None:
    with pytest.raises(ufops.NotFoundError, match="no ufops store"):
        ufops.Store(tmp_path / "empty")
    assert not (tmp_path / "empty").exists(), "opening read-only must not create a store"
    s = ufops.Store(data.data_dir)
    with pytest.raises(ufops.NotFoundError, match="episode not found: nope"):
        s.steps(["nope"])
    with pytest.raises(ufops.NotFoundError):
        s.episodes(version=10_000)
    with pytest.raises(ValueError, match="unknown label"):
        s.episodes(label="maybe")
