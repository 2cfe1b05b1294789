#!/usr/bin/env python3
"""Checks that two ALOHA exports (folders of episode_*.hdf5, or two files) read the same under
h5py: the same files; in each the same groups and datasets; every dataset's dtype, shape and
values (compared a slice of rows at a time, so a 2 GB camera needs little memory); every
attribute's value, numpy dtype and shape, and for strings the HDF5 string type too (fixed or
variable length, charset, width). NaNs compare equal to NaNs (bitwise for floats). Used to check
that a change to the writer left its output unchanged (e.g. an export by the previous binary
against one by the new one, from the same store).

    python3 scripts/aloha_exports_identical.py A B

Exits non-zero listing the differences; prints what it compared.
"""

import os
import sys

import h5py
import numpy as np

ROWS_BYTES = 64 << 20


def objects(f):
    out = {"/": f}
    f.visititems(lambda name, obj: out.__setitem__("/" + name, obj))
    return out


def attr_type(obj, name):
    t = h5py.h5a.open(obj.id, name.encode("utf-8")).get_type()
    if t.get_class() == h5py.h5t.STRING:
        var = t.is_variable_str()
        return ("string", "var" if var else t.get_size(), t.get_cset(), t.get_strpad())
    return ("other", t.get_class(), t.get_size(), t.dtype.str)


def same_values(a, b):
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    if a.dtype.kind in "fc":
        return a.tobytes() == b.tobytes() or np.array_equal(a, b, equal_nan=True)
    return np.array_equal(a, b)


def compare_dataset(x, y, where, diffs):
    if x.dtype != y.dtype or x.shape != y.shape:
        diffs.append(f"{where}: dtype/shape {x.dtype} {x.shape} vs {y.dtype} {y.shape}")
        return 0
    if x.ndim == 0 or x.shape[0] == 0:
        if not same_values(x[()], y[()]):
            diffs.append(f"{where}: values differ")
        return int(np.prod(x.shape))
    row = max(1, int(np.prod(x.shape[1:])) * x.dtype.itemsize)
    step = max(1, ROWS_BYTES // row)
    for r in range(0, x.shape[0], step):
        if not same_values(x[r : r + step], y[r : r + step]):
            diffs.append(f"{where}: values differ in rows {r}..{r + step}")
            break
    return int(np.prod(x.shape))


def compare_file(a_path, b_path, diffs):
    values = 0
    with h5py.File(a_path, "r") as a, h5py.File(b_path, "r") as b:
        oa, ob = objects(a), objects(b)
        if sorted(oa) != sorted(ob):
            diffs.append(f"{a_path}: objects {sorted(set(oa) ^ set(ob))} in one file only")
        for p in sorted(set(oa) & set(ob)):
            x, y = oa[p], ob[p]
            where = f"{os.path.basename(a_path)}:{p}"
            if type(x) is not type(y):
                diffs.append(f"{where}: {type(x).__name__} vs {type(y).__name__}")
                continue
            if isinstance(x, h5py.Dataset):
                values += compare_dataset(x, y, where, diffs)
            if sorted(x.attrs) != sorted(y.attrs):
                diffs.append(f"{where}: attributes {sorted(x.attrs)} vs {sorted(y.attrs)}")
            for k in sorted(set(x.attrs) & set(y.attrs)):
                if attr_type(x, k) != attr_type(y, k):
                    diffs.append(f"{where}@{k}: type {attr_type(x, k)} vs {attr_type(y, k)}")
                if not same_values(x.attrs[k], y.attrs[k]):
                    diffs.append(f"{where}@{k}: {x.attrs[k]!r} vs {y.attrs[k]!r}")
    return len(oa), values


def main():
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    a, b = sys.argv[1], sys.argv[2]
    if os.path.isdir(a):
        names = sorted(n for n in os.listdir(a) if n.endswith(".hdf5"))
        other = sorted(n for n in os.listdir(b) if n.endswith(".hdf5"))
        if names != other:
            sys.exit(f"different files: {names} vs {other}")
        pairs = [(os.path.join(a, n), os.path.join(b, n)) for n in names]
    else:
        pairs = [(a, b)]
    diffs = []
    objs = values = 0
    for x, y in pairs:
        o, v = compare_file(x, y, diffs)
        objs += o
        values += v
    if diffs:
        print("\n".join(diffs[:50]))
        sys.exit(f"{len(diffs)} difference(s)")
    print(f"identical: {len(pairs)} file(s), {objs} objects, {values} values, every attribute")


if __name__ == "__main__":
    main()
