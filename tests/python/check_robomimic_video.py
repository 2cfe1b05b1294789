"""Compares a robomimic export of cameras stored as video (`ufops ingest --images video`, lossy)
with the source file and with the export of the same file ingested with PNG cameras (lossless):

* the same groups and datasets as the PNG export, each with the same dtype and shape;
* cameras (uint8, shape (T, H, W, C): `obs/<camera>`, `next_obs/<camera>`): every frame's PSNR
  against the source file's frame at least DB; the minimum and mean are printed;
* every other dataset identical to the PNG export's, and the demos' attributes too.

    python3 check_robomimic_video.py SOURCE.hdf5 PNG_EXPORT.hdf5 VIDEO_EXPORT.hdf5 --psnr DB
"""

import argparse

import h5py
import numpy as np

from check_aloha_roundtrip import frame_psnrs, is_camera, psnr_summary


def objects(f):
    out = {}
    f.visititems(lambda name, obj: out.__setitem__(name, obj))
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("source")
    ap.add_argument("png_export")
    ap.add_argument("video_export")
    ap.add_argument("--psnr", type=float, required=True)
    args = ap.parse_args()
    with h5py.File(args.source, "r") as src, h5py.File(args.png_export, "r") as png, h5py.File(
        args.video_export, "r"
    ) as vid:
        op, ov = objects(png), objects(vid)
        assert sorted(op) == sorted(ov), (sorted(set(op) ^ set(ov)))
        psnrs, cameras, exact = [], set(), 0
        for p, x in op.items():
            y = ov[p]
            assert type(x) is type(y), p
            if isinstance(x, h5py.Dataset):
                assert x.dtype == y.dtype and x.shape == y.shape, (p, x.dtype, y.dtype, x.shape, y.shape)
                if is_camera(x):
                    # The PNG export holds the source's frames: the video's are compared with both.
                    s = src[p][()]
                    assert np.array_equal(s, x[()]), (p, "the PNG export differs from the source")
                    q = frame_psnrs(s, y[()])
                    assert q.min() >= args.psnr, (p, "frame", int(q.argmin()), float(q.min()))
                    psnrs.append(q)
                    cameras.add(p.rsplit("/", 1)[1])
                else:
                    assert np.array_equal(x[()], y[()]), p
                    exact += 1
            elif p.startswith("data/demo_"):
                assert sorted(x.attrs) == sorted(y.attrs), (p, sorted(x.attrs), sorted(y.attrs))
                for k in x.attrs:
                    assert np.array_equal(x.attrs[k], y.attrs[k]), (p, k, x.attrs[k], y.attrs[k])
        assert psnrs, "no camera compared"
        print(
            f"ok: cameras {sorted(cameras)}: {psnr_summary(psnrs)}; {exact} other datasets identical"
        )


if __name__ == "__main__":
    main()
