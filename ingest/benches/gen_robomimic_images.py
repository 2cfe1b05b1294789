#!/usr/bin/env python3
"""Write a robomimic-layout HDF5 of evaluation rollouts WITH image observations.

Layout follows robomimic's documented format (as `scripts/dataset_states_to_obs.py --camera_names
agentview robot0_eye_in_hand --camera_height 84 --camera_width 84` writes it):
data/demo_i/{obs/<key>, next_obs/<key>, actions, rewards, dones, states}, with the image
observations `obs/agentview_image` and `obs/robot0_eye_in_hand_image` as uint8 [T, 84, 84, 3];
data.attrs total/env_args, demo.attrs num_samples/model_file, mask/<key>.

Storage: like robomimic's script, datasets are contiguous and uncompressed by default; `--compress`
writes them gzip-compressed (h5py picks the chunk shape), as the script's `--compress` flag does.
`--no-next-obs` leaves next_obs out (`--exclude-next-obs`), halving the file.

Frames are smooth synthetic renders (a lit floor gradient, a moving block, sensor noise), so PNG
compresses them about as it compresses real renders, not like random bytes.
Success is a sparse reward of 1 on the last step of successful rollouts.

Used for the ingest memory figures (default `--demos 200`: about 4.7 GB). Write under target/, never git.
"""
import argparse, json
import numpy as np
import h5py

LOWDIM = {"robot0_eef_pos": 3, "robot0_eef_quat": 4, "robot0_gripper_qpos": 2, "object": 14}
CAMERAS = ["agentview_image", "robot0_eye_in_hand_image"]
H = W = 84


def frames(rng, n, cam):
    """n frames of one camera: a static lit background, a block moving across it, noise."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    base = np.stack([60 + 80 * yy / H, 70 + 60 * xx / W, 90 + 40 * (yy + xx) / (H + W)], axis=-1)
    base += rng.normal(0, 6, (H, W, 3)).astype(np.float32)  # texture
    out = np.empty((n, H, W, 3), dtype=np.uint8)
    x0, y0 = rng.uniform(10, 60, 2)
    vx, vy = rng.uniform(-0.2, 0.2, 2)
    color = rng.uniform(120, 250, 3).astype(np.float32)
    size = 14 if cam == 0 else 30
    for t in range(n):
        img = base.copy()
        x = int(np.clip(x0 + vx * t, 0, W - size))
        y = int(np.clip(y0 + vy * t, 0, H - size))
        img[y:y + size, x:x + size] = color
        img += rng.normal(0, 2, (H, W, 3)).astype(np.float32)  # sensor noise
        out[t] = np.clip(img, 0, 255)
    return out


def main():
    p = argparse.ArgumentParser()
    p.add_argument("out")
    p.add_argument("--demos", type=int, default=200)
    p.add_argument("--min-len", type=int, default=150)
    p.add_argument("--max-len", type=int, default=400)
    p.add_argument("--success-rate", type=float, default=0.6)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--compress", action="store_true", help="gzip the obs datasets (robomimic's --compress)")
    p.add_argument("--no-next-obs", action="store_true", help="leave next_obs out (robomimic's --exclude-next-obs)")
    a = p.parse_args()
    rng = np.random.default_rng(a.seed)
    kw = {"compression": "gzip"} if a.compress else {}
    names = []
    with h5py.File(a.out, "w") as f:
        data = f.create_group("data")
        total = 0
        for i in range(a.demos):
            n = int(rng.integers(a.min_len, a.max_len + 1))
            g = data.create_group(f"demo_{i}")
            success = rng.random() < a.success_rate
            obs = {k: rng.standard_normal((n + 1, d)) for k, d in LOWDIM.items()}
            for c, cam in enumerate(CAMERAS):
                obs[cam] = frames(rng, n + 1, c)
            for key, x in obs.items():
                g.create_dataset(f"obs/{key}", data=x[:-1], **kw)
                if not a.no_next_obs:
                    g.create_dataset(f"next_obs/{key}", data=x[1:], **kw)
            g.create_dataset("actions", data=rng.uniform(-1, 1, (n, 7)))
            r = np.zeros(n)
            d = np.zeros(n, dtype=np.int64)
            if success:
                r[-1] = 1.0
            d[-1] = 1
            g.create_dataset("rewards", data=r)
            g.create_dataset("dones", data=d)
            g.create_dataset("states", data=rng.standard_normal((n, 45)))
            g.attrs["num_samples"] = n
            g.attrs["model_file"] = "<mujoco model='lift'/>"
            total += n
            names.append(f"demo_{i}")
        data.attrs["total"] = total
        data.attrs["env_args"] = json.dumps({
            "env_name": "Lift", "type": 1,
            "env_kwargs": {"robots": ["Panda"], "control_freq": 20, "camera_names": ["agentview", "robot0_eye_in_hand"],
                           "camera_heights": H, "camera_widths": W, "use_camera_obs": True},
        })
        cut = int(0.9 * len(names))
        f.create_dataset("mask/train", data=np.array(names[:cut], dtype="S"))
        f.create_dataset("mask/valid", data=np.array(names[cut:], dtype="S"))


if __name__ == "__main__":
    main()
