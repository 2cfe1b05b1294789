"""ufops.features on the repository's LeRobot fixtures, ingested with the CLI: a layer computed
from the store's AV1 video (decoded with range reads) equals a seeded CNN applied to the frames
decoded independently from the fixture's mp4 (PyAV, frames picked by the episodes' timestamps in
the LeRobot metadata); from PNG columns, to the fixture's PNGs decoded with Pillow. Re-running
writes nothing; an interrupted run resumes and ends equal to a clean run; producers hash the
encoder's weights."""
from __future__ import annotations

import copy
import io
import json
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any, Dict, List

import numpy as np
import pytest

from conftest import REPO, Ufops, require, serving

torch = require("torch")
av = require("av")
Image = require("PIL.Image")
pl = require("polars")

import ufops  # noqa: E402
from ufops import features  # noqa: E402

FIXTURES = REPO / "fixtures" / "lerobot"
CAMERA = "observation.images.front"
VIDEO = "videos/observation.images.front/chunk-000/file-000.mp4"
LAYER = "features.tiny-cnn"
TOL = 1e-5


def tiny_cnn(seed: int = 0) -> Any:
    """A stand-in for a policy's vision encoder: random, seeded, 12-d."""
    torch.manual_seed(seed)
    return torch.nn.Sequential(
        torch.nn.Conv2d(3, 8, 3, stride=2),
        torch.nn.BatchNorm2d(8),
        torch.nn.ReLU(),
        torch.nn.Conv2d(8, 16, 3, stride=2),
        torch.nn.ReLU(),
        torch.nn.AdaptiveAvgPool2d(1),
        torch.nn.Flatten(),
        torch.nn.Linear(16, 12),
    ).eval()


ENCODER = tiny_cnn()
PRODUCER = features.producer_of(ENCODER, encoder="tiny-cnn/unit", policy="p", checkpoint="c")


def reference(frames: np.ndarray) -> np.ndarray:
    """The encoder on frames, preprocessed here independently of ufops.features."""
    x = torch.tensor(frames, dtype=torch.float32).permute(0, 3, 1, 2) / 255.0
    with torch.no_grad():
        return ENCODER(x).numpy()  # type: ignore[no-any-return]


def ingest(tmp_path_factory: pytest.TempPathFactory, fixture: str) -> Ufops:
    u = Ufops(tmp_path_factory.mktemp(fixture))
    u.run("init")
    u.run("ingest", str(FIXTURES / fixture), "--policy", "p", "--checkpoint", "c")
    return u


class Interrupted(Exception):
    pass


class FailsAfter:
    """The encoder, failing after `batches` batches (a run interrupted half-way)."""

    def __init__(self, batches: int) -> None:
        self.left = batches

    def __call__(self, x: Any) -> Any:
        if self.left == 0:
            raise Interrupted()
        self.left -= 1
        return ENCODER(x)


def episode_index(store: ufops.Store) -> Dict[str, int]:
    """Store episode id -> the LeRobot episode_index it was ingested from."""
    eps = store.episodes()
    return {i: json.loads(m)["episode_index"] for i, m in zip(eps["id"], eps["metadata"])}


def video_frames_by_episode() -> Dict[int, np.ndarray]:
    """The fixture's episodes' frames: the mp4 decoded in full with PyAV, each step's frame the
    one nearest the episode's from_timestamp + the step's timestamp."""
    root = FIXTURES / "v30_eval_video"
    with av.open(str(root / VIDEO)) as c:
        decoded = [(float(f.pts * f.time_base), f.to_ndarray(format="rgb24")) for f in c.decode(video=0)]
    times = np.array([t for t, _ in decoded])
    meta = pl.read_parquet(root / "meta/episodes/chunk-000/file-000.parquet")
    data = pl.read_parquet(root / "data/chunk-000/file-000.parquet")
    out = {}
    for row in meta.iter_rows(named=True):
        ts = data.filter(pl.col("episode_index") == row["episode_index"])["timestamp"].to_numpy()
        want = row[f"videos/{CAMERA}/from_timestamp"] + ts.astype(np.float64)
        nearest = np.abs(times[None, :] - want[:, None]).argmin(axis=1)
        assert np.abs(times[nearest] - want).max() < 1e-3
        out[row["episode_index"]] = np.stack([decoded[i][1] for i in nearest])
    return out


def png_frames_by_episode() -> Dict[int, np.ndarray]:
    data = pl.read_parquet(FIXTURES / "v30_unlabeled/data/chunk-000/file-000.parquet")
    out = {}
    for (e,), g in data.sort("index").group_by(["episode_index"], maintain_order=True):
        frames = [np.asarray(Image.open(io.BytesIO(x["bytes"])).convert("RGB")) for x in g[CAMERA]]
        out[int(e)] = np.stack(frames)
    return out


def layer_values(store: ufops.Store, ids: List[str], name: str = LAYER) -> Dict[str, np.ndarray]:
    steps = store.steps(ids, layers=[name])
    out = {}
    for i in ids:
        rows = steps.filter(pl.col("episode_id") == i).sort("t")
        out[i] = np.asarray(rows[f"obs.{name}"].to_list(), dtype=np.float32)
    return out


@pytest.fixture(scope="module")
def video_store(tmp_path_factory: pytest.TempPathFactory) -> Ufops:
    return ingest(tmp_path_factory, "v30_eval_video")


@pytest.fixture(scope="module")
def expected_video() -> Dict[int, np.ndarray]:
    return {e: reference(f) for e, f in video_frames_by_episode().items()}


def test_video_layer_equals_the_encoder_on_independently_decoded_frames(
    video_store: Ufops, expected_video: Dict[int, np.ndarray], capsys: pytest.CaptureFixture[str]
) -> None:
    s = ufops.Store(video_store.data_dir)
    before = s.head_version()
    r = features.compute_layer(
        s, ENCODER, name=LAYER, camera=CAMERA, producer=PRODUCER, batch_size=16, commit_every=3
    )
    assert (r.episodes_written, r.episodes_skipped, r.frames) == (8, 0, 519)
    assert r.versions == list(range(before + 1, before + 4)), "8 episodes in groups of 3: 3 versions"
    assert r.producer_hash == s.producer_hash(PRODUCER.to_dict())
    assert r.frames_per_second > 0
    assert "8/8 episodes, 519 frames" in capsys.readouterr().err
    print(f"\nvideo layer: {r.frames} frames in {r.seconds:.2f} s, {r.frames_per_second:.0f} frames/s")

    index = episode_index(s)
    got = layer_values(s, list(index))
    for i, e in index.items():
        assert got[i].shape == expected_video[e].shape == (len(expected_video[e]), 12)
        np.testing.assert_allclose(got[i], expected_video[e], rtol=0, atol=TOL, err_msg=f"episode {e}")

    layers = s.layers()
    assert layers.height == 1
    row = layers.row(0, named=True)
    assert (row["name"], row["dim"], row["episodes"], row["producer_hash"]) == (LAYER, 12, 8, r.producer_hash)
    assert json.loads(row["producer"]) == PRODUCER.to_dict()

    # Again: everything is there already, nothing is written.
    head = s.head_version()
    again = features.compute_layer(s, ENCODER, name=LAYER, camera="images.front", producer=PRODUCER, progress=False)
    assert (again.episodes_written, again.episodes_skipped, again.frames, again.versions) == (0, 8, 0, [])
    assert s.head_version() == head

    # Live frames through encode_frames give the stored rows.
    i, e = next(iter(index.items()))
    frames = video_frames_by_episode()[e]
    np.testing.assert_allclose(features.encode_frames(ENCODER, frames), got[i], atol=TOL)
    np.testing.assert_allclose(features.encode_frames(ENCODER, frames[3]), got[i][3], atol=TOL)


def test_interrupted_run_resumes_and_ends_equal_to_a_clean_run(
    tmp_path_factory: pytest.TempPathFactory, expected_video: Dict[int, np.ndarray]
) -> None:
    s = ufops.Store(ingest(tmp_path_factory, "v30_eval_video").data_dir)
    phash = s.producer_hash(PRODUCER.to_dict())
    # 12 batches of up to 16 frames of one episode: episodes 0 and 1 (5 + 4 batches) are
    # finished, 2 (3 of its 4 batches) is not.
    with pytest.raises(Interrupted):
        features.compute_layer(
            s, FailsAfter(12), name=LAYER, camera=CAMERA, producer=PRODUCER, batch_size=16, commit_every=4,
            progress=False, decode_threads=1,
        )
    index = episode_index(s)
    done = s.layer_episodes(LAYER, phash)
    assert sorted(index[i] for i in done) == [0, 1], "the finished episodes are committed before the error"

    r = features.compute_layer(s, ENCODER, name=LAYER, camera=CAMERA, producer=PRODUCER, batch_size=16, progress=False)
    assert (r.episodes_written, r.episodes_skipped, r.frames) == (6, 2, 519 - 78 - 61)
    assert sorted(s.layer_episodes(LAYER, phash)) == sorted(index)

    clean = ufops.Store(ingest(tmp_path_factory, "v30_eval_video").data_dir)
    features.compute_layer(clean, ENCODER, name=LAYER, camera=CAMERA, producer=PRODUCER, progress=False)
    resumed, fresh = layer_values(s, list(index)), layer_values(clean, list(episode_index(clean)))
    clean_by_episode = {e: fresh[i] for i, e in episode_index(clean).items()}
    for i, e in index.items():
        np.testing.assert_allclose(resumed[i], clean_by_episode[e], rtol=0, atol=TOL)
        np.testing.assert_allclose(resumed[i], expected_video[e], rtol=0, atol=TOL)


def test_png_layer(tmp_path_factory: pytest.TempPathFactory) -> None:
    s = ufops.Store(ingest(tmp_path_factory, "v30_unlabeled").data_dir)
    assert "image.images.front" in s.steps(s.episodes()["id"][0]).columns
    r = features.compute_layer(s, ENCODER, name=LAYER, camera=CAMERA, producer=PRODUCER, batch_size=50, progress=False)
    assert (r.episodes_written, r.frames, len(r.versions)) == (6, 262, 1)
    index = episode_index(s)
    got = layer_values(s, list(index))
    for i, frames in ((i, png_frames_by_episode()[e]) for i, e in index.items()):
        np.testing.assert_allclose(got[i], reference(frames), rtol=0, atol=TOL)

    # Any callable with its own preprocessing: a second layer of raw mean colours, from numpy.
    colours = features.Producer("mean-rgb", "p", "c", "none")
    features.compute_layer(
        s,
        lambda x: x.mean(axis=(1, 2)),
        name="features.rgb",
        camera="images.front",
        producer=colours,
        preprocess=lambda f: f.astype(np.float32),
        progress=False,
    )
    rgb = layer_values(s, list(index), "features.rgb")
    for i, e in index.items():
        np.testing.assert_allclose(rgb[i], png_frames_by_episode()[e].mean(axis=(1, 2)), rtol=1e-6)
    assert sorted(s.layers()["name"].to_list()) == ["features.rgb", LAYER]


def test_frames_come_from_range_reads_in_any_episode_order(video_store: Ufops) -> None:
    s = ufops.Store(video_store.data_dir)
    by_episode = video_frames_by_episode()
    index = episode_index(s)
    ids = sorted(index, key=lambda i: -index[i])  # last episode first: the decoder seeks back
    path = s.steps(ids[0])["media.images.front.path"][0]
    size = s.object_size(path)
    with features.FrameReader(s, CAMERA, read_ahead=4096) as reader:
        last = np.stack(list(reader.episode(ids[0])))
        assert reader.requests > 1 and reader.bytes_fetched < size / 2, (
            "the last episode alone reads a part of the video",
            reader.bytes_fetched,
            size,
        )
        np.testing.assert_array_equal(last, by_episode[index[ids[0]]])
        for i in ids[1:]:
            np.testing.assert_array_equal(np.stack(list(reader.episode(i))), by_episode[index[i]])

    f = features.ObjectFile(s, path, read_ahead=1000)
    with open(video_store.data_dir / "objects" / path, "rb") as local:
        whole = local.read()
    assert f.size == len(whole) and f.read(10) == whole[:10]
    f.seek(-100, 2)
    assert f.read() == whole[-100:] and f.read() == b""
    f.seek(5000)
    assert f.read(3000) == whole[5000:8000]


def test_missing_frames_and_unknown_cameras_are_errors(video_store: Ufops) -> None:
    s = ufops.Store(video_store.data_dir)
    ep = s.episodes()["id"][0]
    steps = s.steps(ep)
    ts = "media.images.front.timestamp"
    late = steps.with_columns(pl.col(ts) + 0.049)
    with features.FrameReader(s, "images.front") as reader:
        exact = np.stack(list(reader.frames(steps)))
        assert len(exact) == steps.height
        # Within half a frame period (0.05 s at 10 fps) the nearest frame is the one.
        np.testing.assert_array_equal(np.stack(list(reader.frames(late))), exact)
        shifted = steps.with_columns(pl.when(pl.col("t") == 5).then(1000.0).otherwise(pl.col(ts)).alias(ts))
        with pytest.raises(ufops.UfopsError, match=f"episode {ep}: camera images.front: frame times decrease"):
            list(reader.frames(shifted))
        beyond = steps.with_columns(pl.col(ts) + 100.0)
        first = steps[ts][0] + 100.0
        with pytest.raises(ufops.UfopsError, match=rf"episode {ep}: camera images.front: no frame at {first:.6f} s"):
            list(reader.frames(beyond))
    with pytest.raises(ufops.NotFoundError, match=r"no camera 'wrist'.*images\.front"):
        features.compute_layer(s, ENCODER, name="features.x", camera="wrist", producer=PRODUCER, progress=False)
    assert s.layers().filter(pl.col("name") == "features.x").height == 0


def test_producer_hashes_the_weights() -> None:
    a, b = tiny_cnn(0), tiny_cnn(0)
    pa = features.producer_of(a, encoder="e", policy="p", checkpoint="c")
    assert pa == features.producer_of(b, encoder="e", policy="p", checkpoint="c")
    assert pa.content_hash == PRODUCER.content_hash == features.state_dict_sha256(copy.deepcopy(a))
    assert pa.to_dict() == {"encoder": "e", "policy": "p", "checkpoint": "c", "content_hash": pa.content_hash}
    with torch.no_grad():
        b[0].weight[0, 0, 0, 0] += 1e-3
    assert features.state_dict_sha256(b) != pa.content_hash
    c = tiny_cnn(0)
    c[1].running_mean += 1.0  # buffers count too
    assert features.state_dict_sha256(c) != pa.content_hash
    assert features.state_dict_sha256(tiny_cnn(1)) != pa.content_hash
    assert features.state_dict_sha256(tiny_cnn(0).double()) != pa.content_hash, "dtype is part of the hash"
    with pytest.raises(ValueError, match="content_hash"):
        features.Producer("e", "p", "c", "")


def test_encode_frames_checks_its_inputs() -> None:
    frames = np.zeros((2, 16, 16, 3), np.uint8)
    enc = tiny_cnn(0).train()
    assert features.encode_frames(enc, frames).shape == (2, 12)
    assert enc.training, "the module's mode is restored"
    assert features.encode_frames(enc, list(frames)).shape == (2, 12)
    with pytest.raises(TypeError, match="uint8"):
        features.encode_frames(enc, frames.astype(np.float32))
    with pytest.raises(ValueError, match=r"must return \(B, D\)"):
        features.encode_frames(torch.nn.Conv2d(3, 4, 3), frames)


def test_layer_over_the_api_equals_the_layer_from_the_store(
    tmp_path_factory: pytest.TempPathFactory, expected_video: Dict[int, np.ndarray]
) -> None:
    """compute_layer against `ufops serve` (Client.layer_store): frames by range requests on the
    episodes' media, the layer written with POST /v1/layers as a trainer; the values equal the
    encoder on independently decoded frames, and a re-run over the API writes nothing."""
    u = ingest(tmp_path_factory, "v30_eval_video")
    with serving(u, "trainer") as server:
        api = ufops.Client(server.url, server.token).layer_store()
        r = features.compute_layer(api, ENCODER, name=LAYER, camera=CAMERA, producer=PRODUCER, batch_size=16,
                                   commit_every=4, progress=False)
        assert (r.episodes_written, r.frames, len(r.versions)) == (8, 519, 2)
        again = features.compute_layer(api, ENCODER, name=LAYER, camera=CAMERA, producer=PRODUCER, progress=False)
        assert (again.episodes_written, again.episodes_skipped, again.versions) == (0, 8, [])
    s = ufops.Store(u.data_dir)
    index = episode_index(s)
    got = layer_values(s, list(index))
    for i, e in index.items():
        np.testing.assert_allclose(got[i], expected_video[e], rtol=0, atol=TOL, err_msg=f"episode {e}")


def test_layer_over_the_api_on_postgres_and_s3(scale_out: Ufops, expected_video: Dict[int, np.ndarray]) -> None:
    """The scale-out path end to end: the fixture ingested into a store on Postgres + S3 (SeaweedFS),
    `ufops serve` on it, compute_layer over the API (frames by range requests on the S3-held mp4)
    interrupted half-way, resumed, and re-run (nothing written); every row read back through the API
    equals the encoder on independently decoded frames."""
    u = scale_out
    u.run("ingest", str(FIXTURES / "v30_eval_video"), "--policy", "p", "--checkpoint", "c")
    with serving(u, "trainer") as server:
        client = ufops.Client(server.url, server.token)
        api = client.layer_store()
        phash = api.producer_hash(PRODUCER.to_dict())
        index = {e["id"]: json.loads(e["metadata"])["episode_index"] if isinstance(e["metadata"], str)
                 else e["metadata"]["episode_index"] for e in client.episodes()}
        assert len(index) == 8

        with pytest.raises(Interrupted):
            features.compute_layer(api, FailsAfter(12), name=LAYER, camera=CAMERA, producer=PRODUCER,
                                   batch_size=16, commit_every=4, progress=False, decode_threads=1)
        done = client.layer_episodes(LAYER, phash)
        assert sorted(index[i] for i in done) == [0, 1], "the finished episodes are committed before the error"

        r = features.compute_layer(api, ENCODER, name=LAYER, camera=CAMERA, producer=PRODUCER, batch_size=16,
                                   commit_every=4, progress=False)
        assert (r.episodes_written, r.episodes_skipped, r.frames) == (6, 2, 519 - 78 - 61)
        assert len(r.versions) == 2, "6 episodes in groups of 4"
        again = features.compute_layer(api, ENCODER, name=LAYER, camera=CAMERA, producer=PRODUCER, progress=False)
        assert (again.episodes_written, again.episodes_skipped, again.versions) == (0, 8, [])

        layers = client.layers()
        assert [(l["name"], l["dim"], l["episodes"]) for l in layers] == [(LAYER, 12, 8)]
        for i, e in index.items():
            rows = client.steps(i, layers=[LAYER]).sort("t")
            got = np.asarray(rows[f"obs.{LAYER}"].to_list(), dtype=np.float32)
            np.testing.assert_allclose(got, expected_video[e], rtol=0, atol=TOL, err_msg=f"episode {e}")


def test_decoding_threads_change_no_bit(tmp_path_factory: pytest.TempPathFactory, video_store: Ufops) -> None:
    """Three decoding threads give the rows one gives, bit for bit: a batch is frames of one
    episode, whichever thread decoded it."""
    one = ufops.Store(video_store.data_dir)
    if not one.layers().height:
        features.compute_layer(one, ENCODER, name=LAYER, camera=CAMERA, producer=PRODUCER, progress=False)
    three = ufops.Store(ingest(tmp_path_factory, "v30_eval_video").data_dir)
    r = features.compute_layer(three, ENCODER, name=LAYER, camera=CAMERA, producer=PRODUCER, progress=False,
                               decode_threads=3, commit_every=2)
    assert (r.episodes_written, r.frames, r.stages["decode"].workers) == (8, 519, 3)
    a, b = layer_values(one, list(episode_index(one))), layer_values(three, list(episode_index(three)))
    by_e = {e: a[i] for i, e in episode_index(one).items()}
    for i, e in episode_index(three).items():
        np.testing.assert_array_equal(b[i], by_e[e], err_msg=f"episode {e}")


def test_a_fast_encoder_gets_more_decoders(tmp_path_factory: pytest.TempPathFactory) -> None:
    """An encoder that outpaces one decoder (here: no work at all) makes compute_layer start
    more decoding threads by itself; the report and the progress line say what each stage did."""
    if (os.cpu_count() or 1) < 2:
        pytest.skip("one CPU: compute_layer starts one decoding thread")
    s = ufops.Store(ingest(tmp_path_factory, "v30_eval_video").data_dir)
    r = features.compute_layer(s, lambda x: np.zeros((len(x), 4), np.float32), preprocess=lambda f: f,
                               name="features.zero", camera=CAMERA, producer=features.Producer("zero", "p", "c", "0"),
                               batch_size=8, progress=False)
    decode, encode, write = (r.stages[k] for k in features.STAGES)
    assert decode.workers >= 2 and decode.frames == encode.frames == write.frames == r.frames == 519
    assert r.bound_by == "decode", {k: v.to_dict() for k, v in r.stages.items()}


def test_ctrl_c_then_resume_leaves_the_store_as_one_run(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Ctrl-C (a real SIGINT to this process) in the middle of compute_layer: the finished
    episodes are committed, the resumed run writes the rest, and the store holds each episode
    once (the versions' episodes add up to 8) with the rows of an uninterrupted run, bit for bit."""
    import ray_encoders

    u = ingest(tmp_path_factory, "v30_eval_video")
    s = ufops.Store(u.data_dir)
    phash = s.producer_hash(PRODUCER.to_dict())

    def watch() -> None:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(s.layer_episodes(LAYER, phash)) < 2:
            time.sleep(0.02)
        os.kill(os.getpid(), signal.SIGINT)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    with pytest.raises(KeyboardInterrupt):
        features.compute_layer(s, ray_encoders.Slow(ENCODER, 0.05), name=LAYER, camera=CAMERA, producer=PRODUCER,
                               batch_size=16, commit_every=2, progress=False)
        time.sleep(30)  # the SIGINT lands in the run (a run that ended first fails the test)
    watcher.join()
    held = s.layer_episodes(LAYER, phash)
    assert 2 <= len(held) < 8
    r = features.compute_layer(s, ENCODER, name=LAYER, camera=CAMERA, producer=PRODUCER, batch_size=16,
                               progress=False)
    assert (r.episodes_written, r.episodes_skipped) == (8 - len(held), len(held))
    per_version = [int(v["message"].rsplit(" on ", 1)[1].split()[0]) for v in u.json("versions", "--json")
                   if v["kind"] == "layer"]
    assert sum(per_version) == 8, per_version

    clean = ufops.Store(ingest(tmp_path_factory, "v30_eval_video").data_dir)
    features.compute_layer(clean, ENCODER, name=LAYER, camera=CAMERA, producer=PRODUCER, batch_size=16,
                           progress=False)
    got, want = layer_values(s, list(episode_index(s))), layer_values(clean, list(episode_index(clean)))
    want_by_e = {e: want[i] for i, e in episode_index(clean).items()}
    for i, e in episode_index(s).items():
        np.testing.assert_array_equal(got[i], want_by_e[e], err_msg=f"episode {e}")
