#!/usr/bin/env python3
"""Writes a synthetic ALOHA/ACT dataset: one HDF5 file per episode, laid out as ALOHA's
recorders write them (h5py defaults, so float32 arrays and numpy-bool attributes):

    /observations/qpos   (T, 14) float32     /observations/qvel (T, 14)
    /observations/effort (T, 14)  (real robots; left out with --sim)
    /observations/images/<camera>
        raw:        (T, H, W, 3) uint8, chunked one frame per chunk
        --compress: (T, padded) uint8, each row a JPEG (quality 50) zero-padded to the longest
                    frame of the episode, with /compress_len (num_cameras, T) float32 holding
                    each frame's real length, rows in the recording's camera order
    /action (T, 14) float32
    @sim (bool), @compress (bool, with --compress), @success (bool, with --success)

Images are smooth (gradients, soft moving blobs, a little texture) so that JPEG and PNG sizes
are like a camera's, not like noise. Everything is drawn from --seed: the same arguments write
the same arrays (and, with one Pillow version, the same JPEG bytes).

    python3 scripts/gen_aloha.py OUT_DIR --episodes 3 --steps 40 --cameras 3 [--compress]
"""

import argparse
import os

import h5py
import numpy as np
from PIL import Image

# ALOHA's camera names in its recorders' order (compress_len rows follow this order, which is not
# the alphabetical order h5py lists datasets in).
CAMERAS = ["cam_high", "cam_low", "cam_left_wrist", "cam_right_wrist", "cam_extra_1", "cam_extra_2"]


def smooth_frames(rng, steps, h, w, cam):
    """(steps, h, w, 3) uint8: a colour gradient, two soft blobs moving along smooth paths and a
    low-amplitude fixed texture."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    yy /= h
    xx /= w
    base = np.stack(
        [
            0.35 + 0.3 * xx + 0.05 * cam,
            0.3 + 0.35 * yy,
            0.45 + 0.2 * (1 - xx) * yy,
        ],
        axis=-1,
    )
    texture = rng.normal(0, 1, (h // 8 + 1, w // 8 + 1, 3)).astype(np.float32)
    texture = np.kron(texture, np.ones((8, 8, 1), dtype=np.float32))[:h, :w] * 0.015
    phase = rng.uniform(0, 2 * np.pi, 4)
    colors = rng.uniform(0.1, 0.9, (2, 3)).astype(np.float32)
    out = np.empty((steps, h, w, 3), dtype=np.uint8)
    for t in range(steps):
        s = t / max(steps - 1, 1)
        img = base + texture
        for b in range(2):
            cy = float(0.5 + 0.3 * np.sin(2 * np.pi * s + phase[2 * b]))
            cx = float(0.5 + 0.3 * np.cos(2 * np.pi * s + phase[2 * b + 1]))
            # separable: exp(-(dy^2 + dx^2) / k) = exp(-dy^2 / k) * exp(-dx^2 / k)
            k = 0.015 + 0.01 * b
            a = np.exp(-((yy[:, :1] - cy) ** 2) / k) * np.exp(-((xx[:1, :] - cx) ** 2) / k)
            a = a[..., None]
            img += (colors[b] - img) * a
        np.multiply(img, 255.0, out=img)
        np.clip(img, 0, 255, out=img)
        out[t] = img
    return out


def joint_paths(rng, steps, dim=14):
    t = np.linspace(0, 1, steps, dtype=np.float64)[:, None]
    freq = rng.uniform(0.5, 2.0, dim)
    phase = rng.uniform(0, 2 * np.pi, dim)
    amp = rng.uniform(0.1, 1.0, dim)
    qpos = amp * np.sin(2 * np.pi * freq * t + phase)
    qvel = np.gradient(qpos, axis=0) * 50.0
    effort = rng.normal(0, 0.5, (steps, dim)).cumsum(axis=0) * 0.1
    action = qpos + rng.normal(0, 0.01, (steps, dim))
    return qpos, qvel, effort, action


def jpeg(frame, quality=50):
    import io

    buf = io.BytesIO()
    Image.fromarray(frame).save(buf, format="JPEG", quality=quality)
    return np.frombuffer(buf.getvalue(), dtype=np.uint8)


def write_episode(path, index, args):
    rng = np.random.default_rng([args.seed, index])
    cams = CAMERAS[: args.cameras]
    qpos, qvel, effort, action = joint_paths(rng, args.steps)
    dtype = "float64" if args.float64 else "float32"
    frames = {c: smooth_frames(rng, args.steps, args.height, args.width, k) for k, c in enumerate(cams)}
    with h5py.File(path, "w", rdcc_nbytes=1024**2 * 2) as root:
        root.attrs["sim"] = bool(args.sim)
        if args.compress:
            root.attrs["compress"] = True
        if args.success:
            root.attrs["success"] = bool(index % 3 != 1)
        obs = root.create_group("observations")
        images = obs.create_group("images")
        obs.create_dataset("qpos", data=qpos.astype(dtype))
        obs.create_dataset("qvel", data=qvel.astype(dtype))
        if not args.sim:
            obs.create_dataset("effort", data=effort.astype(dtype))
        root.create_dataset("action", data=action.astype(dtype))
        if args.compress:
            encoded = {c: [jpeg(f) for f in frames[c]] for c in cams}
            lens = np.array([[len(e) for e in encoded[c]] for c in cams])
            padded = int(lens.max())
            for c in cams:
                d = images.create_dataset(c, (args.steps, padded), dtype="uint8", chunks=(1, padded))
                buf = np.zeros((args.steps, padded), dtype=np.uint8)
                for t, e in enumerate(encoded[c]):
                    buf[t, : len(e)] = e
                d[...] = buf
            cl = root.create_dataset("compress_len", (len(cams), args.steps), dtype="float32")
            cl[...] = lens
        else:
            for c in cams:
                images.create_dataset(
                    c,
                    data=frames[c],
                    dtype="uint8",
                    chunks=(1, args.height, args.width, 3),
                )


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", help="folder to write episode_<i>.hdf5 into (created)")
    p.add_argument("--episodes", type=int, default=3)
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--cameras", type=int, default=3, choices=range(1, len(CAMERAS) + 1))
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--compress", action="store_true", help="JPEG frames padded to a fixed length")
    p.add_argument("--sim", action="store_true", help="@sim = True and no effort dataset")
    p.add_argument("--success", action="store_true", help="a @success attribute per episode")
    p.add_argument("--float64", action="store_true", help="qpos/qvel/effort/action as float64")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    os.makedirs(args.out, exist_ok=True)
    for i in range(args.episodes):
        write_episode(os.path.join(args.out, f"episode_{i}.hdf5"), i, args)


if __name__ == "__main__":
    main()
