"""Compares two ALOHA folders (source, ufops export) with h5py: the same episode files, and in
each the same groups, datasets (dtype, shape, every value) and attributes (value; dtype too,
except that a numpy-bool attribute may come back as int8 0/1, which hdf5-pure writes for it).
An export may add the attributes ufops writes for its labels (`success`, `verifier_score`,
`failure_cause`, `label_spans`) only where the source had none of them.

With `--psnr DB` (an export of cameras stored as video, which is lossy) the cameras, uint8
datasets of shape (T, H, W, C), are compared frame by frame instead: same dtype and shape, and
every frame's PSNR against the source's at least DB; the minimum and mean are printed.

    python3 check_aloha_roundtrip.py SOURCE_DIR EXPORT_DIR [--psnr DB]
"""

import argparse
import os

import h5py
import numpy as np

ADDED = {"success", "verifier_score", "failure_cause", "label_spans"}


def objects(f):
    out = {"/": f}
    f.visititems(lambda name, obj: out.__setitem__("/" + name, obj))
    return out


def same_attr(k, a, b, where):
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype == np.bool_ and b.dtype == np.int8:
        b = b.astype(np.bool_)
    assert a.dtype == b.dtype or (a.dtype.kind in "OSU" and b.dtype.kind in "OSU"), (where, k, a.dtype, b.dtype)
    assert a.shape == b.shape and np.array_equal(a, b), (where, k, a, b)


def is_camera(x):
    return x.dtype == np.uint8 and x.ndim == 4


def frame_psnrs(a, b):
    """Each frame's PSNR of b against a (8-bit), in dB; inf where a frame is exact."""
    a = a.reshape(a.shape[0], -1).astype(np.float64)
    b = b.reshape(b.shape[0], -1).astype(np.float64)
    mse = ((a - b) ** 2).mean(axis=1)
    with np.errstate(divide="ignore"):
        return 10 * np.log10(255.0**2 / mse)


def psnr_summary(psnrs):
    p = np.concatenate(psnrs) if psnrs else np.array([np.inf])
    finite = p[np.isfinite(p)]
    mean = finite.mean() if finite.size else np.inf
    return f"{p.size} frames, PSNR min {p.min():.2f} dB, mean {mean:.2f} dB"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("src")
    ap.add_argument("out")
    ap.add_argument("--psnr", type=float, help="compare cameras by per-frame PSNR (dB) instead of equality")
    args = ap.parse_args()
    src, out = args.src, args.out
    psnrs = []
    names = sorted(n for n in os.listdir(src) if n.endswith(".hdf5"))
    assert names == sorted(os.listdir(out)), (names, sorted(os.listdir(out)))
    values = 0
    for n in names:
        with h5py.File(os.path.join(src, n), "r") as a, h5py.File(os.path.join(out, n), "r") as b:
            oa, ob = objects(a), objects(b)
            assert sorted(oa) == sorted(ob), (n, sorted(oa), sorted(ob))
            for p, x in oa.items():
                y = ob[p]
                assert type(x) is type(y), (n, p)
                if isinstance(x, h5py.Dataset):
                    assert x.dtype == y.dtype and x.shape == y.shape, (n, p, x.dtype, y.dtype, x.shape, y.shape)
                    xa, ya = x[()], y[()]
                    if args.psnr is not None and is_camera(x):
                        q = frame_psnrs(xa, ya)
                        assert q.min() >= args.psnr, (n, p, "frame", int(q.argmin()), float(q.min()))
                        psnrs.append(q)
                    else:
                        assert np.array_equal(xa, ya), (n, p)
                    values += np.size(xa)
                ka, kb = set(x.attrs), set(y.attrs)
                extra = kb - ka
                assert ka <= kb and (p == "/" and extra <= ADDED or not extra), (n, p, ka, kb)
                for k in ka:
                    same_attr(k, x.attrs[k], y.attrs[k], f"{n}:{p}")
    if args.psnr is None:
        print(f"ok: {len(names)} episode files, {values} values identical")
    else:
        assert psnrs, "no camera compared"
        print(f"ok: {len(names)} episode files, {values} values; cameras: {psnr_summary(psnrs)}; the rest identical")


if __name__ == "__main__":
    main()
