"""Reads the files h5stream's property test wrote (tests/h5py_reads_back.rs) with h5py and
compares each with what the test meant to write: every group and dataset (dtype, shape, the
values' bytes) and every attribute (numbers: dtype, shape, bytes; strings: fixed or variable
length, charset, width, shape, values).

    python3 h5py_check.py EXPECTED.json

EXPECTED.json is a list of {"file": PATH, "seed": N, "objects": {path: description}}.
Exits non-zero with the first difference of each file that differs.
"""

import json
import sys

import h5py
import numpy as np


def attr(obj, name):
    aid = h5py.h5a.open(obj.id, name.encode("utf-8"))
    t = aid.get_type()
    shape = list(aid.shape)
    if t.get_class() == h5py.h5t.STRING:
        var = t.is_variable_str()
        utf8 = t.get_cset() == h5py.h5t.CSET_UTF8
        pad = t.get_strpad()
        want_pad = h5py.h5t.STR_NULLTERM if var else h5py.h5t.STR_NULLPAD
        assert pad == want_pad, (name, pad)
        v = obj.attrs[name]
        vals = [v] if shape == [] else list(v)
        vals = [x.decode("utf-8") if isinstance(x, bytes) else str(x) for x in vals]
        kind = ("var_" if var else "fixed_") + ("utf8" if utf8 else "ascii")
        return {"type": "str", "kind": kind, "width": None if var else t.get_size(), "shape": shape,
                "values": vals}
    a = np.asarray(obj.attrs[name])
    return {"type": "num", "dtype": a.dtype.str, "shape": list(a.shape), "hex": a.tobytes().hex()}


def describe(f):
    out = {}

    def one(path, obj):
        d = {"attrs": {k: attr(obj, k) for k in obj.attrs}}
        if isinstance(obj, h5py.Dataset):
            a = obj[()]
            a = np.asarray(a)
            d.update(kind="dataset", dtype=obj.dtype.str, shape=list(obj.shape), hex=a.tobytes().hex())
        else:
            d["kind"] = "group"
        out[path] = d

    one("/", f)
    f.visititems(lambda name, obj: one("/" + name, obj))
    return out


def first_difference(want, got):
    for p in sorted(set(want) | set(got)):
        if p not in got:
            return f"{p}: missing"
        if p not in want:
            return f"{p}: not written"
        a, b = want[p], got[p]
        for k in sorted(set(a) | set(b)):
            if k == "attrs":
                for n in sorted(set(a["attrs"]) | set(b["attrs"])):
                    if a["attrs"].get(n) != b["attrs"].get(n):
                        return f"{p}@{n}: wrote {a['attrs'].get(n)}, h5py read {b['attrs'].get(n)}"
            elif a.get(k) != b.get(k):
                return f"{p} {k}: wrote {str(a.get(k))[:200]}, h5py read {str(b.get(k))[:200]}"
    return None


def main():
    cases = json.load(open(sys.argv[1]))
    bad = 0
    objects = 0
    for c in cases:
        with h5py.File(c["file"], "r") as f:
            got = describe(f)
        diff = first_difference(c["objects"], got)
        objects += len(got)
        if diff:
            bad += 1
            print(f"seed {c['seed']}: {diff}")
    if bad:
        sys.exit(f"{bad} of {len(cases)} files differ")
    print(f"ok: {len(cases)} files, {objects} objects read back exactly")


if __name__ == "__main__":
    main()
