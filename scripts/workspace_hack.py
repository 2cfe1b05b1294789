#!/usr/bin/env python3
"""Keeps `workspace-hack/Cargo.toml` true: the features the Python extension's dependencies need
so that `pip install ./clients/python` (maturin builds `-p ufops-py` alone) compiles them with the
same features as `cargo test --workspace` did, and so reuses that build instead of compiling the
dependency tree a second time (cargo resolves features per selection of packages; the stable
answer is a "workspace hack" crate, as cargo-hakari generates, and RFC 3692's
`feature-unification = "workspace"` is not stable yet).

    python3 scripts/workspace_hack.py           # rewrite workspace-hack/Cargo.toml
    python3 scripts/workspace_hack.py --check   # fail if it is stale (scripts/check.sh)

It compares two `cargo tree` resolutions — the workspace with its dev-dependencies (what
`cargo test --workspace` builds) and `ufops-py` with the features the tests' wheel is built with
— per package and per side (host: build scripts and proc-macros; target: the rest), and lists
every package of the extension's tree whose features differ, with the workspace's features, as
an optional dependency of the hack crate behind its feature `on`.
"""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path
from typing import Dict, Set, Tuple

ROOT = Path(__file__).resolve().parent.parent
HACK = ROOT / "workspace-hack" / "Cargo.toml"
PY_FEATURES = "testing,workspace-hack"
Key = Tuple[str, str, str, bool]  # (name, version, path or "", host)

LINE = re.compile(r"^(?P<prefix>(?:[│├└─ ]{4})*)(?P<body>.*)$")


def resolve(args: list[str]) -> Dict[Key, Set[str]]:
    """Features of every package unit of a `cargo tree` resolution, keyed by side."""
    out = subprocess.run(
        ["cargo", "tree", "--offline", "-f", "{p}|{f}", *args],
        cwd=ROOT, check=True, capture_output=True, text=True,
    ).stdout
    units: Dict[Key, Set[str]] = {}
    host_at: Dict[int, bool] = {}  # depth -> the node there is host-side
    section_at: Dict[int, str] = {}  # depth -> the kind of dependencies listed at that depth
    for raw in out.splitlines():
        m = LINE.match(raw)
        if not m or not m.group("body"):
            continue
        prefix, body = m.group("prefix"), m.group("body")
        depth = len(prefix) // 4
        if body.startswith("["):  # "[build-dependencies]": the kind of the children that follow
            section_at[depth + 1] = body.strip("[]")
            continue
        for d in [d for d in section_at if d > depth]:
            del section_at[d]
        pkg, _, feats = body.partition("|")
        pkg = pkg.replace("(*)", "").strip()
        proc_macro = "(proc-macro)" in pkg
        pkg = pkg.replace("(proc-macro)", "").strip()
        parts = pkg.split(" ", 2)
        name, version = parts[0], parts[1].lstrip("v")
        path = parts[2].strip("()") if len(parts) > 2 else ""
        if path.startswith("registry") or path.startswith("https://"):
            path = ""
        host = proc_macro or host_at.get(depth - 1, False) or section_at.get(depth) == "build-dependencies"
        host_at[depth] = host
        features = {f.strip() for f in feats.replace("(*)", "").split(",") if f.strip()}
        units.setdefault((name, version, path, host), set()).update(features)
    return units


def differing(workspace: Dict[Key, Set[str]]) -> Dict[Key, Set[str]]:
    """Packages of the extension's tree (with the hack as it is on disk) whose features are not
    the workspace's, with the workspace's features."""
    python = resolve(["-p", "ufops-py", "--features", PY_FEATURES, "-e", "normal,build"])
    out: Dict[Key, Set[str]] = {}
    for key, have in python.items():
        if key[0] in ("ufops-py", "workspace-hack"):
            continue
        want = workspace.get(key)
        if want is None or want == have:
            continue
        if not have <= want:
            sys.exit(f"{key[0]} {key[1]}: the extension enables features the workspace does not: {sorted(have - want)}")
        out[key] = want
    return out


def render(units: Dict[Key, Set[str]]) -> str:
    counts: Dict[str, int] = {}
    for name, _, _, _ in {(n, v, "", h) for (n, v, _, h) in units}:
        counts[name] = counts.get(name, 0) + 1
    sections = {False: [], True: []}  # type: Dict[bool, list[str]]
    names = []
    for (name, version, path, host), features in sorted(units.items()):
        alias = name if counts[name] == 1 else f"{name}-{version.replace('.', '_').replace('+', '_')}"
        names.append(alias)
        source = f'path = "../{Path(path).relative_to(ROOT)}"' if path else f'version = "{version.split("+")[0]}"'
        package = f'package = "{name}", ' if alias != name else ""
        default = "default" in features
        feats = ", ".join(f'"{f}"' for f in sorted(features - {"default"}))
        sections[host].append(
            f'{alias} = {{ {package}{source}, default-features = {str(default).lower()}, features = [{feats}], optional = true }}'
        )
    head = f"""# GENERATED by scripts/workspace_hack.py: do not edit (scripts/check.sh checks it is current).
#
# The features `cargo test --workspace` builds the Python extension's dependencies with, for the
# packages whose features differ when `ufops-py` is built alone (maturin: `-p ufops-py`). The
# tests' wheel enables `ufops-py/workspace-hack`, which turns on `on` here, so installing it
# reuses the workspace's build instead of compiling the tree again. Without `on` (every other
# build) this crate pulls in nothing.
[package]
name = "workspace-hack"
version = "0.1.0"
edition = "2021"
license = "Apache-2.0"
publish = false
description = "Feature unification for the Python extension's build (generated)"

[features]
on = [{", ".join(f'"dep:{n}"' for n in sorted(set(names)))}]

[dependencies]
"""
    body = "\n".join(sections[False]) + "\n"
    if sections[True]:
        body += "\n# Build scripts and proc-macros resolve their features apart (resolver 2).\n[build-dependencies]\n"
        body += "\n".join(sections[True]) + "\n"
    return head + body


def main() -> None:
    check = "--check" in sys.argv[1:]
    lock = ROOT / "Cargo.lock"
    before = (HACK.read_text() if HACK.exists() else "", lock.read_text())
    # From nothing: a package the hack adds may pull in others, so add until nothing differs.
    hack: Dict[Key, Set[str]] = {}
    HACK.write_text(render(hack))
    workspace = resolve(["--workspace", "-e", "normal,build,dev"])
    for _ in range(8):
        more = differing(workspace)
        if not more:
            break
        hack.update(more)
        HACK.write_text(render(hack))
    else:
        sys.exit("workspace-hack/Cargo.toml did not settle after 8 rounds")
    text = HACK.read_text()
    if check:
        HACK.write_text(before[0])
        lock.write_text(before[1])
        if text != before[0]:
            sys.exit("workspace-hack/Cargo.toml is stale: run python3 scripts/workspace_hack.py")
    print(f"workspace-hack/Cargo.toml: current ({len(hack)} packages)")


if __name__ == "__main__":
    main()
